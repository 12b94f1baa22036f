"""Renderer: a target surface to actuator setpoints, per experimental condition.

Setpoint vectors follow :class:`~crs_study.layout.Layout` actuator order: pixel heights above
base (mm), then for each beam the length fed into the display by its start and end boundary
servos (mm, >= 0).

Conditions are strategies registered by name (:data:`CONDITIONS`):

``pixel-only``
    pixel heights sampled from the target, every boundary servo at neutral (0 mm).
``crs``
    the same pixel heights, and for each beam the compression that makes the beam's length in
    the display equal to the target's arc length along the beam's line between its clamps
    (crs-paper.md, Supplementary Discussion 7)::

        feed = L_target - L_straight,   L_target = integral sqrt(1 + (dz/ds)^2) ds

Split rule: each end feeds half of ``feed``. When half exceeds one end's boundary travel, that
end feeds its full travel and the other end takes the rest, so the parts always sum to the whole
while the whole fits in the two ends' travel. The beam's shape does not depend on the split
(both clamps sit at base height and fixed positions); the even split halves the distance each
servo moves and therefore the time a change takes.

Clamp policy: a setpoint outside its actuator's range (pixel 0..travel, boundary
0..boundary travel) is clipped to the range and reported in :attr:`Rendering.clamped`, or,
with ``policy="error"``, raised as :class:`~crs_study.errors.RenderError`. Nothing beyond range
is ever passed on silently.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crs_study.errors import RenderError
from crs_study.layout import Layout
from crs_study.targets import Bump, arc_excess

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


#: Registered conditions: name -> function(layout, target, geometry) -> raw setpoints.
CONDITIONS: dict[str, Callable[[Layout, Bump, BeamGeometry | None], np.ndarray]] = {
    "pixel-only": render_pixel_only,
    "crs": render_crs,
}


def register_condition(name: str,
                       func: Callable[[Layout, Bump, BeamGeometry | None], np.ndarray]) -> None:
    """Add a condition strategy (e.g. an optimised CRS) under ``name``."""
    CONDITIONS[name] = func


class Renderer:
    """Renders targets for one layout and condition, reusing precomputed beam geometry."""

    def __init__(self, layout: Layout, condition: str, policy: ClampPolicy = "clip") -> None:
        if condition not in CONDITIONS:
            raise RenderError(
                f"unknown condition {condition!r}; known: {', '.join(sorted(CONDITIONS))}"
            )
        if policy not in ("clip", "error"):
            raise RenderError(f"unknown clamp policy {policy!r}; known: clip, error")
        self.layout = layout
        self.condition = condition
        self.policy = policy
        self._func = CONDITIONS[condition]
        self._geometry = BeamGeometry(layout)
        self._upper = np.array([a.calibration.travel_mm for a in layout.actuators])

    def render(self, target: Bump) -> Rendering:
        raw = self._func(self.layout, target, self._geometry)
        return self.limit(raw)

    def limit(self, raw: np.ndarray) -> Rendering:
        """Apply the clamp policy to a raw setpoint vector."""
        clipped = np.clip(raw, 0.0, self._upper)
        bad = np.flatnonzero(np.abs(clipped - raw) > 1e-12)
        if bad.size == 0:
            return Rendering(raw, ())
        messages = tuple(
            f"{self.layout.actuators[i].name}: {raw[i]:.3f} mm clipped to {clipped[i]:.3f} mm "
            f"(range 0..{self._upper[i]:g} mm)"
            for i in bad
        )
        if self.policy == "error":
            raise RenderError(f"{self.condition}: setpoint out of range: {messages[0]}")
        return Rendering(clipped, messages)


def render(layout: Layout, target: Bump, condition: str, policy: ClampPolicy = "clip"
           ) -> Rendering:
    """One-off rendering; build a :class:`Renderer` to render many frames."""
    return Renderer(layout, condition, policy).render(target)
