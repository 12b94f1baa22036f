"""The raised-cosine bump's setpoints, per frame, with the layout's constants taken out.

:class:`BumpPath` computes what the ``pixel-only`` and ``crs`` conditions of
:mod:`crs_study.rendering.render` compute for a :class:`~crs_study.stimuli.targets.Bump`,
within rounding, with fewer and cheaper steps: the live link renders one frame per packet on
the real clock (software time per packet must stay under 1 % of the frame's wire time), and a
session's stimuli are rendered frame by frame too.

Why it is faster (measured: ``crs-study bench render`` and ``crs-study bench live``)
    The general path builds a :class:`Bump`, samples it through :meth:`Bump.height` and
    integrates the arc excess with :func:`~crs_study.stimuli.targets.arc_excess`, each
    checking and converting its inputs: about 40 numpy calls a 2D CRS frame with the feed cap,
    nearly all on arrays of 9 to 19 numbers, where a call's fixed cost is the whole cost. Here
    the pixel positions, the beam lines and their actuator indices are unpacked once per
    layout; the pixel heights (19 cosines) and the per-beam scalars of the chord (foot of the
    centre, half chord, clipped ends) are plain float arithmetic; numpy runs only on the
    chord's quadrature nodes (9 calls) and the feed cap's products
    (:mod:`~crs_study.rendering.feed_cap`, 5 calls). The live loop sleeps between frames while
    the machine's other processes run, and meets every numpy call with cold caches: on the
    shared 2-core machine a frame took 370 us after a 29 ms pause against 60-100 us back to
    back, the general path 510 us against 80-150 (thread CPU time, medians of 80 frames of a
    finger writing 9, three runs); fewer distinct calls is what counts there.

Within rounding, not to the last bit
    The pixel heights use Python's ``math`` (cos, hypot) where the general path uses numpy's
    (their last bits may differ), and the chord's integrand is written as
    ``c hypot(t, 1/c) - 1`` (:meth:`BumpPath._feeds`). tests/test_render_bump_path.py holds
    both paths within 1e-10 mm of each other and of the renderer before this module (4e-14 mm
    measured), seven orders of magnitude below a pulse quantum (0.009 mm), with the same clip
    and cap messages.
"""

from __future__ import annotations

import math

import numpy as np

from crs_study.geometry.layout import Layout
from crs_study.stimuli.targets import _SLOPE_PER_PANEL, _panel_rule

_TWO_PI = 2.0 * math.pi
#: rho's floor (mm): hypot(p, q) > 0 where p = q = 0 (the integrand is 0 there)
_LEAST_OFFSET_MM = 1e-300
#: below this steepest slope 1 / c overflows and the excess is below 1e-290 mm: 0
_LEAST_AMPLITUDE = 1e-150


