"""The raised-cosine bump's setpoints, per frame, with the layout's constants taken out.

:class:`BumpPath` computes what the ``pixel-only`` and ``crs`` conditions of
:mod:`crs_study.rendering.render` compute for a :class:`~crs_study.stimuli.targets.Bump`, to
the last bit, with fewer and cheaper steps: the live link renders one frame per packet on the
real clock (issue 18: software time per packet under 1 % of the frame's wire time), and a
session's stimuli are rendered frame by frame too.

Why it is faster (measured: ``crs-study bench render`` and ``crs-study bench live``)
    The general path builds a :class:`Bump`, samples it through :meth:`Bump.height` and
    integrates the arc excess with :func:`~crs_study.stimuli.targets.arc_excess`, each
    checking and converting its inputs: about 75 numpy calls a 2D CRS frame, nearly all on
    arrays of 9 to 19 numbers, where a call's fixed cost is the whole cost. Here the pixel
    positions, the beam lines and their actuator indices are unpacked once per layout; the
    per-beam scalars of the chord (foot of the centre, half chord, clipped ends) are plain
    float arithmetic (9 beams); numpy runs only where the arrays are long (the pixels' cosine,
    the chord's quadrature nodes): about 25 calls. A live loop that sleeps between frames on a
    loaded machine meets every call with cold caches, so fewer distinct calls is what counts.

Why to the last bit
    Every operation is the general path's, in its order, on the same values: the IEEE 754
    operations +, -, *, /, sqrt, min and max round identically in Python and numpy, and the
    transcendental ones (cos, sin, hypot) stay numpy calls on the same arrays. So a frame
    rendered here is the frame the general path renders, and switching paths changes no
    stored frame log (tests/test_render_bump_path.py compares both over random bumps).
"""

from __future__ import annotations

import math

import numpy as np

from crs_study.geometry.layout import Layout
from crs_study.stimuli.targets import _SLOPE_PER_PANEL, _panel_rule

_TWO_PI = 2.0 * np.pi


class BumpPath:
    """Setpoints of the ``pixel-only`` or ``crs`` condition for a bump, before limits.

    Build once per layout. :meth:`setpoints` returns a new vector (actuator order) and leaves
    each beam's start and end feed in :attr:`starts` and :attr:`ends` (floats, beam order)
    for the limits.
    """

    def __init__(self, layout: Layout, crs: bool) -> None:
        self.crs = crs
        self.n_actuators = layout.n_actuators
        self.n_pixels = layout.n_pixels
        xy = np.asarray(layout.pixel_xy, dtype=float)
        self._px = np.ascontiguousarray(xy[:, 0])
        self._py = np.ascontiguousarray(xy[:, 1])
        self._boundary_travel = float(layout.boundary_travel_mm)
        lines = []
        for beam in layout.beams:
            sx, sy = float(beam.start[0]), float(beam.start[1])
            dx, dy = float(beam.end[0]) - sx, float(beam.end[1]) - sy
            straight = float(np.hypot(dx, dy))  # as BeamGeometry: np.hypot of the difference
            scale = straight if straight > 0 else 1.0
            lines.append((sx, sy, dx / scale, dy / scale, straight))
        self._lines = tuple(lines)
        self._start_servo = np.array([b.start_servo for b in layout.beams], dtype=np.intp)
        self._end_servo = np.array([b.end_servo for b in layout.beams], dtype=np.intp)
        #: each beam's start and end feed in the last :meth:`setpoints` (empty: no feeds)
        self.starts: list[float] = []
        self.ends: list[float] = []

    def setpoints(self, cx: float, cy: float, diameter: float, height: float) -> np.ndarray:
        """Raw setpoints (mm) of a bump centred at (cx, cy) (layout frame, mm), Eq. 7.

        Pixel heights ``z_f / 2 [1 + cos(2 pi rho / l)]`` inside the support, 0 outside (as
        :meth:`Bump.height`); with ``crs`` each beam's feed, the arc excess of
        :func:`~crs_study.stimuli.targets.arc_excess` split by
        :func:`~crs_study.rendering.render.split_feed`.
        """
        out = np.zeros(self.n_actuators)
        z = out[: self.n_pixels]
        rho = np.hypot(self._px - cx, self._py - cy)
        np.multiply(rho, _TWO_PI, out=z)
        z /= diameter
        np.cos(z, out=z)
        z += 1.0
        z *= 0.5 * height
        z[rho > 0.5 * diameter] = 0.0
        if self.crs and self._lines:
            totals = self._feeds(cx, cy, diameter, height)
            travel = self._boundary_travel
            self.starts = starts = [min(0.5 * t, travel) for t in totals]
            self.ends = ends = [t - s for t, s in zip(totals, starts, strict=True)]
            out[self._start_servo] = starts
            out[self._end_servo] = ends
        return out

    def _feeds(self, cx: float, cy: float, diameter: float, height: float) -> list[float]:
        """Arc excess along every beam line (:func:`~crs_study.stimuli.targets.arc_excess`,
        operation for operation: its docstring has the formula)."""
        radius = 0.5 * diameter
        radius_sq = radius * radius
        mids, widths, offsets = [], [], []
        for sx, sy, ux, uy, span in self._lines:
            rx = cx - sx
            ry = cy - sy
            along = rx * ux + ry * uy
            offset_sq = rx * rx + ry * ry - along * along
            if not offset_sq >= 0.0:  # np.maximum(., 0.0), NaN aside
                offset_sq = 0.0
            reach = radius_sq - offset_sq
            half = math.sqrt(reach) if reach >= 0.0 else 0.0
            lo = along - half
            lo = (lo if lo < span else span) if lo >= 0.0 else 0.0
            hi = along + half
            hi = (hi if hi < span else span) if hi >= 0.0 else 0.0
            widths.append(0.5 * (hi - lo))
            mids.append(0.5 * (lo + hi) - along)
            offsets.append(offset_sq)
        if height == 0.0 or not any(widths):
            return [0.0] * len(widths)  # what the integral gives: slope 0 or no chord
        nodes, weights = _panel_rule(max(1, math.ceil(np.pi * height / diameter
                                                      / _SLOPE_PER_PANEL)))
        columns = np.array((widths, mids, offsets))[:, :, None]  # (3, beams, 1)
        width_col = columns[0]
        p = width_col * nodes
        p += columns[1]
        rho = p * p
        rho += columns[2]
        np.sqrt(rho, out=rho)
        np.maximum(rho, 1e-300, out=rho)  # rho = 0 only where p = 0
        wavenumber = _TWO_PI / diameter
        slope = np.sin(wavenumber * rho)
        slope *= (-0.5 * height * wavenumber)
        p /= rho
        slope *= p
        slope *= slope
        root = 1.0 + slope
        np.sqrt(root, out=root)
        root += 1.0
        slope /= root
        return (columns[0, :, 0] * (slope @ weights)).tolist()
