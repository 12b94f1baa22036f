"""The live session: finger packets in over UDP, the bump of Eq. 7 out to the display.

The loop (one thread; the serial device's writer threads put the bytes on the ports)
    1. wait for a datagram, the wire or a deadline (``select``);
    2. read every datagram waiting; each is decoded and either dropped and counted (malformed,
       stale: not newer than the last accepted, as RFC 1982 serial numbers, so the sequence
       may wrap; another stream's while one is shown) or
       accepted: it becomes *the newest*, and the packet it replaces, never shown, is counted
       superseded;
    3. when the wire can take a frame (the last frame's last byte leaves within ``lead_s``),
       the newest packet, moved to where the finger will be when this frame's servos are in
       place (:mod:`crs_study.live.predict`; ``predict.method = "off"``: as it came), is
       rendered (the same :class:`~crs_study.rendering.render.Renderer`, clip
       policy and feed cap as a session's stimuli) and handed to the device, whose calibrated
       limits refuse anything out of range, as in a session. So frames go at the rate the wire
       allows, each carrying the newest position, never a queue of old ones; what goes on the
       wire is the device's write policy (changed channels only, the two boards written
       concurrently: :mod:`crs_study.device.writes`).

A finger outside the recognition area, or not pressing, is a flat display
(:mod:`crs_study.live.area`). The display starts in its neutral pose (a full write, so every
later frame is changed-only).

Stopping safely
    No accepted packet for ``silence_s`` (0.5 s): the display is flattened at once and the
    session keeps listening (a stream that resumes is shown again, from any sequence number: a
    sender restarted with its old stream id is not locked out; a new stream may take over only
    now); with ``exit_on_silence`` the session ends instead. Ctrl-C, SIGTERM, SIGHUP
    (:mod:`crs_study.signals`), the end of ``duration_s`` or ``max_packets``, or a device
    fault end it: the device is closed, which sends the neutral pose and releases the ports.
    A signal after the first (or one while closing) asks for what is already being done: it
    is absorbed (counted in ``signals_while_closing``), and the result comes back as after one.
    A device fault is reported in the result (``stopped_by``, ``faults``), not raised, so what
    was measured is not lost.

Why silence flattens rather than ends the session: a headset streaming over USB pauses now
and then; flattening is what keeps a finger from meeting a bump the scene no longer tracks,
and ending would stop a demonstration at every pause. The option is there for the other choice.
"""

from __future__ import annotations

import math
import select
import signal
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from crs_study.device.base import BAUD_RATE, BITS_PER_BYTE, Device, open_device
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout, load_layout
from crs_study.live.area import PAPER_DIAMETER_MM, RecognitionArea
from crs_study.live.boards import BoardTap, HostModel, ShownFrame
from crs_study.live.errors import LiveError, PacketError
from crs_study.live.landing import FingerHistory
from crs_study.live.link import MAX_BATCH, Listener, parse_address
from crs_study.live.packet import decode_packet, newer
from crs_study.live.predict import PredictConfig, Predictor
from crs_study.live.record import Recorder
from crs_study.live.result import FrameCounts, LatencyLog, LiveResult, PacketCounts
from crs_study.live.timing import FrameTiming
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.render import Renderer
from crs_study.signals import PAUSE_SIGNALS, SignalInterrupt, describe, handling

#: Longest single wait of the loop (s): how often it looks at the clock with nothing to do.
MAX_WAIT_S = 0.05
#: How often the loop reads the boards while a frame's landing is overdue (s).
POLL_S = 0.005
#: How often the live view is redrawn (s).
VIEW_PERIOD_S = 0.25
#: Frames counted in the live view's recent window.
VIEW_WINDOW = 300
#: Longest the session waits at its end for the last frame to leave the wire (s).
DRAIN_S = 1.0


