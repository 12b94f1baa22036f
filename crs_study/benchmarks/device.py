"""Bench area ``device``: the serial device against the 9600-baud wire it drives.

Figures (baselines measured or computed in the same run):

1. Achieved frame rate with every channel changing in every frame, SerialDevice writing two
   paced fake ports that take the wire's time per byte (10 bits at 9600 baud, 1.0417 ms; a
   pty does not throttle, so the port sleeps that long in ``write``), against the wire bound
   1 / (64 bytes x 1.0417 ms) = 15.0 frames/s. Target: ratio >= 0.95.
2. Software time per frame (``send()`` plus building and encoding the busiest controller's
   SERVO_MOVE), against the full frame's wire time, 66.7 ms. Target: ratio <= 0.01.
3. Median wire latency of the default protocol's digit stimuli on the 2D device (bump of
   90 mm, 5 mm high, moving along the shipped digit strokes; CRS condition, the busier one),
   changed-only channels with the default dead-band and the devices' full refresh (every
   channel once a second, the first frame of each stimulus full), against sending
   everything. Target: <= 45 ms (the paper's device: 75 ms).
4. The same with the channel map made lopsided (24 channels on A, 13 on B), against the
   shipped balanced map (19/18): what balancing saves.
"""

from __future__ import annotations

import statistics
import threading
import time
from dataclasses import replace

import numpy as np

from crs_study.benchmarks import Figure, median_seconds
from crs_study.clock import RealClock
from crs_study.device.base import BYTE_TIME_S, full_frame_rate_hz, full_frame_wire_time_s
from crs_study.device.calibration import PulseMap
from crs_study.device.schedule import wire_plan
from crs_study.device.serial_device import SerialDevice
from crs_study.device.serial_port import SerialOptions
from crs_study.device.writes import ChannelSplit
from crs_study.geometry.layout import load_layout
from crs_study.paths import shipped_file
from crs_study.protocol import load_protocol
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import make_stimulus

AREA = "device"
DESCRIPTION = "serial device vs the 9600-baud wire: frame rate, software time, latency"

TARGET_RATE_RATIO = 0.95
TARGET_SOFTWARE_RATIO = 0.01
TARGET_LATENCY_S = 0.045


class PacedPort:
    """A serial-like port that takes the wire's time to write (``byte_s`` a byte, 0: none);
    records write intervals and keeps the bytes (tests decode them)."""

    def __init__(self, name: str, byte_s: float) -> None:
        self.name, self.byte_s = name, byte_s
        self.is_open, self.in_waiting = True, 0
        self.writes: list[tuple[float, float, int]] = []
        self.data = bytearray()
        self._lock = threading.Lock()

    def write(self, data: bytes) -> int:
        start = time.monotonic()
        end = start + len(data) * self.byte_s
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(left, 0.002) if left > 0.003 else 0)
        with self._lock:
            self.writes.append((start, time.monotonic(), len(data)))
            self.data += data
        return len(data)

    def read(self, n: int) -> bytes:
        time.sleep(0.02)
        return b""

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False


def _achieved_rate(layout, seconds: float) -> tuple[float, float, list[float]]:
    """Frames/s on the busiest port with every channel changing; send() times (s)."""
    ports = [PacedPort(c.name, BYTE_TIME_S) for c in layout.controllers]
    device = SerialDevice(layout, ports, RealClock(),
                          SerialOptions(check_battery=False, refresh_s=0.0))
    send_times = []
    with device:
        start = time.monotonic()
        k = 0
        while time.monotonic() - start < seconds:
            setpoints = np.full(layout.n_actuators, 1.0 + (k % 2))  # every channel changes
            t0 = time.perf_counter()
            device.send(setpoints)
            send_times.append(time.perf_counter() - t0)
            k += 1
            time.sleep(0.001)  # frames come far faster than the wire takes them
        device.wait_sent(1.0)
    busiest = max(ports, key=lambda p: p.writes[0][2])  # the longest full frame
    starts = [w[0] for w in busiest.writes[:-1]]  # the last write is close()'s neutral pose
    rate = (len(starts) - 1) / (starts[-1] - starts[0]) if len(starts) > 1 else 0.0
    return rate, len(starts), send_times


