"""``spline``: each beam as a clamped cubic spline through the pixel heights (no axial load).

A beam bent only by its point supports, with no axial load and no foundation, satisfies
EI y'''' = 0 between supports with y, y', y'' continuous at the pixels: a cubic spline. The ends
are at base height with zero slope at the clamps (``CubicSpline(..., bc_type="clamped")``).
This is a beam **without** boundary servos: it stays near the pixel heights and does not put a
peak between two pixels (DESIGN.md: bump of wavelength 3 pitches half-way between two pixels,
pixel heights 0.75, spline maximum about 0.77). It is not a model of the CRS condition; use
``beam`` for that. In 2D the splines form the same network, joined by the same fabric, as the
compressed beams (:mod:`crs_study.display.network`).

Yield: the curvature of a cubic spline is largest at a knot (y'' is piecewise linear), so the
check against the yield curvature 2 sigma_y / (E t) looks at the knots only.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from crs_study.display.base import register
from crs_study.display.network import (
    BeamProfiles,
    NetworkModel,
    beam_support_positions,
    check_setpoints,
    check_yield,
    commanded_lengths,
)
from crs_study.layout import Layout

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(12)


def spline_arc_length(spline: CubicSpline) -> float:
    """Arc length integral sqrt(1 + y'^2) ds, 12-point Gauss-Legendre on each knot interval."""
    x = spline.x
    half = 0.5 * np.diff(x)
    s = (0.5 * (x[1:] + x[:-1]))[:, None] + half[:, None] * _GL_NODES[None, :]
    return float(np.sum(half[:, None] * _GL_WEIGHTS * np.sqrt(1.0 + spline(s, 1) ** 2)))


@register
class SplineModel(NetworkModel):
    """Clamped cubic spline per beam through the pixel heights; fabric between beams in 2D."""

    name = "spline"
    description = "beam without axial load: clamped cubic spline through the pixels"

    def __init__(self, layout: Layout, check_yield_curvature: bool = True, **options) -> None:
        super().__init__(layout, **options)
        self.supports = [beam_support_positions(layout, b) for b in layout.beams]
        self.pixels = [list(b.pixels) for b in layout.beams]
        self.check_yield_curvature = check_yield_curvature

    def splines(self, setpoints_mm: np.ndarray) -> list[CubicSpline]:
        setpoints = check_setpoints(self.layout, setpoints_mm, self.name)
        out = []
        for b, (s, pixels) in enumerate(zip(self.supports, self.pixels, strict=True)):
            heights = np.concatenate([[0.0], setpoints[pixels], [0.0]])
            spline = CubicSpline(s, heights, bc_type="clamped")
            if self.check_yield_curvature:
                y2 = spline(s, 2)
                y1 = spline(s, 1)
                check_yield(self.name, b, float(np.max(np.abs(y2) / (1 + y1**2) ** 1.5)),
                            self.layout)
            out.append(spline)
        return out

    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        splines = self.splines(setpoints_mm)

        def evaluate(beam: np.ndarray, s: np.ndarray) -> np.ndarray:
            out = np.empty(s.shape)
            for b in np.unique(beam):
                mask = beam == b
                out[mask] = splines[b](s[mask])
            return out

        return BeamProfiles(
            spans_mm=self.spans, evaluate=evaluate,
            axial_load_n=np.zeros(len(splines)),
            critical_load_n=np.full(len(splines), np.inf),
            commanded_length_mm=commanded_lengths(self.layout, np.asarray(setpoints_mm, float)),
            length_mm=np.array([spline_arc_length(sp) for sp in splines]),
        )
