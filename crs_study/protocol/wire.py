"""A protocol's stimuli on the wire: bytes, frame-rate bounds and latency per condition.

One function for what ``crs-study validate`` and ``crs-study device check`` both report.
Two bounds (:mod:`crs_study.device.schedule`):

* full frames: every channel of every controller in every frame, 3 n + 7 bytes a frame at
  9600 baud on each controller's port (the bound the protocol check uses);
* changed-only frames: only the channels whose pulse width moved more than the dead-band
  since the last write, with a full refresh every ``refresh_s``; each stimulus starts after
  an idle inter-trial interval from the neutral pose, so its first frame is full and is left
  out of the busiest frame (:func:`crs_study.device.schedule.wire_plan`).

Every stimulus the protocol shows counts: each symbol, at each level of ``[levels]``, rendered
in each condition (frames from the one render cache,
:func:`crs_study.rendering.frames.render_frames`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

from crs_study.device.base import (
    BYTE_TIME_S,
    channels_per_controller,
    full_frame_rate_hz,
    full_frame_wire_time_s,
    servo_move_bytes,
)
from crs_study.device.schedule import DEFAULT_DEADBAND_US, DEFAULT_REFRESH_S, wire_plan
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import make_stimulus


@dataclass(frozen=True)
class ConditionWire:
    """The changed-only wire use of one condition's stimuli (times in ms, rates in frames/s).

    ``busiest_frame_*`` is the largest frame after the first of any stimulus on the busiest
    port; ``changed_only_rate_hz`` the lowest over the stimuli of the highest rate at which
    their frames fit (refresh aside) and ``rate_bound_hz`` the same with the refresh;
    latencies are from a frame's due time to the end of its write, over every frame, with
    changed-only frames and (``latency_full_*``) when every frame carries every channel.
    """

    condition: str
    frames: int
    mean_bytes_per_frame: float
    busiest_frame_bytes: int
    busiest_frame_wire_ms: float
    busiest_frame_budget_percent: float
    changed_only_rate_hz: float
    rate_bound_hz: float
    latency_ms_median: float
    latency_ms_max: float
    latency_full_ms_median: float


@dataclass(frozen=True)
class WireBudget:
    """The wire use of a protocol's stimuli on a device (see the module docstring).

    ``full_frame_*``: the bytes of a full frame over all controllers, the busiest
    controller's write time (ms), that time as a percentage of the frame period, and the
    highest rate at which full frames fit. ``conditions``: per condition, in the protocol's
    order, with the dead-band (us) and refresh interval (s, 0: none) they were planned with.
    """

    frame_rate_hz: float
    deadband_us: int
    refresh_s: float
    full_frame_bytes: int
    full_frame_busiest_controller_ms: float
    full_frame_budget_percent: float
    full_frame_max_rate_hz: float
    conditions: tuple[ConditionWire, ...]

    def condition(self, name: str) -> ConditionWire:
        return next(c for c in self.conditions if c.condition == name)

    def to_frame(self):
        """One row per condition (the columns of :class:`ConditionWire`)."""
        import pandas as pd  # only here: validate and device check need no pandas

        return pd.DataFrame([asdict(c) for c in self.conditions])

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)


def wire_budget(protocol: Protocol, layout: Layout | None = None, *,
                deadband_us: int = DEFAULT_DEADBAND_US, refresh_s: float = DEFAULT_REFRESH_S
                ) -> WireBudget:
    """Plan every stimulus of ``protocol`` on the wire of ``layout`` (default: the protocol's
    device) with a serial device's dead-band and full-refresh interval."""
    layout = layout if layout is not None else protocol.layout()
    rate = protocol.frame_rate_hz
    period = 1.0 / rate
    stimuli = [make_stimulus(protocol, layout, d, v) for v in protocol.level_values
               for d in protocol.symbols]
    conditions = []
    for condition in protocol.conditions:
        # the frames a session on this device sends: the cap's room for its dead-band
        renderer = Renderer(layout, condition, wire=WireSlack(int(deadband_us)))
        plans = [wire_plan(layout, render_frames(s, renderer), rate, deadband_us=deadband_us,
                           refresh_s=refresh_s) for s in stimuli]
        frames = sum(p.n_frames for p in plans)
        busiest = max(int(p.changed_bytes[1:].max(initial=0)) for p in plans)
        latency = np.concatenate([p.latency_changed_s for p in plans])
        conditions.append(ConditionWire(
            condition=condition, frames=frames,
            mean_bytes_per_frame=sum(int(p.changed_bytes.sum()) for p in plans) / frames,
            busiest_frame_bytes=busiest,
            busiest_frame_wire_ms=busiest * BYTE_TIME_S * 1e3,
            busiest_frame_budget_percent=100.0 * busiest * BYTE_TIME_S / period,
            changed_only_rate_hz=min(p.changed_only_rate_hz for p in plans),
            rate_bound_hz=min(p.rate_bound_hz for p in plans),
            latency_ms_median=float(np.median(latency)) * 1e3,
            latency_ms_max=float(np.max(latency)) * 1e3,
            latency_full_ms_median=float(np.median(np.concatenate(
                [p.latency_full_s for p in plans]))) * 1e3,
        ))
    full_time = full_frame_wire_time_s(layout)
    return WireBudget(
        frame_rate_hz=rate, deadband_us=deadband_us, refresh_s=refresh_s,
        full_frame_bytes=sum(servo_move_bytes(n) for n in
                             channels_per_controller(layout).values() if n),
        full_frame_busiest_controller_ms=full_time * 1e3,
        full_frame_budget_percent=100.0 * full_time / period,
        full_frame_max_rate_hz=full_frame_rate_hz(layout), conditions=tuple(conditions))
