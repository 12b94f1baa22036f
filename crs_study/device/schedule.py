"""Frame scheduling: what a stimulus costs on the wire, the frame rate it allows, its latency.

The wire (LSC protocol): each controller has its own 9600-baud port, 10 bits a byte
(1.0417 ms), written concurrently; a SERVO_MOVE for n servos is 3 n + 7 bytes. A frame is on the
wire until its busiest controller's bytes have left.

Changed-only frames: a channel goes into a controller's SERVO_MOVE only when its whole-us pulse
width differs by more than ``deadband_us`` from what was last sent on it (dead-band 0: any
change; default :data:`DEFAULT_DEADBAND_US`). Send-everything frames carry every channel of
the controller.

Writes: what goes on the wire, and when, is the host's write policy
(:mod:`~crs_study.device.writes`), the very code that drives both devices: merging, never
queueing (a frame handed over while its port's wire is busy waits, a newer one replaces it);
changed-only channels; the full refresh every ``refresh_s`` (default
:data:`~.writes.DEFAULT_REFRESH_S`, 0: never), riding on the first write that starts
``refresh_s`` or more after the last full write. :func:`simulate_port` runs the policy over a
frame sequence. The latency of frame k is the time from its stimulus time ``t_k = k / f`` to the
last byte of the write that carries it (or a newer frame that superseded it), the worst over
controllers; it stays bounded (about two writes) however fast frames come. A refresh frame takes
the full frame's wire time, so with the refresh on, the frame rate at which every frame fits its
period (:attr:`WirePlan.rate_bound_hz`) is never above the full-frame bound, and the frames
after a refresh that overran its period wait: the latencies count them. By default the last full
write is long past, so frame 0 is full, as the first frame after the device opens or has been
idle for ``refresh_s`` (a stimulus onset after the response phase).

Balance: which channel is on which controller is pinned by the device file (the reasons are in
:mod:`~crs_study.device.serial_device`, "Which channel goes on which controller"):
:func:`channel_balance` reports how evenly the file spreads them (the full frame is bounded by
the busiest controller) and how many to rewire where it does not, and both devices warn on
open (:func:`warn_if_unbalanced`) when the busiest controller's full frame is more than 10 %
longer than an even split's. The shipped 2D device file is balanced, 19 channels on A and 18
on B.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from crs_study.device.base import (
    BAUD_RATE,
    BYTE_TIME_S,
    DeviceWarning,
    full_frame_rate_hz,
    servo_move_bytes,
)
from crs_study.device.calibration import PulseMap
from crs_study.device.writes import (
    DEFAULT_DEADBAND_US,
    DEFAULT_REFRESH_S,
    ChannelSplit,
    PortWrites,
    Write,
    WritePolicy,
)
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout

__all__ = ["DEFAULT_DEADBAND_US", "DEFAULT_REFRESH_S", "IMBALANCE_WARN", "Balance",
           "ChannelSplit", "PortRun", "WirePlan", "changed_bytes_per_frame", "channel_balance",
           "max_frame_rate_hz", "simulate_port", "warn_if_unbalanced", "wire_plan"]

#: A busiest controller whose full frame is this much longer than an even split's is reported.
IMBALANCE_WARN = 0.10


@dataclass(frozen=True)
class Balance:
    """How the device file spreads channels over controllers."""

    counts: dict[str, int]
    busiest: str
    full_frame_bytes: int  # busiest controller, every channel
    even_split_bytes: int  # what an even split would need
    excess: float  # full_frame_bytes / even_split_bytes - 1
    moves: tuple[tuple[str, str, int], ...] = ()  # (from, to, channels) that would even it

    @property
    def balanced(self) -> bool:
        return self.excess <= IMBALANCE_WARN

    def describe(self) -> str:
        counts = ", ".join(f"{name}: {n}" for name, n in self.counts.items())
        moves = "; ".join(f"{n} from {a} to {b}" for a, b, n in self.moves)
        verdict = "balanced" if self.balanced else (
            f"unbalanced: {self.busiest}'s full frame is {self.excess:.0%} longer than an even "
            f"split's; rewire channels ({moves}) and record them in the device file")
        return f"channels per controller {counts} ({verdict})"


def channel_balance(layout: Layout) -> Balance:
    """How evenly ``layout`` spreads its channels, and the fewest moves to an even split.

    An even split puts at most ceil(n / controllers) channels on a board (the shipped 2D file:
    37 on two, 19 and 18), within each board's channel count.
    """
    counts = {c.name: 0 for c in layout.controllers}
    for a in layout.actuators:
        counts[a.controller] += 1
    busiest = max(counts, key=counts.__getitem__)
    even = math.ceil(layout.n_actuators / len(counts))
    full = servo_move_bytes(counts[busiest])
    room = {c.name: min(even, c.channels) - counts[c.name] for c in layout.controllers}
    moves = []
    for name in sorted(counts, key=lambda n: -counts[n]):
        surplus = counts[name] - even
        for target in sorted(room, key=lambda n: -room[n]):
            if surplus <= 0:
                break
            n = min(surplus, room[target])
            if n > 0 and target != name:
                moves.append((name, target, n))
                room[target] -= n
                surplus -= n
    return Balance(counts, busiest, full, servo_move_bytes(even),
                   full / servo_move_bytes(even) - 1.0, tuple(moves))


def warn_if_unbalanced(layout: Layout, stacklevel: int = 3) -> Balance:
    """:func:`channel_balance`, with a :class:`~.base.DeviceWarning` when it is unbalanced
    (what both devices do on open)."""
    balance = channel_balance(layout)
    if not balance.balanced:
        warnings.warn(f"{layout.name}: {balance.describe()}", DeviceWarning,
                      stacklevel=stacklevel)
    return balance


@dataclass(frozen=True, eq=False)
class WirePlan:
    """Wire use and latency of one stimulus at one frame rate. Build with :func:`wire_plan`.

    Rates in frames/s, times in seconds, bytes per controller in device-file order.
    """

    frame_rate_hz: float
    deadband_us: int
    refresh_s: float  # full-refresh interval (0: none)
    controllers: tuple[str, ...]
    full_bytes: tuple[int, ...]  # every channel, per controller
    changed_bytes: np.ndarray  # (n_frames, n_controllers): each frame's changed channels
    full_frame_rate_hz: float  # wire bound, every channel in every frame
    changed_only_rate_hz: float  # highest rate at which frames 1.. fit, refresh aside
    latency_changed_s: np.ndarray  # (n_frames,) changed-only with the refresh, merging
    latency_full_s: np.ndarray  # (n_frames,) send-everything, merging
    merged_changed: int  # frames superseded before they reached the wire
    merged_full: int
    refreshes: int  # full refresh writes in the changed-only run (busiest port)

    @property
    def n_frames(self) -> int:
        return len(self.latency_changed_s)

    @property
    def median_latency_s(self) -> float:
        return float(np.median(self.latency_changed_s)) if self.n_frames else 0.0

    @property
    def max_latency_s(self) -> float:
        return float(np.max(self.latency_changed_s)) if self.n_frames else 0.0

    @property
    def median_latency_full_s(self) -> float:
        return float(np.median(self.latency_full_s)) if self.n_frames else 0.0

    @property
    def max_latency_full_s(self) -> float:
        return float(np.max(self.latency_full_s)) if self.n_frames else 0.0

    @property
    def within_full_bound(self) -> bool:
        """Every frame fits its period even if every channel changes (refreshes included)."""
        return self.frame_rate_hz <= self.full_frame_rate_hz * (1 + 1e-9)

    @property
    def rate_bound_hz(self) -> float:
        """Highest frame rate at which every frame after the first fits its period, the full
        refresh included: with it on, some frame of every refresh interval carries every
        channel, so the bound is the lower of the changed-only and the full-frame bounds."""
        if self.refresh_s > 0:
            return min(self.changed_only_rate_hz, self.full_frame_rate_hz)
        return self.changed_only_rate_hz

    @property
    def within_changed_bound(self) -> bool:
        """Every frame fits its period with changed-only frames, the refresh included."""
        return self.frame_rate_hz <= self.rate_bound_hz * (1 + 1e-9)

    def summary(self) -> dict:
        """Plain numbers (ms, frames/s, bytes) for printing or JSON."""
        busiest = self.changed_bytes.max(axis=1) if self.n_frames else np.zeros(0)
        return {
            "frame_rate_hz": self.frame_rate_hz,
            "frames": self.n_frames,
            "deadband_us": self.deadband_us,
            "refresh_s": self.refresh_s,
            "full_frame_bytes": dict(zip(self.controllers, self.full_bytes, strict=True)),
            "full_frame_rate_hz": self.full_frame_rate_hz,
            "changed_only_rate_hz": self.changed_only_rate_hz,
            "rate_bound_hz": self.rate_bound_hz,
            "refreshes": self.refreshes,
            "changed_bytes_busiest_median": float(np.median(busiest)) if len(busiest) else 0.0,
            "changed_bytes_busiest_max": int(busiest.max()) if len(busiest) else 0,
            "latency_changed_ms": {"median": self.median_latency_s * 1e3,
                                   "max": self.max_latency_s * 1e3},
            "latency_full_ms": {"median": self.median_latency_full_s * 1e3,
                                "max": self.max_latency_full_s * 1e3},
            "merged_changed": self.merged_changed,
            "merged_full": self.merged_full,
            "within_full_bound": self.within_full_bound,
            "within_changed_bound": self.within_changed_bound,
        }


def changed_bytes_per_frame(pulses: np.ndarray, split: ChannelSplit,
                            initial: np.ndarray | None, deadband_us: int = DEFAULT_DEADBAND_US
                            ) -> np.ndarray:
    """Bytes each frame needs per controller when every frame goes out on its own.

    ``pulses`` (n_frames, n_actuators) whole us; ``initial`` the pulses already on the wire
    before frame 0 (None: unknown, frame 0 sends every channel).
    """
    out = np.zeros((len(pulses), len(split.members)), dtype=np.int64)
    for c in range(len(split.members)):
        last = None if initial is None else initial[split.members[c]].copy()
        for k, frame in enumerate(pulses):
            local = split.changed(c, frame, last, deadband_us)
            if len(local):
                out[k, c] = servo_move_bytes(len(local))
                mine = frame[split.members[c]]
                if last is None:
                    last = mine.copy()
                else:
                    last[local] = mine[local]
    return out


@dataclass(frozen=True, eq=False)
class PortRun:
    """What the write policy did on one port over a frame sequence (:func:`simulate_port`)."""

    writes: list[Write]  # in order; a write of 0 bytes (nothing changed) puts nothing on the wire
    latency_s: np.ndarray = field(repr=False)  # per frame: end of the write carrying it - t_k
    merged: int  # frames superseded before they reached the wire

    @property
    def refreshes(self) -> int:
        """Full writes (in a changed-only run from a known pose: the refreshes)."""
        return sum(w.full for w in self.writes)


def simulate_port(pulses: np.ndarray, times: np.ndarray, policy: WritePolicy,
                  last_sent: np.ndarray | None = None, last_full_at: float = -math.inf,
                  move_ms: int = 0) -> PortRun:
    """The write policy (:class:`~.writes.PortWrites`) on one port: frame k (this
    controller's whole-us ``pulses[k]``) wanted at ``times[k]`` (non-decreasing), until the
    last frame has been written.

    ``last_sent``, ``last_full_at``: the port before frame 0 (None, -inf: nothing sent yet).
    """
    port = PortWrites(pulses.shape[1], policy, last_sent, last_full_at)
    latency = np.zeros(len(times))
    writes: list[Write] = []
    waiting: list[int] = []  # frames wanted and not yet carried by a write
    merged = 0

    def take(t: float) -> None:
        write = port.take(t)
        writes.append(write)
        for j in waiting:
            latency[j] = write.done - times[j]
        waiting.clear()

    for k, t in enumerate(times):
        while port.next_write_at() <= t:  # due by t: goes before frame k (the tie rule)
            take(port.next_write_at())
        merged += port.want(t, pulses[k], move_ms)
        waiting.append(k)
        if port.next_write_at() <= t:
            take(t)
    if port.pending:
        take(port.next_write_at())
    return PortRun(writes, latency, merged)


def wire_plan(layout: Layout, setpoints_sequence: np.ndarray, frame_rate_hz: float,
              deadband_us: int = DEFAULT_DEADBAND_US,
              initial_setpoints: np.ndarray | None = None,
              refresh_s: float = DEFAULT_REFRESH_S, last_refresh_s: float = -math.inf
              ) -> WirePlan:
    """Wire use and latency of a stimulus (n_frames x n_actuators, mm) at ``frame_rate_hz``.

    Frame k is due at ``k / frame_rate_hz``. ``initial_setpoints`` is the pose before frame 0
    (default: neutral, as between trials). ``refresh_s`` is the full-refresh interval (0:
    none) and ``last_refresh_s`` the time of the last full write before frame 0 (frame 0 at
    0 s; default: long before, so frame 0 is full; module docstring). Setpoints outside
    calibrated limits raise :class:`DeviceError` (they could never be sent).
    """
    if not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
        raise DeviceError(f"frame rate: expected a number > 0 frames/s, got {frame_rate_hz!r}")
    if not (math.isfinite(refresh_s) and refresh_s >= 0):
        raise DeviceError(f"refresh interval: expected a number of seconds >= 0 (0: none), "
                          f"got {refresh_s!r}")
    if math.isnan(last_refresh_s) or last_refresh_s > 0:
        raise DeviceError(f"last refresh: expected a time <= 0 s (frame 0 is at 0 s), "
                          f"got {last_refresh_s!r}")
    pulse_map = PulseMap.from_layout(layout)
    pulses = pulse_map.to_pulses(np.asarray(setpoints_sequence, dtype=float).reshape(
        -1, layout.n_actuators))
    initial = pulse_map.to_pulses(layout.neutral_setpoints() if initial_setpoints is None
                                  else initial_setpoints)
    split = ChannelSplit(layout)
    changed = changed_bytes_per_frame(pulses, split, initial, deadband_us)
    times = np.arange(len(pulses)) / frame_rate_hz
    lat_changed = np.zeros(len(pulses))
    lat_full = np.zeros(len(pulses))
    merged_changed = merged_full = refreshes = 0
    policy = WritePolicy(deadband_us, refresh_s, BAUD_RATE)
    send_all = WritePolicy(deadband_us, 0.0, BAUD_RATE, send_all=True)
    for members in split.members:
        mine = pulses[:, members]
        run = simulate_port(mine, times, policy, initial[members], last_refresh_s)
        everything = simulate_port(mine, times, send_all, initial[members])
        lat_changed = np.maximum(lat_changed, run.latency_s)
        lat_full = np.maximum(lat_full, everything.latency_s)
        merged_changed = max(merged_changed, run.merged)
        merged_full = max(merged_full, everything.merged)
        refreshes = max(refreshes, run.refreshes)
    steady = changed[1:].max() if len(changed) > 1 else 0
    return WirePlan(
        frame_rate_hz=float(frame_rate_hz), deadband_us=int(deadband_us),
        refresh_s=float(refresh_s), controllers=split.names,
        full_bytes=tuple(servo_move_bytes(len(m)) if len(m) else 0 for m in split.members),
        changed_bytes=changed, full_frame_rate_hz=full_frame_rate_hz(layout),
        changed_only_rate_hz=1.0 / (steady * BYTE_TIME_S) if steady else math.inf,
        latency_changed_s=lat_changed, latency_full_s=lat_full,
        merged_changed=merged_changed, merged_full=merged_full, refreshes=refreshes,
    )


def max_frame_rate_hz(layout: Layout, setpoints_sequence: np.ndarray,
                      deadband_us: int = DEFAULT_DEADBAND_US,
                      initial_setpoints: np.ndarray | None = None,
                      refresh_s: float = DEFAULT_REFRESH_S) -> float:
    """Highest frame rate at which every frame after the first fits its period on the wire.

    1 / (largest changed-only SERVO_MOVE over frames 1.. and controllers x 1.0417 ms), and
    with the full refresh on (``refresh_s`` > 0) at most the full-frame bound
    (:attr:`WirePlan.rate_bound_hz`). The first frame (onset from ``initial_setpoints``) may
    take longer; it merges, never queues. Infinite when nothing changes after the first frame
    and there is no refresh.
    """
    return wire_plan(layout, setpoints_sequence, 1.0, deadband_us, initial_setpoints,
                     refresh_s).rate_bound_hz
