"""Bench area ``writes``: the write policy's refresh rule against the rule it replaced.

The write policy (:mod:`crs_study.device.writes`) lets the full refresh ride on a frame: the
first write ``refresh_s`` after the last full one carries every channel. SerialDevice's writer
used to send it on its own the moment it fell due with the wire free, carrying the last wanted
frame (the newest frame then waited behind it). Both rules are run here through the same
:class:`~crs_study.device.writes.PortWrites` (the old one by asking it for a full write of the
last wanted pulses whenever the refresh fell due with no frame waiting) over the default
protocol's ten CRS digit stimuli on the 2D device, at the protocol's frame rate, refresh every
1 s, each stimulus starting 0.4 s into the refresh interval (so the refresh falls between two
frames, as it mostly does).

Figures (value: riding; baseline: on its own, same stimuli, same run): the largest and the
99th-percentile wire latency of a frame (from its time to the end of the write carrying it,
the worse controller), and the bytes both boards get. Informative (no target): they are what
decided the rule (device/writes.py).
"""

from __future__ import annotations

import numpy as np

from crs_study.benchmarks import Figure
from crs_study.benchmarks.device import _digit_frames
from crs_study.device.calibration import PulseMap
from crs_study.device.writes import ChannelSplit, PortWrites, WritePolicy
from crs_study.geometry.layout import load_layout

AREA = "writes"
DESCRIPTION = "the refresh riding on a frame vs sent on its own when due: latency and bytes"

#: Where in the refresh interval each stimulus starts (s since the last full write).
PHASE_S = 0.4
REFRESH_S = 1.0


def _latencies(pulses, times, initial, refresh_alone: bool):
    """Per-frame latency (s) and bytes on one port, the refresh riding or going alone."""
    port = PortWrites(pulses.shape[1], WritePolicy(1, REFRESH_S), initial, -PHASE_S)
    port.wanted = initial  # the pose on the board before the stimulus
    latency = np.zeros(len(times))
    waiting: list[int] = []
    sent = 0

    def write_at(t: float) -> None:
        nonlocal sent
        write = port.take(t)
        sent += write.n_bytes
        for j in waiting:
            latency[j] = write.done - times[j]
        waiting.clear()

    def due() -> float:
        if port.pending or not refresh_alone:
            return port.next_write_at()
        return max(port.free_at, port.last_full_at + REFRESH_S)  # the refresh, on its own

    for k, t in enumerate(times):
        while (at := due()) <= t:
            if not port.pending:
                port.want(at, port.wanted, 0, full=True)
            write_at(at)
        port.want(t, pulses[k], 0)
        waiting.append(k)
        if port.next_write_at() <= t:
            write_at(t)
    if port.pending:
        write_at(port.next_write_at())
    return latency, sent


def run(quick: bool) -> list[Figure]:
    layout = load_layout("crs2d")
    stimuli, rate = _digit_frames(layout, "crs", quick)
    pulse_map, split = PulseMap.from_layout(layout), ChannelSplit(layout)
    initial = pulse_map.to_pulses(layout.neutral_setpoints())
    results = {}
    for alone in (False, True):
        latencies, total = [], 0
        for frames in stimuli:
            pulses = pulse_map.to_pulses(frames)
            times = np.arange(len(pulses)) / rate
            worst = np.zeros(len(pulses))
            for members in split.members:
                latency, sent = _latencies(pulses[:, members], times, initial[members], alone)
                worst = np.maximum(worst, latency)
                total += sent
            latencies.append(worst)
        results[alone] = np.concatenate(latencies), total
    (riding, riding_bytes), (alone, alone_bytes) = results[False], results[True]
    n = len(riding)
    baseline = "refresh sent on its own when due (the serial device before the policy)"
    return [
        Figure(AREA, f"largest wire latency, crs digits at {rate:g}/s ({n} frames), refresh "
               "riding on a frame", float(riding.max()), "s", baseline, float(alone.max())),
        Figure(AREA, "99th-percentile wire latency, crs digits, refresh riding on a frame",
               float(np.percentile(riding, 99)), "s", baseline,
               float(np.percentile(alone, 99))),
        Figure(AREA, "bytes on the wire, crs digits, refresh riding on a frame",
               float(riding_bytes), "bytes", baseline, float(alone_bytes)),
    ]
