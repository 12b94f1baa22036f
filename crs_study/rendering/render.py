"""Renderer: a target surface to actuator setpoints, per experimental condition.

Setpoint vectors follow :class:`~crs_study.geometry.Layout` actuator order: pixel heights above
base (mm), then for each beam the length fed into the display by its start and end boundary
servos (mm, >= 0).

Conditions are :class:`~crs_study.rendering.conditions.Condition` objects registered by name
(:data:`CONDITIONS`); each carries its strategy. The two shipped:

``pixel-only``
    pixel heights sampled from the target, every boundary servo at neutral (0 mm).
``crs``
    the same pixel heights, and for each beam the compression that makes the beam's length in
    the display equal to the target's arc length along the beam's line between its clamps
    (Wang, Meng & Chen 2025, Supplementary Discussion 7; docs/physics.md)::

        feed = L_target - L_straight,   L_target = integral sqrt(1 + (dz/ds)^2) ds

Split rule: each end feeds half of ``feed``. When half exceeds one end's boundary travel, that
end feeds its full travel and the other end takes the rest, so the parts always sum to the whole
while the whole fits in the two ends' travel. The beam's shape does not depend on the split
(both clamps sit at base height and fixed positions); the even split halves the distance each
servo moves and therefore the time a change takes.

Feed cap (``cap_feed=True``, the default): a beam cannot be made longer than its longest
stable shape through the commanded pixel heights, the one at the solver's margin of the
critical load (0.98 N_cr, beam without foundation: the display as shown). Beyond it the real
beam would buckle into a mode its pixels do not control (Eq. 3: the denominator vanishes at
N_cr), and the ``beam`` model raises :class:`~crs_study.errors.CollapseError`. The feed rule
asks for that in two ways: a bump crossing a beam's line between pixels (or between the last
pixel and a clamp) while every pixel of the beam is at base (the beam can then only take the
steel's elastic shortening, ~N_cr S / EA, a few micrometres), and tall bumps whose arc length
exceeds what the pixel heights can guide. So the total feed of each beam is capped at
:meth:`~crs_study.display.beam.CompressedBeams.longest_feeds` (the beam then shows its longest
stable shape) and the cap is reported in :attr:`Rendering.clamped` like any clip, or raised
under ``policy="error"``. By default (``wire``) the cap also leaves room for what the boards
hold instead of the setpoints (whole-us pulses, the write policy's dead-band), so that the
pulses they keep never collapse a beam either (:mod:`~crs_study.rendering.feed_cap`).
Measured (``crs-study`` at commit of this change, before the wire's room): the shipped digit
stimuli need no cap (0 of 537 frames); bump centres uniform in the 2D pixel hull need it in
0/3000 frames at z_f = 1 mm and 35/3000 at 5 mm; centres beyond the hull, where the flat-beam
case lives, in ~23 %. ``cap_feed=False`` keeps the paper's rule unchanged (the quality
criteria evaluate that rule and report the points where it collapses).

Clamp policy: a setpoint outside its actuator's range (pixel 0..travel, boundary
0..boundary travel) is clipped to the range and reported in :attr:`Rendering.clamped`, or,
with ``policy="error"``, raised as :class:`~crs_study.errors.RenderError`. Nothing beyond range
is ever passed on silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crs_study.display.beam import CompressedBeams
from crs_study.errors import RenderError
from crs_study.geometry.layout import Layout
from crs_study.rendering.bump_path import BumpPath
from crs_study.rendering.conditions import (  # noqa: F401  (CONDITIONS: re-exported)
    CONDITIONS,
    Condition,
    get_condition,
    register_condition,
)
from crs_study.rendering.feed_cap import DEFAULT_WIRE, FeedCap, WireSlack
from crs_study.stimuli.targets import Bump, arc_excess

ClampPolicy = Literal["clip", "error"]


@dataclass(frozen=True)
class Rendering:
    """Setpoints for one frame and what had to be clipped to reach them."""

    setpoints: np.ndarray  # (n_actuators,) mm
    clamped: tuple[str, ...]  # one message per clipped actuator, empty when nothing was


class BeamGeometry:
    """Every beam line of a layout as arrays, precomputed once, for vectorised arc lengths."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        self.starts = np.array([b.start for b in layout.beams], dtype=float).reshape(-1, 2)
        ends = np.array([b.end for b in layout.beams], dtype=float).reshape(-1, 2)
        self.straight = np.hypot(*(ends - self.starts).T)
        self.units = (ends - self.starts) / np.where(self.straight > 0, self.straight, 1.0)[:, None]
        self.start_servo = np.array([b.start_servo for b in layout.beams], dtype=int)
        self.end_servo = np.array([b.end_servo for b in layout.beams], dtype=int)

    def feeds(self, target: Bump) -> np.ndarray:
        """Target arc length minus straight length along each beam line between its clamps."""
        return arc_excess(target, self.starts, self.units, self.straight)

    def arc_lengths(self, target: Bump) -> np.ndarray:
        """Target arc length along each beam line between its clamps (mm)."""
        return self.straight + self.feeds(target)