class BumpPath:
    """Setpoints of the ``pixel-only`` or ``crs`` condition for a bump, before limits.

    Build once per layout. :meth:`parts` gives the pixel heights and each beam's start and
    end feed as Python floats (the limits work on those); :meth:`setpoints` puts them into a
    vector in actuator order.
    """

    def __init__(self, layout: Layout, crs: bool) -> None:
        self.crs = crs
        self.n_actuators = layout.n_actuators
        self.n_pixels = layout.n_pixels
        self._pixels = tuple((float(x), float(y)) for x, y in np.asarray(layout.pixel_xy,
                                                                          dtype=float).tolist())
        self._boundary_travel = float(layout.boundary_travel_mm)
        lines = []
        for beam in layout.beams:
            sx, sy = float(beam.start[0]), float(beam.start[1])
            dx, dy = float(beam.end[0]) - sx, float(beam.end[1]) - sy
            straight = float(np.hypot(dx, dy))  # as BeamGeometry: np.hypot of the difference
            scale = straight if straight > 0 else 1.0
            lines.append((sx, sy, dx / scale, dy / scale, straight))
        self._lines = tuple(lines)
        self._servos = tuple((b.start_servo, b.end_servo) for b in layout.beams)
        self._rest = [0.0] * (self.n_actuators - self.n_pixels)
        self._rules: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}

    def parts(self, cx: float, cy: float, diameter: float, height: float
              ) -> tuple[list[float], list[float], list[float]]:
        """``(pixel heights, start feeds, end feeds)`` (mm) of a bump centred at (cx, cy)
        (layout frame, mm), Eq. 7.

        Pixel heights ``z_f / 2 [1 + cos(2 pi rho / l)]`` inside the support, 0 outside (as
        :meth:`Bump.height`, in Python floats: 19 pixels cost less so than as numpy calls);
        with ``crs`` each beam's feed, the arc excess of
        :func:`~crs_study.stimuli.targets.arc_excess` split by
        :func:`~crs_study.rendering.render.split_feed`; without, no feeds (empty lists).
        """
        half, radius = 0.5 * height, 0.5 * diameter
        heights = []
        for x, y in self._pixels:
            rho = math.hypot(x - cx, y - cy)
            heights.append(half * (1.0 + math.cos(_TWO_PI * rho / diameter)) if rho <= radius
                           else 0.0)
        if not (self.crs and self._lines):
            return heights, [], []
        travel = self._boundary_travel
        starts, ends = [], []
        for total in self._feeds(cx, cy, diameter, height):
            start = min(0.5 * total, travel)
            starts.append(start)
            ends.append(total - start)
        return heights, starts, ends

    def setpoints(self, heights: list[float], starts: list[float], ends: list[float]
                  ) -> np.ndarray:
        """:meth:`parts` as a setpoint vector (actuator order; feeds 0 where none)."""
        values = heights + self._rest
        # no feeds (pixel-only): every boundary servo at rest
        for (start_servo, end_servo), start, end in zip(self._servos, starts, ends,
                                                        strict=False):
            values[start_servo] = start
            values[end_servo] = end
        return np.array(values)

    def _rule(self, panels: int) -> tuple[np.ndarray, np.ndarray, float]:
        """The chord's quadrature rule for ``panels`` panels: nodes as a column, weights, and
        the weights' sum (cached per rule)."""
        rule = self._rules.get(panels)
        if rule is None:
            nodes, weights = _panel_rule(panels)
            rule = self._rules[panels] = (np.ascontiguousarray(nodes[:, None]),
                                          np.ascontiguousarray(weights), float(weights.sum()))
        return rule

    def _feeds(self, cx: float, cy: float, diameter: float, height: float) -> list[float]:
        """Arc excess along every beam line: :func:`~crs_study.stimuli.targets.arc_excess`'s
        chord and quadrature (its docstring has the formula), with the integrand as

            sqrt(1 + s^2) - 1 = c hypot(t, 1/c) - 1,   s = c t,  c = pi z_f / l,
            t = sin(2 pi rho / l) p / rho,             rho = hypot(p, q),

        so that sum_n w_n [...] = c sum_n w_n hypot(t_n, 1/c) - sum_n w_n: 9 numpy calls
        (against 19), the last subtraction in floats per beam. The cancellation costs
        ~1e-15 of the chord's length (tests/test_render_bump_path.py's tolerance)."""
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
            # the centre's distance from the line, > 0 so that rho = 0 nowhere
            offsets.append(max(math.sqrt(offset_sq), _LEAST_OFFSET_MM))
        amplitude = math.pi * height / diameter  # c, the steepest slope
        if not amplitude > _LEAST_AMPLITUDE or not any(widths):
            return [0.0] * len(widths)  # no slope or no chord: no excess (below 1e-290 mm)
        nodes, weights, weight_sum = self._rule(max(1, math.ceil(amplitude / _SLOPE_PER_PANEL)))
        width_row, mid_row, offset_row = np.array((widths, mids, offsets))
        p = nodes * width_row  # (nodes, beams): signed distance from the foot of the centre
        p += mid_row
        rho = np.hypot(p, offset_row)
        phase = rho * (_TWO_PI / diameter)
        np.sin(phase, out=phase)
        phase *= p
        phase /= rho  # t
        np.hypot(phase, 1.0 / amplitude, out=phase)
        sums = (weights @ phase).tolist()
        return [width * (amplitude * total - weight_sum)
                for width, total in zip(widths, sums, strict=True)]
