"""Target surfaces: what the display should show.

The stimulus of the paper is a raised-cosine bump (Wang, Meng & Chen 2025, Eq. 7)::

    z(x, y) = z_f / 2 * [1 + cos(2 pi rho / l)],   rho = |(x, y) - (x_f, y_f)| <= l / 2
    z(x, y) = 0                                     otherwise

with diameter l (90 mm in the paper), height z_f and centre (x_f, y_f) anywhere. The 1D
counterpart is the same profile in x alone (rho = |x - x_f|). All lengths in millimetres.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from crs_study.errors import RenderError

#: The steepest bump (pi z_f / l, Eq. 7) any model is asked to show: far beyond what a pixel
#: display of millimetre pitch can render, and below where the arc-length quadrature's panel
#: count (one per 0.3 of slope) would overflow memory.
MAX_SLOPE = 1e4


@dataclass(frozen=True)
class Bump:
    """The raised-cosine bump of Eq. 7.

    Parameters
    ----------
    centre_mm : (x_f, y_f); y_f is ignored on a 1D (line) device: the renderer (and
        :func:`crs_study.rendering.render.render`) show rho = |x - x_f| there.
    diameter_mm : l, the bump's diameter (support), > 0.
    height_mm : z_f, the height at the centre, >= 0.
    """

    centre_mm: tuple[float, float]
    diameter_mm: float
    height_mm: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.diameter_mm) and self.diameter_mm > 0):
            raise RenderError(f"bump diameter must be > 0 mm, got {self.diameter_mm!r}")
        if not (np.isfinite(self.height_mm) and self.height_mm >= 0):
            raise RenderError(f"bump height must be >= 0 mm, got {self.height_mm!r}")
        if not all(np.isfinite(self.centre_mm)):
            raise RenderError(f"bump centre must be finite, got {self.centre_mm!r}")
        slope = math.pi * self.height_mm / self.diameter_mm  # Eq. 7's steepest slope
        if not slope <= MAX_SLOPE:
            raise RenderError(
                f"bump_height_mm = {self.height_mm!r}, bump_diameter_mm = {self.diameter_mm!r}: "
                f"the bump's steepest slope pi z_f / l = {slope:.3g} is beyond {MAX_SLOPE:g} (a "
                "diameter far below the display's pitch); expected bump_diameter_mm >= "
                f"{math.pi * self.height_mm / MAX_SLOPE:.3g} mm")

    def radius(self, xy_mm: np.ndarray) -> np.ndarray:
        """Distance rho from the centre for points (..., 2)."""
        xy = np.asarray(xy_mm, dtype=float)
        return np.hypot(xy[..., 0] - self.centre_mm[0], xy[..., 1] - self.centre_mm[1])

    def height(self, xy_mm: np.ndarray) -> np.ndarray:
        """z at points (..., 2), Eq. 7."""
        rho = self.radius(xy_mm)
        z = 0.5 * self.height_mm * (1.0 + np.cos(2.0 * np.pi * rho / self.diameter_mm))
        return np.where(rho <= 0.5 * self.diameter_mm, z, 0.0)

    def slope_along(self, xy_mm: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Directional derivative dz/ds at points (..., 2) along a unit ``direction``.

        dz/drho = -(pi z_f / l) sin(2 pi rho / l) inside the support, 0 outside;
        dz/ds = dz/drho * (p - c) . u / rho (0 at the centre, where the gradient vanishes).
        """
        xy = np.asarray(xy_mm, dtype=float)
        rho = self.radius(xy)
        l = self.diameter_mm
        dz_drho = np.where(rho <= 0.5 * l,
                           -np.pi * self.height_mm / l * np.sin(2.0 * np.pi * rho / l), 0.0)
        dx = xy[..., 0] - self.centre_mm[0]
        dy = xy[..., 1] - self.centre_mm[1]
        along = dx * direction[0] + dy * direction[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_angle = np.where(rho > 0, along / np.where(rho > 0, rho, 1.0), 0.0)
        return dz_drho * cos_angle

    def curvature_max(self) -> float:
        """Largest |z''| of the profile, at the centre: 2 pi^2 z_f / l^2 (1/mm)."""
        return 2.0 * np.pi**2 * self.height_mm / self.diameter_mm**2

    def moved_to(self, centre_mm: tuple[float, float]) -> Bump:
        return Bump((float(centre_mm[0]), float(centre_mm[1])), self.diameter_mm, self.height_mm)


#: Gauss-Legendre rule on [-1, 1] for the arc-length integral over a chord of the support. The
#: integrand is analytic on the chord (z depends on rho^2 only) but sqrt(1 + s^2) has complex
#: singularities that close in as the slope grows, so the chord is cut into one panel per
#: 0.3 of the bump's largest slope pi z_f / l: the excess length is then exact to ~1e-10 of
#: itself (tests/test_targets.py checks against scipy.integrate.quad up to slope 19).
_CHORD_NODES, _CHORD_WEIGHTS = np.polynomial.legendre.leggauss(20)
_SLOPE_PER_PANEL = 0.3


@functools.lru_cache(maxsize=64)
def _panel_rule(panels: int) -> tuple[np.ndarray, np.ndarray]:
    """Composite Gauss-Legendre on [-1, 1] with ``panels`` equal panels (nodes, weights)."""
    if panels == 1:
        return _CHORD_NODES, _CHORD_WEIGHTS
    centres = -1.0 + (2.0 * np.arange(panels) + 1.0) / panels
    nodes = (centres[:, None] + _CHORD_NODES[None, :] / panels).ravel()
    return nodes, np.tile(_CHORD_WEIGHTS / panels, panels)


def arc_excess(target: Bump, starts_mm: np.ndarray, units: np.ndarray, spans_mm: np.ndarray,
               ) -> np.ndarray:
    """Arc length minus straight length of the target along many segments at once.

    Segment k runs from ``starts_mm[k]`` along the unit vector ``units[k]`` for ``spans_mm[k]``.
    Outside the bump's support the surface is flat, so only the chord of the segment inside the
    disc rho <= l/2 contributes::

        excess = integral_chord [sqrt(1 + s^2) - 1] dt,
        s = dz/dt = -(pi z_f / l) sin(2 pi rho / l) p / rho

    with p the signed distance along the segment from the foot of the centre and
    rho = sqrt(p^2 + q^2), q the centre's offset from the line. The integrand is written
    s^2 / (1 + sqrt(1 + s^2)) (no cancellation) and integrated by Gauss-Legendre on the chord.
    """
    radius = 0.5 * target.diameter_mm
    rel = np.subtract(target.centre_mm, starts_mm)
    along = rel[:, 0] * units[:, 0] + rel[:, 1] * units[:, 1]  # foot of the centre, from start
    offset_sq = np.maximum(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] - along * along, 0.0)
    half = np.sqrt(np.maximum(radius * radius - offset_sq, 0.0))
    lo = np.minimum(np.maximum(along - half, 0.0), spans_mm)
    hi = np.minimum(np.maximum(along + half, 0.0), spans_mm)
    width = 0.5 * (hi - lo)
    slope_max = np.pi * target.height_mm / target.diameter_mm
    nodes, weights = _panel_rule(max(1, math.ceil(slope_max / _SLOPE_PER_PANEL)))
    p = (0.5 * (lo + hi) - along)[:, None] + width[:, None] * nodes
    rho = np.maximum(np.sqrt(p * p + offset_sq[:, None]), 1e-300)  # rho = 0 only where p = 0
    wavenumber = 2.0 * np.pi / target.diameter_mm
    slope = (-0.5 * target.height_mm * wavenumber) * np.sin(wavenumber * rho) * (p / rho)
    sq = slope * slope
    return width * ((sq / (1.0 + np.sqrt(1.0 + sq))) @ weights)


def arc_length(target: Bump, start_mm: tuple[float, float], end_mm: tuple[float, float],
               ) -> float:
    """Arc length of the target's section along the straight segment start->end (mm).

    L = integral_0^S sqrt(1 + (dz/ds)^2) ds = S + :func:`arc_excess` (the flat part outside the
    support adds exactly its length).
    """
    start = np.asarray(start_mm, dtype=float).reshape(1, 2)
    delta = np.asarray(end_mm, dtype=float).reshape(1, 2) - start
    span = float(np.hypot(delta[0, 0], delta[0, 1]))
    if span == 0.0:
        return 0.0
    return span + float(arc_excess(target, start, delta / span, np.array([span]))[0])
