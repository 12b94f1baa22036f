"""Bench area ``live``: the live link's latency at the headset's 72 packets a second, and
where its bumps land against the finger with and without prediction
(:mod:`crs_study.benchmarks._live_landing`, first).

A finger writes digit 9 with the package's strokes (60 mm high, 30 mm/s, pressing 5 mm,
lifting between strokes; :func:`crs_study.live.trace.digit_trace`), sent over UDP on loopback
at 72 packets/s to a live session (CRS condition, 2D device, default write policy: changed
channels only, dead-band 1 us, full refresh every second) on two devices in turn:

``sim``   ``sim://``: the simulated device; its virtual boards time each frame's last byte
          and model the servos;
``pty``   two virtual LSC-24 boards behind pseudo-terminals, paced at 9600 baud, written by the
          real serial code (SerialDevice's writer threads); the boards' own record times the
          frames (and the servos, replayed through the servo model).

Figures, per device, each against the wire time measured in the same run (the median frame's
time on the wire: its busiest board's bytes at 10 bits a byte), with these targets:

1. arrival -> last byte on the wire, median: <= 40 ms (the paper's whole device: 75 ms);
2. the same, 99th percentile: <= 80 ms;
3. arrival -> servos in place, median: <= 75 ms;
4. software per packet (decode, render, hand-over; CPU time of the session's thread), median:
   ratio to the frame's wire time < 0.01;
and informative: the 95th percentile, how far the display lags the newest packet (every packet,
newest wins), frames written a second, on pty the host model's error (the write policy's
prediction of a frame's landing against the board's record), and the software per packet in a
warm loop (decode, render, pulses, the SERVO_MOVE bytes of both boards, packet after packet with
no wait: medians of 5 repeats of CPU time), which tells the work from what a loop that sleeps
between frames pays on a loaded machine (cold caches); the renderer's part alone, one frame
after a pause of the frame's wire time (as in the loop) and back to back, the cold caches' cost
in this run; and the same pair for an empty call (two reads of the thread's CPU clock around a
call that does nothing), the machine's own floor under every figure taken after a pause.

A quick run sends the first 2.5 s of the trace.
"""

from __future__ import annotations

import statistics
import threading
import time

from crs_study.benchmarks import Figure, median_seconds
from crs_study.benchmarks import _live_landing as landing
from crs_study.clock import RealClock
from crs_study.device import open_device
from crs_study.device.calibration import PulseMap
from crs_study.device.serial_device import SerialDevice
from crs_study.device.virtual_pty import VirtualControllerPty
from crs_study.device.writes import ChannelSplit
from crs_study.geometry.layout import load_layout
from crs_study.live.area import RecognitionArea
from crs_study.live.boards import BoardTap, virtual_boards
from crs_study.live.packet import FingerPacket, decode_packet, encode_packet
from crs_study.live.sender import send_trace
from crs_study.live.session import LiveConfig, LiveSession
from crs_study.live.trace import FingerTrace, digit_trace
from crs_study.rendering.render import Renderer

AREA = "live"
DESCRIPTION = "the live link at 72 packets/s: arrival -> wire -> servos, software per packet"

TARGET_WIRE_MEDIAN_S = 0.040
TARGET_WIRE_P99_S = 0.080
TARGET_IN_PLACE_MEDIAN_S = 0.075
TARGET_SOFTWARE_SHARE = 0.01
QUICK_S = 2.5


def bench_trace(quick: bool):
    """The trace both devices get (module docstring)."""

    trace = digit_trace(9, height_mm=60.0, speed_mm_s=30.0, press_mm=5.0)
    if quick:
        keep = trace.times <= QUICK_S
        trace = FingerTrace(trace.times[keep], trace.xyz[keep], trace.name)
    return trace


def run_session(device, trace, tap=None):
    """A live session on ``device`` (not opened) fed ``trace`` from a sender thread; it ends
    on the sender's silence. Returns the LiveResult."""

    session = LiveSession(device, LiveConfig(listen="127.0.0.1:0", exit_on_silence=True,
                                             silence_s=0.3), tap=tap)
    ready = threading.Event()

    def view(running) -> None:  # called once the port is open: the sender may start
        ready.set()

    session.view = view

    def send() -> None:
        if ready.wait(10.0):
            send_trace(trace, ("127.0.0.1", session.listener.address[1]))

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    result = session.run()
    sender.join(timeout=5.0)
    return result


def _sim(trace):

    return run_session(open_device("sim://", load_layout("crs2d"), record=True), trace)


def _pty(trace):

    layout = load_layout("crs2d")
    boards = virtual_boards(layout, time.monotonic())
    bridges = [VirtualControllerPty(board, baud=9600) for board in boards]
    try:
        device = SerialDevice(layout, [b.open_serial() for b in bridges], RealClock())
        device.url = "serial://" + ",".join(b.port for b in bridges)
        return run_session(device, trace, BoardTap(layout, boards))
    finally:
        for bridge in bridges:
            bridge.close()