def _digit_frames(layout, condition: str, quick: bool):
    protocol = load_protocol(shipped_file("protocols/digit_identification.toml"))
    renderer = Renderer(layout, condition)
    digits = protocol.symbols[:3] if quick else protocol.symbols
    return [render_frames(make_stimulus(protocol, layout, d), renderer) for d in digits], \
        protocol.frame_rate_hz


def _lopsided(layout):
    """The same device with five of B's channels moved to A (24 / 13)."""
    acts = list(layout.actuators)
    moved = [i for i, a in enumerate(acts) if a.controller == "B"][:5]
    for channel, i in zip(range(20, 25), moved, strict=True):
        acts[i] = replace(acts[i], controller="A", channel=channel)
    return replace(layout, actuators=tuple(acts))


def _median_latency(layout, stimuli, rate: float) -> tuple[float, float]:
    plans = [wire_plan(layout, frames, rate) for frames in stimuli]
    changed = np.concatenate([p.latency_changed_s for p in plans])
    full = np.concatenate([p.latency_full_s for p in plans])
    return float(np.median(changed)), float(np.median(full))


def run(quick: bool) -> list[Figure]:
    layout = load_layout("crs2d")
    figures = []

    bound = full_frame_rate_hz(layout)
    rate, writes, send_times = _achieved_rate(layout, 1.5 if quick else 5.0)
    figures.append(Figure(
        area=AREA, name=f"achieved frame rate, every channel changing ({writes} writes, "
        "paced 9600-baud ports)", value=rate, unit="frames/s",
        baseline_name="wire bound, 64-byte frame", baseline=bound,
        target=f"ratio >= {TARGET_RATE_RATIO}", passed=rate >= TARGET_RATE_RATIO * bound))

    pulse_map, split = PulseMap.from_layout(layout), ChannelSplit(layout)
    pulses = pulse_map.to_pulses(np.full(layout.n_actuators, 2.0))
    repeat, number = (5, 200) if quick else (15, 1000)
    build = median_seconds(lambda: split.frame(0, pulses, split.changed(0, pulses, None), 67),
                           repeat, number)
    software = statistics.median(send_times) + build
    wire = full_frame_wire_time_s(layout)
    figures.append(Figure(
        area=AREA, name="software time per frame (send + build and encode busiest frame)",
        value=software, unit="s", baseline_name="full frame's wire time", baseline=wire,
        target=f"ratio <= {TARGET_SOFTWARE_RATIO}",
        passed=software <= TARGET_SOFTWARE_RATIO * wire))

    for condition in ("crs", "pixel-only"):
        stimuli, frame_rate = _digit_frames(layout, condition, quick)
        changed, full = _median_latency(layout, stimuli, frame_rate)
        n = sum(len(s) for s in stimuli)
        checked = condition == "crs"
        figures.append(Figure(
            area=AREA, name=f"median wire latency, {condition} digits at {frame_rate:g}/s "
            f"({n} frames), changed-only (paper's device: 75 ms)", value=changed, unit="s",
            baseline_name="sending every channel", baseline=full,
            target=f"value <= {TARGET_LATENCY_S * 1e3:g} ms" if checked else "",
            passed=changed <= TARGET_LATENCY_S if checked else None))
        if checked:
            lopsided_changed, lopsided_full = _median_latency(_lopsided(layout), stimuli,
                                                              frame_rate)
            figures.append(Figure(
                area=AREA, name="median wire latency, crs digits, lopsided map 24/13 "
                "(changed-only)", value=lopsided_changed, unit="s",
                baseline_name="balanced map 19/18 (changed-only)", baseline=changed))
            figures.append(Figure(
                area=AREA, name="median wire latency, crs digits, lopsided map 24/13 "
                "(send everything)", value=lopsided_full, unit="s",
                baseline_name="balanced map 19/18 (send everything)", baseline=full))
    return figures
