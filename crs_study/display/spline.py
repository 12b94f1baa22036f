"""``spline``: each beam as a clamped cubic spline through the pixel heights (no axial load).

A beam bent only by its point supports, with no axial load and no foundation, satisfies
EI y'''' = 0 between supports with y, y', y'' continuous at the pixels: a cubic spline. The ends
are at base height with zero slope at the clamps (``CubicSpline(..., bc_type="clamped")``).
This is a beam **without** boundary servos: it stays near the pixel heights and does not put a
peak where the target has one. The quick check in docs/physics.md (bump of wavelength 3 pitches
half-way between two pixels, pixel heights 0.75, target 1.0) once quoted a "spline maximum
about 0.77"; what we compute is 0.902 (published 1D device: clamps one pitch beyond the end
pixels, pixels 0, 0.75, 0.75, 0, 0). No interpolating cubic spline gives 0.77: natural or
not-a-knot ends at the end pixels 0.88 / 0.87, clamps 0.5-2 pitches out 0.89-0.91, four pixels
clamped at the outer two 0.94, an infinite lattice 0.9007 (scipy ``CubicSpline``;
tests/test_display_spline.py). Only an unloaded beam on a stiff skin foundation comes down to
it (beta ~ 3 kPa, Delta ~ 1.5, and its maximum then sits near a pixel). It is not a model of
the CRS condition; use ``beam`` for that. In 2D the splines form the same network, joined by
the same fabric, as the compressed beams (:mod:`crs_study.display.network`).

Yield: the curvature kappa = |y''| / (1 + y'^2)^(3/2) is at most |y''|, and |y''| of a cubic
spline is largest at a knot (y'' is linear on each segment), so the check against the yield
curvature 2 sigma_y / (E t) compares the largest knot |y''| with it: a bound, never an
underestimate (kappa at the knots alone could miss an interior maximum where the slope is
smaller). The bound is tight to the slope factor, under 5 % for slopes below 0.18 (a 5 mm
bump of 90 mm diameter has at most pi z_f / l = 0.17).
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
)
from crs_study.geometry.layout import Layout

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(12)  # sqrt(1 + y'^2), y' quadratic


def spline_arc_length(spline: CubicSpline) -> float:
    """Arc length integral sqrt(1 + y'^2) ds, 12-point Gauss-Legendre on each knot interval."""
    x = spline.x
    half = 0.5 * np.diff(x)
    s = (0.5 * (x[1:] + x[:-1]))[:, None] + half[:, None] * _GL_NODES[None, :]
    return float(np.sum(half[:, None] * _GL_WEIGHTS * np.sqrt(1.0 + spline(s, 1) ** 2)))


@register
class SplineModel(NetworkModel):
    """Clamped cubic spline per beam through the pixel heights; fabric between beams in 2D.

    The knot slopes of a clamped spline are linear in the knot heights, so the map from pixel
    heights to knot slopes is taken from scipy's ``CubicSpline`` once per beam (on unit
    heights); a frame is then one small product and a vectorised cubic Hermite evaluation
    (no spline objects per frame).
    """

    name = "spline"
    description = "beam without axial load: clamped cubic spline through the pixels"

    def __init__(self, layout: Layout, check_yield_curvature: bool = True, **options) -> None:
        super().__init__(layout, **options)
        self.supports = [beam_support_positions(layout, b) for b in layout.beams]
        self.pixels = [list(b.pixels) for b in layout.beams]
        self.check_yield_curvature = check_yield_curvature
        n_beams = len(self.supports)
        p = max(len(s) for s in self.supports) - 1  # segments
        self.n_segments = np.array([len(s) - 1 for s in self.supports])
        self.knots = np.zeros((n_beams, p + 1))
        self.pixel_map = np.zeros((n_beams, p + 1), dtype=int)
        self.pixel_mask = np.zeros((n_beams, p + 1))
        self.slope_map = np.zeros((n_beams, p + 1, p + 1))  # knot heights -> knot slopes
        for b, (s, pixels) in enumerate(zip(self.supports, self.pixels, strict=True)):
            n = len(s)
            self.knots[b, :n] = s
            self.knots[b, n:] = s[-1]
            self.pixel_map[b, 1:n - 1] = pixels
            self.pixel_mask[b, 1:n - 1] = 1.0
            unit = CubicSpline(s, np.eye(n), bc_type="clamped", axis=0)
            self.slope_map[b, :n, :n] = unit(s, 1)
        self.seg_start = self.knots[:, :-1]
        self.seg_length = np.diff(self.knots, axis=1)
        half = 0.5 * self.seg_length
        self.gl_t = (half[:, :, None] * (_GL_NODES + 1.0)).reshape(n_beams, -1)
        self.gl_w = (half[:, :, None] * _GL_WEIGHTS).reshape(n_beams, -1)
        self.gl_seg = np.repeat(np.arange(p), len(_GL_NODES))
        self.start_servo = np.array([b.start_servo for b in layout.beams], dtype=int)
        self.end_servo = np.array([b.end_servo for b in layout.beams], dtype=int)

    def splines(self, setpoints_mm: np.ndarray) -> list[CubicSpline]:
        """scipy CubicSpline objects of the beams (for inspection; the model does not use them)."""
        setpoints = check_setpoints(self.layout, setpoints_mm, self.name)
        return [CubicSpline(s, np.concatenate([[0.0], setpoints[pixels], [0.0]]),
                            bc_type="clamped")
                for s, pixels in zip(self.supports, self.pixels, strict=True)]

    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        setpoints = check_setpoints(self.layout, setpoints_mm, self.name)
        y = setpoints[self.pixel_map] * self.pixel_mask  # knot heights (B, P + 1)
        m = np.matmul(self.slope_map, y[:, :, None])[..., 0]  # knot slopes
        ell = np.where(self.seg_length > 0.0, self.seg_length, 1.0)
        rise = np.diff(y, axis=1) / ell  # (B, P)
        # y'' at the left and right end of each segment (cubic Hermite)
        left = (6.0 * rise - 4.0 * m[:, :-1] - 2.0 * m[:, 1:]) / ell
        right = (-6.0 * rise + 2.0 * m[:, :-1] + 4.0 * m[:, 1:]) / ell
        real = self.seg_length > 0.0
        if self.check_yield_curvature:  # |y''| bounds the curvature; largest at a knot
            worst = (np.maximum(np.abs(left), np.abs(right)) * real).max(axis=1)
            b = int(np.argmax(worst))
            check_yield(self.name, b, float(worst[b]), self.layout)
        # slope on a segment: m0 + left t + (right - left) t^2 / (2 l)
        t = self.gl_t
        seg = self.gl_seg
        slope = (m[:, seg] + left[:, seg] * t
                 + (right - left)[:, seg] * t * t / (2.0 * ell[:, seg]))
        lengths = np.sum(self.gl_w * np.sqrt(1.0 + slope**2), axis=-1)
        def evaluate_prepared(query: tuple[np.ndarray, ...]) -> np.ndarray:
            beam, k, w = query
            return (w[0] * y[beam, k] + w[1] * m[beam, k] + w[2] * y[beam, k + 1]
                    + w[3] * m[beam, k + 1])

        def evaluate(beam: np.ndarray, s: np.ndarray) -> np.ndarray:
            return evaluate_prepared(self._prepare(beam, s))

        return BeamProfiles(
            spans_mm=self.spans, evaluate=evaluate,
            axial_load_n=np.zeros(len(self.supports)),
            critical_load_n=np.full(len(self.supports), np.inf),
            commanded_length_mm=self.spans + setpoints[self.start_servo]
            + setpoints[self.end_servo],
            length_mm=lengths,
            prepare=self._prepare, evaluate_prepared=evaluate_prepared, geometry=self,
        )

    def _prepare(self, beam: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
        """Segment and cubic Hermite weights of points (beam, s): frame-independent."""
        k = np.sum(s[:, None] >= self.knots[beam, :-1], axis=1) - 1
        k = np.clip(k, 0, self.n_segments[beam] - 1)
        h = self.seg_length[beam, k]
        x = (s - self.knots[beam, k]) / np.where(h > 0.0, h, 1.0)
        x2 = x * x
        x3 = x2 * x
        return beam, k, np.stack([2 * x3 - 3 * x2 + 1, (x3 - 2 * x2 + x) * h,
                                  3 * x2 - 2 * x3, (x3 - x2) * h])