@dataclass(frozen=True)
class LiveConfig:
    """How a live session runs (module docstring). Times in seconds, lengths in mm."""

    listen: str = "127.0.0.1:5005"
    condition: str = "crs"
    diameter_mm: float = PAPER_DIAMETER_MM
    max_height_mm: float | None = None  # None: the pixels' travel
    area_margin_mm: float = 0.0
    silence_s: float = 0.5
    exit_on_silence: bool = False
    move_ms: int = 0  # SERVO_MOVE time: 0, as fast as the servos go (the position is now)
    lead_s: float = 0.002  # hand a frame over this long before the wire frees
    duration_s: float | None = None
    max_packets: int | None = None
    record: str | None = None
    predict: PredictConfig = field(default_factory=PredictConfig)

    def __post_init__(self) -> None:
        parse_address(self.listen, "listen address")
        if not isinstance(self.predict, PredictConfig):
            raise LiveError(f"predict: expected a PredictConfig, got {self.predict!r}")

        def number(name: str, low: float, high: float, optional: bool = False) -> None:
            value = getattr(self, name)
            if optional and value is None:
                return
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not (math.isfinite(value) and low <= value <= high):
                raise LiveError(f"{name}: expected a number in [{low:g}, {high:g}], "
                                f"got {value!r}")

        number("silence_s", 0.01, 3600.0)
        number("lead_s", 0.0, 0.1)
        number("duration_s", 0.001, 86400.0, optional=True)
        number("area_margin_mm", 0.0, 1000.0)
        number("diameter_mm", 1.0, 1000.0)
        number("max_height_mm", 0.001, 100.0, optional=True)
        if isinstance(self.move_ms, bool) or not isinstance(self.move_ms, int) \
                or not 0 <= self.move_ms <= 30000:
            raise LiveError(f"move_ms: expected a whole number of ms 0..30000, "
                            f"got {self.move_ms!r}")
        if self.max_packets is not None and (isinstance(self.max_packets, bool) or not
                                             isinstance(self.max_packets, int)
                                             or not 1 <= self.max_packets <= 10**9):
            raise LiveError(f"max_packets: expected a whole number 1..1e9, "
                            f"got {self.max_packets!r}")


