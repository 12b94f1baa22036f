"""CRS mechanics limits: collapse (Eq. 4), beam length change, curvature and travel of a stimulus.

Units: mm and N (EI in N mm^2, the Winkler modulus beta in N/mm^2, loads in N).

* No-collapse number (Wang, Meng & Chen 2025, Eq. 4): Delta = 16 pi^4 EI / (27 beta d^4); the beam
  collapses when pressed into the skin if Delta < 1. It follows from the critical loads of
  Eq. 3, N_cr^(n) = (16 n^4 pi^4 EI + 3 beta l^4) / (4 n^2 pi^2 l^2) with l = 3 d: Delta > 1 is
  N_cr^(1) < N_cr^(3) (tests/test_quality.py checks the two agree).
* Beam length change under the first critical load: dl = N_cr^(1) L / (E A), which for
  Delta >> 1 tends to pi^2 b^2 L / (3 l^2), b the beam thickness (paper, after Eq. 4).
* Stimulus limits (paper, "additional constraints"; Supplementary Discussion 8): the beam's
  curvature must stay below the yield curvature 2 sigma_y / (E b), the pixel heights within
  travel, and the length each boundary servo feeds within its travel. The largest curvature
  of the Eq. 7 bump is 2 pi^2 z_f / l^2 (at its centre; along any beam line it is no larger).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from crs_study.display.beam_equations import no_collapse_number
from crs_study.errors import CollapseError, RenderError
from crs_study.geometry.layout import BeamSection, Layout
from crs_study.rendering.render import BeamGeometry, split_feed
from crs_study.stimuli.targets import Bump, arc_excess


def layout_delta(layout: Layout) -> float:
    """Delta of a device: its beam section, skin foundation and pixel pitch."""
    return no_collapse_number(layout.beam_section.bending_stiffness,
                              layout.foundation_stiffness, layout.pitch_mm)


def collapses(delta: float) -> bool:
    """Eq. 4: the beam collapses into the skin when Delta < 1 (Delta = 1 is the boundary)."""
    return delta < 1.0


def check_no_collapse(layout: Layout) -> float:
    """Delta of the device, or :class:`CollapseError` when it is below 1."""
    delta = layout_delta(layout)
    if collapses(delta):
        raise CollapseError(
            f"{layout.source}: Delta = 16 pi^4 EI / (27 beta d^4) = {delta:.3g} < 1 (Eq. 4) with "
            f"EI = {layout.beam_section.bending_stiffness:.4g} N mm^2, beta = "
            f"{layout.foundation_stiffness:.4g} N/mm^2, d = {layout.pitch_mm:g} mm: the beam "
            f"collapses; use a stiffer beam, a softer skin or a smaller pitch"
        )
    return delta


def critical_load(bending_stiffness: float, foundation_stiffness: float, wavelength_mm: float,
                  n: int = 1) -> float:
    """N_cr^(n) = (16 n^4 pi^4 EI + 3 beta l^4) / (4 n^2 pi^2 l^2) (N), the zero of Eq. 3's
    denominator."""
    l = wavelength_mm
    return ((16 * n**4 * math.pi**4 * bending_stiffness + 3 * foundation_stiffness * l**4)
            / (4 * n**2 * math.pi**2 * l**2))


def length_change(section: BeamSection, beam_length_mm: float, wavelength_mm: float,
                  foundation_stiffness: float = 0.0) -> float:
    """Axial shortening of the beam at the first critical load: N_cr^(1) L / (E A) (mm)."""
    load = critical_load(section.bending_stiffness, foundation_stiffness, wavelength_mm)
    return load * beam_length_mm / (section.youngs_modulus_mpa * section.area_mm2)


def length_change_thin(thickness_mm: float, beam_length_mm: float, wavelength_mm: float) -> float:
    """pi^2 b^2 L / (3 l^2): the material-free limit of :func:`length_change` for Delta >> 1."""
    return math.pi**2 * thickness_mm**2 * beam_length_mm / (3 * wavelength_mm**2)


@dataclass(frozen=True)
class StimulusLimits:
    """How a bump sits against the device's limits (mm, 1/mm)."""

    curvature: float  # 2 pi^2 z_f / l^2
    yield_curvature: float  # 2 sigma_y / (E b)
    height: float  # z_f, the highest pixel asks at most this
    travel: float
    feed: float  # the largest length one boundary servo feeds (even split)
    boundary_travel: float

    def problems(self) -> dict[str, str]:
        """The limits broken, by name (``"curvature"``, ``"height"``, ``"feed"``): what was
        asked against the limit. The protocol check (:mod:`crs_study.protocol.feasibility`)
        words its errors from these too."""
        out = {}
        if self.curvature > self.yield_curvature:
            out["curvature"] = (f"curvature {self.curvature:.4g} /mm (2 pi^2 z_f / l^2) exceeds "
                                f"the beam's yield curvature {self.yield_curvature:.4g} /mm")
        if self.height > self.travel:
            out["height"] = f"height {self.height:g} mm exceeds the pixel travel {self.travel:g} mm"
        if self.feed > self.boundary_travel:
            out["feed"] = (f"boundary feed {self.feed:.4g} mm exceeds the boundary travel "
                           f"{self.boundary_travel:g} mm")
        return out

    def violations(self) -> list[str]:
        return list(self.problems().values())

    @property
    def ok(self) -> bool:
        return not self.violations()


def stimulus_limits(layout: Layout, bump: Bump) -> StimulusLimits:
    """Curvature, height and boundary feed of ``bump`` on ``layout`` against their limits."""
    start, end = split_feed(BeamGeometry(layout).feeds(bump), layout.boundary_travel_mm)
    feed = float(max(start.max(initial=0.0), end.max(initial=0.0)))
    return StimulusLimits(bump.curvature_max(), layout.beam_section.yield_curvature_per_mm,
                          bump.height_mm, layout.travel_mm, feed, layout.boundary_travel_mm)


def check_stimulus(layout: Layout, bump: Bump) -> StimulusLimits:
    """The limits, or :class:`RenderError` naming the first one the bump breaks."""
    limits = stimulus_limits(layout, bump)
    problems = limits.violations()
    if problems:
        raise RenderError(f"{layout.source}: bump {bump!r}: {problems[0]}")
    return limits


def max_height(layout: Layout, diameter_mm: float) -> float:
    """Largest z_f of a bump of diameter l the device can show anywhere within every limit.

    min(travel, yield: kappa_y l^2 / (2 pi^2), feed: the height whose arc excess along a full
    diameter, the worst beam, equals both ends' boundary travel).
    """
    by_curvature = layout.beam_section.yield_curvature_per_mm * diameter_mm**2 / (2 * math.pi**2)
    through = np.array([[-diameter_mm, 0.0]]), np.array([[1.0, 0.0]]), np.array([2 * diameter_mm])

    def excess(height: float) -> float:
        return float(arc_excess(Bump((0.0, 0.0), diameter_mm, height), *through)[0])

    budget = 2 * layout.boundary_travel_mm
    upper = diameter_mm
    while excess(upper) < budget:
        upper *= 2
    by_feed = brentq(lambda h: excess(h) - budget, 0.0, upper, xtol=1e-9)
    return float(min(layout.travel_mm, by_curvature, by_feed))