def split_feed(total_mm: np.ndarray, end_travel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Split each beam's total feed between its start and end servo (module docstring).

    Returns (start, end) with start + end == total whenever total <= 2 * end_travel.
    """
    total = np.asarray(total_mm, dtype=float)
    start = np.minimum(0.5 * total, end_travel_mm)
    end = total - start
    return start, end


def pixel_heights(layout: Layout, target: Bump) -> np.ndarray:
    return target.height(layout.pixel_xy)


def render_pixel_only(layout: Layout, target: Bump, geometry: BeamGeometry | None = None
                      ) -> np.ndarray:
    setpoints = np.zeros(layout.n_actuators)
    setpoints[: layout.n_pixels] = pixel_heights(layout, target)
    return setpoints


def render_crs(layout: Layout, target: Bump, geometry: BeamGeometry | None = None
               ) -> np.ndarray:
    geometry = geometry or BeamGeometry(layout)
    setpoints = render_pixel_only(layout, target)
    start, end = split_feed(geometry.feeds(target), layout.boundary_travel_mm)
    setpoints[geometry.start_servo] = start
    setpoints[geometry.end_servo] = end
    return setpoints


register_condition(Condition(
    "pixel-only", render_pixel_only, drives_beams=False, display_model="linear",
    fast_path=True, description="the pixels alone under the fabric sewn to their tips"))
register_condition(Condition(
    "crs", render_crs, drives_beams=True, display_model="beam", fast_path=True,
    description="the continuity reinforcement skeleton: compressed beams guided by the "
                "pixels"))


class Renderer:
    """Renders targets for one layout and condition, reusing precomputed beam geometry.

    ``wire``: what the boards may hold instead of a setpoint (whole-us pulses, the write
    policy's dead-band), which the feed cap leaves room for (:mod:`~crs_study.rendering.
    feed_cap`); ``None``: the setpoints reach the beams exactly (the cap is then the longest
    stable shape itself). A :class:`Bump` under a condition with a ``fast_path`` takes the
    fast path of :mod:`~crs_study.rendering.bump_path` (the same setpoints within 1e-10 mm).
    """

    def __init__(self, layout: Layout, condition: str, policy: ClampPolicy = "clip",
                 cap_feed: bool = True, wire: WireSlack | None = DEFAULT_WIRE) -> None:
        meaning = get_condition(condition)
        if policy not in ("clip", "error"):
            raise RenderError(f"unknown clamp policy {policy!r}; known: clip, error")
        self.layout = layout
        self.condition = condition
        self.policy = policy
        self._func = meaning.render
        self._geometry = BeamGeometry(layout)
        self._upper = np.array([a.calibration.travel_mm for a in layout.actuators])
        self.cap_feed = cap_feed
        self.wire = wire if cap_feed else None
        self._cap = FeedCap(layout, self.wire) if cap_feed and layout.beams else None
        # A line of pixels shows the 1D counterpart of Eq. 7: the profile in x alone
        self._line_y = float(layout.pixel_xy[0, 1]) if layout.lattice == "line" else None
        self._bump = BumpPath(layout, crs=meaning.drives_beams) if meaning.fast_path else None
        n = layout.n_pixels
        self._pixel_upper = float(self._upper[:n].min()) if n else 0.0
        self._feed_upper = float(self._upper[n:].min()) if layout.n_actuators > n else 0.0

    @property
    def _beams(self) -> CompressedBeams | None:
        """The cap's beam solver once a frame has fed a beam (None before, and without a cap)."""
        return None if self._cap is None else self._cap._beams

    def render(self, target: Bump) -> Rendering:
        if self._bump is not None and type(target) is Bump:
            centre = target.centre_mm
            return self._render_bump(centre[0], centre[1], target.diameter_mm,
                                     target.height_mm)
        if self._line_y is not None and target.centre_mm[1] != self._line_y:
            target = target.moved_to((target.centre_mm[0], self._line_y))  # y_f is ignored
        raw = self._func(self.layout, target, self._geometry)
        return self.limit(raw)

    def render_bump(self, centre_mm: tuple[float, float], diameter_mm: float,
                    height_mm: float) -> Rendering:
        """``render(Bump(centre_mm, diameter_mm, height_mm))`` without building the Bump
        (the live link's path: one frame per packet); the same checks of the numbers."""
        cx, cy = float(centre_mm[0]), float(centre_mm[1])
        diameter, height = float(diameter_mm), float(height_mm)
        if self._bump is None or not (math.isfinite(diameter) and diameter > 0
                                      and math.isfinite(height) and height >= 0
                                      and math.isfinite(cx) and math.isfinite(cy)):
            return self.render(Bump((cx, cy), diameter, height))  # its checks, its messages
        return self._render_bump(cx, cy, diameter, height)

    def _render_bump(self, cx: float, cy: float, diameter: float, height: float
                     ) -> Rendering:
        if self._line_y is not None:
            cy = self._line_y  # y_f is ignored on a line of pixels
        path = self._bump
        heights, starts, ends = path.parts(cx, cy, diameter, height)
        if height > self._pixel_upper or (starts and max(max(starts), max(ends))
                                          > self._feed_upper):
            return self.limit(path.setpoints(heights, starts, ends))  # something to clip
        # nothing lies outside its range (pixels <= z_f, feeds >= 0): limit() would clip
        # nothing, so only the cap is left
        if self._cap is None or not starts:
            return Rendering(path.setpoints(heights, starts, ends), ())
        setpoints = path.setpoints(heights, starts, ends)
        capped_starts, capped_ends, messages = self._cap.apply(
            setpoints[: self.layout.n_pixels], starts, ends)
        if messages and self.policy == "error":
            raise RenderError(f"{self.condition}: {messages[0]}")
        if capped_starts != starts or capped_ends != ends:
            setpoints = path.setpoints(heights, capped_starts, capped_ends)
        return Rendering(setpoints, tuple(messages))

    def limit(self, raw: np.ndarray) -> Rendering:
        """Apply the clamp policy and the feed cap to a raw setpoint vector."""
        clipped = np.clip(raw, 0.0, self._upper)
        bad = np.flatnonzero(np.abs(clipped - raw) > 1e-12)
        messages = [
            f"{self.layout.actuators[i].name}: {raw[i]:.3f} mm clipped to {clipped[i]:.3f} mm "
            f"(range 0..{self._upper[i]:g} mm)"
            for i in bad
        ]
        if messages and self.policy == "error":
            raise RenderError(f"{self.condition}: setpoint out of range: {messages[0]}")
        capped = clipped
        if self._cap is not None:
            g = self._geometry
            starts, ends = clipped[g.start_servo].tolist(), clipped[g.end_servo].tolist()
            capped_starts, capped_ends, cap_messages = self._cap.apply(
                clipped[: self.layout.n_pixels], starts, ends)
            if cap_messages and self.policy == "error":
                raise RenderError(f"{self.condition}: {cap_messages[0]}")
            messages += cap_messages
            if capped_starts != starts or capped_ends != ends:
                capped = clipped.copy()
                capped[g.start_servo] = capped_starts
                capped[g.end_servo] = capped_ends
        if not messages and capped is clipped:
            return Rendering(raw, ())
        return Rendering(capped, tuple(messages))


def render(layout: Layout, target: Bump, condition: str, policy: ClampPolicy = "clip"
           ) -> Rendering:
    """One-off rendering; build a :class:`Renderer` to render many frames."""
    return Renderer(layout, condition, policy).render(target)