class LiveSession:
    """One live session on ``device`` (not yet opened; the session opens and closes it).

    ``tap``: where frame landings come from (:class:`~crs_study.live.boards.BoardTap` for
    virtual boards given by the caller, e.g. pty boards); default: the simulated device's own
    boards for ``sim://``, the device's model otherwise. ``view``: called with the session
    about every :data:`VIEW_PERIOD_S` (the terminal view).
    """

    def __init__(self, device: Device, config: LiveConfig | None = None, tap=None,
                 view=None) -> None:

        self.device = device
        self.config = config or LiveConfig()
        self.layout: Layout = device.layout
        self.area = RecognitionArea.for_layout(self.layout, self.config.area_margin_mm,
                                               self.config.diameter_mm,
                                               self.config.max_height_mm)
        # clip policy and feed cap as a session's, the cap's room for this device's dead-band
        self.renderer = Renderer(self.layout, self.config.condition,
                                 wire=WireSlack.for_device(device))
        self.tap = tap
        self.view = view
        self.neutral = self.layout.neutral_setpoints()
        self.predictor = Predictor(self.config.predict)
        self.timing = FrameTiming(device, self.config.move_ms)
        self.finger = FingerHistory()
        self.byte_s = BITS_PER_BYTE / getattr(getattr(device, "options", None), "baud",
                                              BAUD_RATE)
        self.packets = PacketCounts()
        self.frames = FrameCounts(bytes=[0] * len(self.layout.controllers))
        self.log = LatencyLog()
        self.state = "waiting"  # waiting (no packet yet), live, silent
        self.stream: int | None = None
        self.last_sequence = -1
        self.last_arrival = -math.inf
        self.newest = None  # (packet, datagram, decode seconds) not yet shown
        self.superseded: list[float] = []  # their arrivals, for the next frame
        self.next_frame_at = -math.inf
        self.silences = 0
        self.frame_index = 0
        self.flat_shown = True
        self.stopped_by = ""
        self.stopping = False
        self.signals_while_closing = 0  # stop signals that came while the session closed
        self.faults: list[str] = []
        self.started = self.ended = math.nan
        self.listener: Listener | None = None
        self.recorder: Recorder | None = None

    # -- running -------------------------------------------------------------------------

    def run(self) -> LiveResult:
        """Listen, show, stop safely (module docstring); the result, also after a fault."""
        if getattr(self.device.clock, "is_virtual", False):
            raise LiveError("live mode runs on the real clock: packets arrive in real time")
        host, port = parse_address(self.config.listen, "listen address")
        self.listener = Listener(host, port)
        try:
            with handling(self._on_signal, PAUSE_SIGNALS):
                try:
                    self.start()
                    self._loop()
                except KeyboardInterrupt as interrupt:
                    self.stopped_by = describe(interrupt)
                except DeviceError as fault:
                    self.stopped_by = "device fault"
                    self.faults.append(str(fault))
                finally:
                    self.stopping = True
                    self._close()
        finally:
            self.listener.close()
        return self.result()

    def _on_signal(self, signum: int, frame: object) -> None:
        """The first stop signal stops the loop (as Ctrl-C, :mod:`crs_study.signals`); any
        later one is counted only: it would ask for the close already under way."""
        if self.stopping:
            self.signals_while_closing += 1
            return
        self.stopping = True
        raise KeyboardInterrupt if signum == signal.SIGINT else SignalInterrupt(signum)

    def start(self) -> None:
        """Open the device and show the neutral pose (:meth:`run` does; a simulation on a
        virtual clock calls :meth:`start`, :meth:`take`, :meth:`show` and :meth:`finish`)."""
        self.started = self.device.clock.now()
        if self.config.record:
            header = {"layout": self.layout.name, "condition": self.config.condition,
                      "device": getattr(self.device, "url", type(self.device).__name__),
                      "listen": self.listen_address, "area": self.area.describe(),
                      "config": asdict(self.config), "t0": self.started,
                      "predictor": self.config.predict.describe()}
            self.recorder = Recorder(self.config.record, header, self.started)
        # the first rendering builds the beams' tables (~0.2 s): not on a packet's time
        self.renderer.render(self.area.bump(0.0, 0.0, self.area.max_height_mm))
        self.device.open()
        if self.tap is None:
            boards = getattr(self.device, "boards", None)
            if boards and all(getattr(b, "record", False) for b in boards):
                self.tap = BoardTap(self.layout, boards,
                                    advance=lambda t: self.device.displayed_setpoints(t))
            else:
                self.tap = HostModel()
        self._hand_over(self.neutral, "start", None, 0.0)

    @property
    def listen_address(self) -> str:
        if self.listener is None:
            return self.config.listen
        host, port = self.listener.address
        return f"{host}:{port}"

    def _loop(self) -> None:
        config = self.config
        end_at = self.started + config.duration_s if config.duration_s else math.inf
        view_at = self.started
        while True:
            now = time.monotonic()
            if now >= end_at:
                self.stopped_by = "duration"
                return
            if config.max_packets is not None and self.packets.received >= config.max_packets \
                    and self.newest is None:
                self.stopped_by = "max packets"
                return
            landing = self.tap.next_due()  # a landing the boards have not shown yet: look often
            wake = min(end_at, view_at if self.view else math.inf,
                       landing if landing > now else now + POLL_S)
            if self.newest is not None:
                wake = min(wake, self.next_frame_at)
            if self.state == "live":
                wake = min(wake, self.last_arrival + config.silence_s)
            ready, _, _ = select.select([self.listener], [], [],
                                        min(max(wake - now, 0.0), MAX_WAIT_S))
            if ready:
                left = (MAX_BATCH if config.max_packets is None
                        else config.max_packets - self.packets.received)
                for datagram in self.listener.receive(left):
                    self.take(datagram)
            now = time.monotonic()
            if self.newest is not None and now >= self.next_frame_at:
                self.show()
            if self.state == "live" and now >= self.last_arrival + config.silence_s:
                self.state = "silent"
                self.silences += 1
                if config.exit_on_silence:
                    self.stopped_by = "silence"
                    return
                if not self.flat_shown:
                    self._hand_over(self.neutral, "silence", None, 0.0)
            self.finish(self.tap.poll(now))
            if self.view and now >= view_at:
                self.view(self)
                view_at = now + VIEW_PERIOD_S

    # -- packets -------------------------------------------------------------------------

    def take(self, datagram) -> None:
        counts = self.packets
        counts.received += 1
        start = time.thread_time()
        try:
            packet = decode_packet(datagram.data)
        except PacketError as exc:
            counts.malformed += 1
            if self.recorder:
                self.recorder.packet(datagram, "malformed", reason=str(exc))
            return
        decode_s = time.thread_time() - start
        status = "accepted"
        if self.state != "live":  # nothing shown now: any stream (re)starts its sequence
            self.stream, self.last_sequence = packet.stream, -1
            self.predictor.reset()
        elif packet.stream != self.stream:
            status = "other_stream"
        if status == "accepted" and not newer(packet.sequence, self.last_sequence):
            status = "stale"
        if self.recorder:
            self.recorder.packet(datagram, status, packet)
        if status != "accepted":
            setattr(counts, status, getattr(counts, status) + 1)
            return
        counts.accepted += 1
        if not self.area.contains(packet.x_mm, packet.y_mm):
            counts.out_of_area += 1
        self.last_sequence = packet.sequence
        self.last_arrival = datagram.arrival
        self.predictor.update(datagram.arrival, packet.x_mm, packet.y_mm, packet.z_mm)
        self.finger.add(datagram.arrival, packet.x_mm, packet.y_mm, packet.z_mm)
        self.state = "live"
        if self.newest is not None:
            counts.superseded += 1
            self.superseded.append(self.newest[1].arrival)
        self.newest = (packet, datagram, decode_s)

    def show(self) -> None:
        packet, datagram, decode_s = self.newest
        self.newest = None
        start = time.thread_time()
        now = self.device.clock.now()
        raw = (packet.x_mm, packet.y_mm, packet.z_mm)
        if self.config.predict.on:  # late binding: rendered for when it will be in place
            shown, rendered_for, (kind, setpoints, clamped) = self.timing.bind(
                now, self.predictor, raw, self._render)
        else:
            shown, rendered_for = self.predictor.at(now, raw)
            kind, setpoints, clamped = self._render(shown)
        self.packets.shown += 1
        frame = self._hand_over(setpoints, kind, packet.sequence, decode_s, start, clamped,
                                shown if kind == "finger" else None, rendered_for)
        frame.arrivals = [datagram.arrival, *self.superseded]
        self.superseded = []

    def _render(self, position: tuple) -> tuple[str, np.ndarray, bool]:
        """(kind, setpoints, clamped) of the bump under a finger at ``position``."""
        placed = self.area.place(*position)
        if placed is None or placed[2] <= 0.0:
            return "flat", self.neutral, False
        rendering = self.renderer.render_bump(placed[:2], self.area.diameter_mm, placed[2])
        return "finger", rendering.setpoints, bool(rendering.clamped)

    def _hand_over(self, setpoints: np.ndarray, kind: str, sequence: int | None,
                   decode_s: float, start: float | None = None, clamped: bool = False,
                   shown: tuple | None = None, rendered_for: float = math.nan) -> ShownFrame:
        report = self.device.send(setpoints, self.config.move_ms)
        self.timing.handed(report.commanded_at, setpoints, report.wire_done_at)
        software = decode_s + (time.thread_time() - start) if start is not None else math.nan
        frame = ShownFrame(self.frame_index, kind, setpoints, report.commanded_at,
                           report.wire_done_at, report.bytes_sent, sequence,
                           software_s=software, shown=shown, rendered_for=rendered_for)
        self.frame_index += 1
        counts = self.frames
        counts.handed += 1
        if kind in ("finger", "flat", "silence"):
            setattr(counts, kind, getattr(counts, kind) + 1)
        counts.clamped += clamped
        if frame.wrote:
            counts.written += 1
            counts.bytes = [a + b for a, b in zip(counts.bytes, report.bytes_sent, strict=True)]
            self.next_frame_at = report.wire_done_at - self.config.lead_s
        else:
            counts.unchanged += kind != "start"
        self.flat_shown = kind != "finger"
        self.tap.add(frame)
        if self.recorder:
            self.recorder.frame(frame, clamped)
        return frame

    def finish(self, frames: list[ShownFrame]) -> None:
        """Count the frames whose bytes have arrived (or never will)."""
        for frame in frames:
            if self.recorder:
                self.recorder.landed(frame)
            if frame.lost:
                self.frames.lost += 1
            if frame.kind == "close" or not frame.arrivals:
                continue
            shown = frame.wrote and not frame.lost
            for arrival in frame.arrivals:
                self.log.newest.add(frame.done_at - arrival if shown else math.nan)
            if frame.kind == "finger" and frame.wrote and not frame.lost:
                self.log.add(frame, max(frame.bytes_sent) * self.byte_s,
                             self.finger.error(frame))

    # -- stopping ------------------------------------------------------------------------

    def _close(self) -> None:
        """Neutral pose, ports released; the last landings read."""
        if self.tap is None:  # the device did not open
            self.ended = time.monotonic()
            self._close_device()
            self._close_recording()
            return
        if self.stopped_by in ("duration", "max packets", "silence"):
            # let the last frame leave the wire before the neutral pose replaces it
            deadline = time.monotonic() + DRAIN_S
            while time.monotonic() < min(self.next_frame_at + self.config.lead_s, deadline):
                time.sleep(0.001)
        self.ended = time.monotonic()
        neutral = ShownFrame(self.frame_index, "close", self.neutral, self.ended,
                             self.ended + DRAIN_S, (1,) * len(self.layout.controllers))
        self.tap.add(neutral)
        self._close_device()
        deadline = time.monotonic() + DRAIN_S
        while True:
            now = time.monotonic()
            self.finish(self.tap.poll(now, flush=now >= deadline))
            if not getattr(self.tap, "pending", None) or now >= deadline:
                break
            time.sleep(0.005)
        self._close_recording()

    def _close_recording(self) -> None:
        if self.recorder:
            self.recorder.end(self.result().to_json())
            self.recorder.close()

    def _close_device(self) -> None:
        before = len(self.device.faults)
        try:
            self.device.close()
        except DeviceError as exc:
            self.faults.append(f"close: {exc}")
        self.faults.extend(f for f in self.device.faults[before:] if f not in self.faults)

    def result(self) -> LiveResult:
        ended = self.ended if math.isfinite(self.ended) else time.monotonic()
        return LiveResult(
            device=getattr(self.device, "url", type(self.device).__name__),
            layout=self.layout.name, condition=self.config.condition,
            listen=self.listen_address, area=self.area.describe(),
            source=getattr(self.tap, "source", "host model"),
            duration_s=ended - self.started if math.isfinite(self.started) else 0.0,
            stopped_by=self.stopped_by or "running", faults=list(self.faults),
            packets=self.packets, frames=self.frames, silences=self.silences,
            unmatched_board_frames=getattr(self.tap, "unmatched", 0),
            kernel_stamps=bool(self.listener and self.listener.kernel_stamps),
            log=self.log, config=asdict(self.config))


def serve(device: str | Device, layout: str | Layout = "crs2d",
          config: LiveConfig | None = None, view=None, **device_options) -> LiveResult:
    """Run a live session (:class:`LiveSession`) on ``device``: a URL (``sim://``, the boards'
    own record then times the frames; ``serial://...``) or a Device not yet opened."""
    if isinstance(device, str):
        layout = load_layout(layout) if isinstance(layout, str) else layout
        if device.startswith("sim://"):
            device_options.setdefault("record", True)
        device = open_device(device, layout, **device_options)
    return LiveSession(device, config, view=view).run()
