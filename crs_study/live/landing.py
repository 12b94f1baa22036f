"""Where the bump landed against where the finger was: position error, lead and overshoot.

A frame's **position error** is the distance in the display's plane between the bump's centre
it rendered and the finger at the moment its servos were in place (its last byte's arrival
where no servo time is known). Its **lead** is the time its position was rendered for minus
that moment: > 0 the bump shows where the finger will be later (haptics ahead of vision).
At a **stroke end** (the finger stops pressing, or stops moving) the **overshoot** is how far
past the end, along the stroke's last direction, any bump landed that was rendered from a
packet of before the finger left the end: what a prediction that runs on costs.

:class:`FingerHistory` measures the error in a running session from the packets themselves;
:func:`landing_errors` measures a run against a known true trace (the simulation of
:mod:`crs_study.live.simulate`, where the finger's true path is the trace before tracker
jitter).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from crs_study.live.trace import FingerTrace

#: Below this speed (mm/s) a pressing finger counts as still: a stroke ended.
STILL_MM_S = 2.0
#: A stroke's direction at its end: from the path's point this far back (mm).
DIRECTION_BACK_MM = 3.0
#: Longest a stroke end is watched for overshoot (s).
END_WINDOW_S = 0.5


def landed_at(frame) -> float:
    """When a frame's servos were in place, or its last byte arrived where that is unknown."""
    return frame.in_place_at if math.isfinite(frame.in_place_at) else frame.done_at


class FingerHistory:
    """The accepted packets of the last ``keep_s`` seconds, to find the finger at a frame's
    landing (linear interpolation between the packets around it; the newest after it)."""

    def __init__(self, keep_s: float = 2.0) -> None:
        self.keep_s = keep_s
        self.samples: deque[tuple[float, float, float, float]] = deque()

    def add(self, t: float, x: float, y: float, z: float) -> None:
        self.samples.append((t, x, y, z))
        while self.samples[0][0] < t - self.keep_s:
            self.samples.popleft()

    def at(self, t: float) -> tuple[float, float, float] | None:
        if not self.samples or t < self.samples[0][0]:
            return None
        before = after = self.samples[-1]
        for sample in reversed(self.samples):
            if sample[0] <= t:
                before = sample
                break
            after = sample
        if after[0] <= before[0]:
            return before[1:]
        w = (t - before[0]) / (after[0] - before[0])
        return tuple(a + w * (b - a) for a, b in zip(before[1:], after[1:], strict=True))

    def error(self, frame) -> float:
        """The frame's position error (mm), NaN when it showed no bump or the finger did not
        press then."""
        finger = self.at(landed_at(frame))
        if frame.shown is None or finger is None or finger[2] <= 0:
            return math.nan
        return math.hypot(frame.shown[0] - finger[0], frame.shown[1] - finger[1])


@dataclass(frozen=True)
class LandingErrors:
    """One run's errors: ``errors_mm`` per frame that landed on a pressing, moving finger (a
    held one is not what prediction is for, and its many frames would hide the moving ones'
    errors), ``leads_s`` per finger frame, ``overshoot_mm`` per stroke end."""

    errors_mm: np.ndarray
    leads_s: np.ndarray
    overshoot_mm: np.ndarray


def stroke_ends(trace: FingerTrace) -> list[int]:
    """Samples where a pressing finger stops: it moved into the sample and then lifts, stands
    still or the trace ends."""
    pressed = trace.xyz[:, 2] > 0
    speed = np.hypot(*np.diff(trace.xyz[:, :2], axis=0).T) / np.diff(trace.times)
    ends = []
    for k in range(1, len(trace)):
        if not (pressed[k] and pressed[k - 1] and speed[k - 1] > STILL_MM_S):
            continue
        if k == len(trace) - 1 or not pressed[k + 1] or speed[k] <= STILL_MM_S:
            ends.append(k)
    return ends


def landing_errors(frames, truth: FingerTrace, t0: float) -> LandingErrors:
    """Errors of ``frames`` (finished finger frames) against ``truth``, whose time 0 is ``t0``
    on the frames' clock (module docstring)."""
    frames = [f for f in frames if f.shown is not None and not f.lost]
    landed = np.array([landed_at(f) for f in frames]) - t0
    shown = np.array([f.shown for f in frames]).reshape(-1, 3)
    true = np.column_stack([np.interp(landed, truth.times, truth.xyz[:, i]) for i in range(3)])
    # the finger's speed at landing (mm/s, the true path's finite difference)
    step = 1e-3
    ahead = np.column_stack([np.interp(landed + step, truth.times, truth.xyz[:, i])
                             for i in range(2)])
    moving = (true[:, 2] > 0) & (np.hypot(*(ahead - true[:, :2]).T) / step > STILL_MM_S)
    errors = np.hypot(*(shown[moving, :2] - true[moving, :2]).T)
    leads = np.array([f.rendered_for for f in frames]) - t0 - landed
    carried = np.array([f.arrivals[0] if f.arrivals else math.nan for f in frames]) - t0
    overshoot = []
    xy = truth.xyz[:, :2]
    for k in stroke_ends(truth):
        end, t_end = xy[k], truth.times[k]
        back = np.flatnonzero(np.hypot(*(xy[:k] - end).T) >= DIRECTION_BACK_MM)
        if not back.size:
            continue
        u = (end - xy[back[-1]]) / np.linalg.norm(end - xy[back[-1]])
        # frames that carried a packet from before the finger left the end (lifted, or moved
        # 1 mm on), landing after it got there
        left = np.flatnonzero((truth.times > t_end) & ((truth.xyz[:, 2] <= 0)
                                                       | (np.hypot(*(xy - end).T) > 1.0)))
        leave = truth.times[left[0]] if left.size else math.inf
        watched = (landed >= t_end) & (landed < t_end + END_WINDOW_S) & (carried < leave)
        past = (shown[watched, :2] - end) @ u
        overshoot.append(float(max(0.0, past.max())) if past.size else 0.0)
    return LandingErrors(errors, leads, np.array(overshoot))