def figures(name: str, result) -> list[Figure]:
    """The figures of one run (module docstring)."""
    d = result.latency
    wire = d["frame_wire"].median
    base = "frame wire time (median, this run)"
    ms = 1e3

    def fig(label: str, value: float, target_s: float | None = None, text: str = "",
            unit: str = "ms", baseline: float = wire * ms, passed: bool | None = None
            ) -> Figure:
        if target_s is not None:
            text, passed = f"<= {target_s * ms:g} ms", bool(value <= target_s * ms)
        return Figure(AREA, f"{name}: {label}", value, unit, base, baseline, text, passed)

    share = d["software_share"].median
    figs = [
        fig("arrival->last byte, median", d["wire"].median * ms, TARGET_WIRE_MEDIAN_S),
        fig("arrival->last byte, p99", d["wire"].p99 * ms, TARGET_WIRE_P99_S),
        fig("arrival->servos in place, median", d["in_place"].median * ms,
            TARGET_IN_PLACE_MEDIAN_S),
        fig("software per packet (CPU), median", d["software"].median * ms,
            text=f"ratio < {TARGET_SOFTWARE_SHARE:g}", passed=bool(share < TARGET_SOFTWARE_SHARE)),
        fig("arrival->last byte, p95", d["wire"].p95 * ms),
        fig("display behind newest packet, median", d["newest"].median * ms),
        fig("frames written a second", result.frame_rate_hz, unit="1/s", baseline=1.0 / wire),
    ]
    if result.source == "boards" and name == "pty":
        figs.append(fig("host model error, median |landed - predicted|",
                        abs(d["host_error"].median) * ms))
    return figs


def warm_software_s(trace) -> float:
    """CPU seconds per packet of decode, render, pulses and encode, back to back (median of 5
    repeats over the trace's packets)."""
    import numpy as np


    layout = load_layout("crs2d")
    area, renderer = RecognitionArea.for_layout(layout), Renderer(layout, "crs")
    pulse_map, split = PulseMap.from_layout(layout), ChannelSplit(layout)
    packets = [encode_packet(FingerPacket(1, k, 0.0, x, y, z))
               for k, (x, y, z) in enumerate(trace.xyz.tolist())]
    renderer.render(area.bump(0.0, 0.0, 5.0))  # the beams' tables, built once
    every = [np.arange(len(m)) for m in split.members]

    def pipeline() -> None:
        for data in packets:
            p = decode_packet(data)
            bump = area.bump(p.x_mm, p.y_mm, p.z_mm)
            pulses = pulse_map.to_pulses(renderer.render(bump).setpoints)
            for c in range(len(every)):
                split.frame(c, pulses, every[c], 0)

    return median_seconds(pipeline, repeat=5, timer=time.process_time) / len(packets)


def pressed_placements(trace, quick: bool) -> list[tuple[float, float, float]]:
    """The trace's pressed packets as (x, y, height) in the layout frame, thinned to 20 (quick)
    or 80."""
    area = RecognitionArea.for_layout(load_layout("crs2d"))
    placed = [p for p in (area.place(x, y, z) for x, y, z in trace.xyz.tolist())
              if p is not None and p[2] > 0.0]
    return placed[:: max(1, len(placed) // (20 if quick else 80))]


def cpu_after_pause_s(work, items, pause_s: float) -> tuple[float, float]:
    """Thread CPU seconds of ``work(item)``, median over ``items``: ``(after a pause of
    pause_s, back to back)`` (three passes).

    The live loop sleeps between frames while the machine's other processes run; the pair
    tells what that costs the same work (cold caches) in this run."""
    paused, warm = [], []
    for item in items:
        time.sleep(pause_s)
        start = time.thread_time()
        work(item)
        paused.append(time.thread_time() - start)
    for _ in range(3):
        for item in items:
            start = time.thread_time()
            work(item)
            warm.append(time.thread_time() - start)
    return statistics.median(paused), statistics.median(warm)


def render_work(placed):
    """One live frame's rendering (the renderer's bump path) of a placement, its tables
    built."""
    renderer = Renderer(load_layout("crs2d"), "crs")
    diameter = RecognitionArea.for_layout(renderer.layout).diameter_mm
    renderer.render_bump(placed[0][:2], diameter, placed[0][2])  # the beams' tables

    def work(item) -> None:
        renderer.render_bump(item[:2], diameter, item[2])

    return work


def nothing(item) -> None:
    """The empty work: what timing a call costs, after a pause and back to back."""


def run(quick: bool, traces=()) -> list[Figure]:
    trace = bench_trace(quick)
    out = landing.run(quick, traces)
    for name, runner in (("sim", _sim), ("pty", _pty)):
        result = runner(trace)
        if not result.ok or result.source != "boards":
            raise RuntimeError(f"bench live {name}: {result.stopped_by}: {result.faults}")
        out += figures(name, result)
    wire = next(f.baseline for f in out if f.name == "pty: arrival->last byte, median")
    out.append(Figure(AREA, "software per packet, warm loop (CPU)", warm_software_s(trace) * 1e3,
                      "ms", "frame wire time (median, this run)", wire))
    placed = pressed_placements(trace, quick)
    for what, work in (("render one frame", render_work(placed)), ("an empty call", nothing)):
        paused, warm = cpu_after_pause_s(work, placed, wire * 1e-3)
        for label, seconds in (("after a frame's pause", paused), ("back to back", warm)):
            out.append(Figure(AREA, f"{what} {label} (CPU), median", seconds * 1e3, "ms",
                              "frame wire time (median, this run)", wire))
    return out
