"""One LSC board's serial port: its options, its writer and reader threads.

Ports run 9600 baud 8N1 with read and write timeouts. Each port has a writer thread, so
controllers are written concurrently. :meth:`~crs_study.device.serial_device.SerialDevice.send`
converts setpoints to whole-us pulses (refusing anything outside calibrated limits before any
byte moves), hands them to the port's :class:`~.writes.PortWrites` as its *latest wanted pulses*
and returns at once. The writer thread writes what the policy decides, when it decides it: once
the wire is free, one SERVO_MOVE of the channels whose wanted pulse differs from the last sent
by more than the dead-band; a frame handed over while a previous one still waits replaces it
(merged, never queued), so latency never grows. The full refresh rides on the first write
``refresh_s`` after the last full one (a frame the board lost or garbled is repaired; why it
never goes on its own: :mod:`~crs_study.device.writes`). The simulated device and the wire
estimate run the same policy, so they put the same bytes on the wire. With ``pace`` (the
default) the writer writes once the wire is free: the bytes already written have had their time
at ``10 / baud`` s a byte (less ``lead_s``, so the next frame follows without a gap despite
wake-up jitter) *and* the port's output buffer (``out_waiting``) holds at most
:data:`OUT_WAITING_LOW_BYTES`. The model alone is not enough: on a wire slower than nominal (an
adapter's baud error, gaps between bytes) bytes would pile up in the OS buffer and latency grow
without bound; ``out_waiting`` alone is not either (a USB adapter's chip FIFO is not counted). A
port without ``out_waiting`` (AttributeError, NotImplementedError) is paced by the model; one
whose buffer does not drain within ``write_timeout_s`` has failed. Linux ptys report 0
(:mod:`~crs_study.device.virtual_pty` has a port that counts). Without ``pace`` the writer
writes as soon as a frame is handed over and relies on the port's own blocking (for ports that
throttle themselves).

:class:`~crs_study.device.serial_device.SerialDevice` holds one :class:`SerialPort` per
controller.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, fields
from typing import Any

import serial

from crs_study.clock import Clock
from crs_study.device import protocol_lscsim
from crs_study.device.base import (
    BITS_PER_BYTE,
    LOW_BATTERY_MV,
)
from crs_study.device.codec import (
    MOVE_TIME_MAX_MS,
    BatteryVoltage,
    Direction,
    get_battery_voltage,
)
from crs_study.device.decoder import FrameDecoder
from crs_study.device.writes import (
    DEFAULT_DEADBAND_US,
    DEFAULT_REFRESH_S,
    ChannelSplit,
    PortWrites,
    WritePolicy,
)
from crs_study.errors import DeviceError

#: The writer writes once the port's output buffer (``out_waiting``) holds at most this many
#: bytes (about 4 ms at 9600 baud: the next frame follows without a gap, never behind a queue).
OUT_WAITING_LOW_BYTES = 4

#: Longest single wait of a writer thread (s): it looks at its port again at least this often.
MAX_WAIT_S = 0.5

#: Baud rates a port may be opened at (the LSC boards take 9600 only; LSC protocol).
MIN_BAUD, MAX_BAUD = 300, 4_000_000
#: Longest full-refresh interval (s), as the simulated device's; longer is a typo, and a
#: wait that long overflows the platform's time_t.
MAX_REFRESH_S = 3600.0
#: Longest read, write or battery timeout (s): a port silent for a minute has failed.
MAX_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class SerialOptions:
    """Options of :class:`SerialDevice` (all times in seconds unless named otherwise)."""

    move_ms: int | None = None  # SERVO_MOVE time when send() gets none; None: one full frame
    refresh_s: float = DEFAULT_REFRESH_S  # a frame this long after the last full one: full
    deadband_us: int = DEFAULT_DEADBAND_US  # resend a channel when it moved more than this
    baud: int = 9600  # the LSC boards support 9600 only (LSC protocol)
    pace: bool = True  # write no faster than the wire carries bytes
    lead_s: float = 0.002  # write this early before the wire frees, against wake-up jitter
    write_timeout_s: float = 0.5
    read_timeout_s: float = 0.05
    battery_timeout_s: float = 0.3  # how long to wait for a battery reply on open
    heartbeat_timeout_s: float = 0.3  # how long a heartbeat waits for every board's answer
    check_battery: bool = True
    min_battery_mv: int = LOW_BATTERY_MV
    neutral_move_ms: int = 500  # move time of the neutral pose on close

    def __post_init__(self) -> None:
        def need(name: str, ok: bool, expected: str) -> None:
            if not ok:
                raise DeviceError(f"serial option {name}: expected {expected}, "
                                  f"got {getattr(self, name)!r}")

        def within(name: str, low: float, high: float, open_low: bool = False) -> None:
            x = getattr(self, name)
            ok = is_finite_number(x) and (low < x if open_low else low <= x) and x <= high
            need(name, ok, f"a number of seconds in {'(' if open_low else '['}{low:g}, {high:g}]")

        within("refresh_s", 0.0, MAX_REFRESH_S)
        within("lead_s", 0.0, 1.0)
        for name in ("write_timeout_s", "read_timeout_s", "battery_timeout_s",
                     "heartbeat_timeout_s"):
            within(name, 0.0, MAX_TIMEOUT_S, open_low=True)
        need("move_ms", self.move_ms is None or is_whole(self.move_ms, 0, MOVE_TIME_MAX_MS),
             f"a whole number of ms 0..{MOVE_TIME_MAX_MS}")
        need("neutral_move_ms", is_whole(self.neutral_move_ms, 0, MOVE_TIME_MAX_MS),
             f"a whole number of ms 0..{MOVE_TIME_MAX_MS}")
        need("deadband_us", is_whole(self.deadband_us, 0, 100), "a whole number of us 0..100")
        need("baud", is_whole(self.baud, MIN_BAUD, MAX_BAUD), f"a baud rate {MIN_BAUD}..{MAX_BAUD}")
        need("min_battery_mv", is_whole(self.min_battery_mv, 0, 65535), "a whole number of mV")

    @classmethod
    def from_options(cls, options: dict[str, Any]) -> SerialOptions:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise DeviceError(f"unknown serial option(s) {', '.join(map(repr, unknown))}; "
                              f"known: {', '.join(sorted(known))}")
        return cls(**options)


def is_finite_number(x: object) -> bool:
    """``x`` is a finite int or float (not a bool)."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def is_whole(x: object, low: int, high: int) -> bool:
    """``x`` is an int (not a bool) in [low, high]."""
    return isinstance(x, int) and not isinstance(x, bool) and low <= x <= high


def serial_for_spec(spec: str, **settings: Any) -> Any:
    """``serial.serial_for_url(spec, **settings)``, with the simulator's ``lscsim://`` scheme
    registered first when ``spec`` uses it (so a dry run of the serial path needs no code)."""
    if spec.startswith("lscsim://"):
        protocol_lscsim.register()
    return serial.serial_for_url(spec, **settings)


def parse_serial_url(url: str) -> list[str]:
    """The port specs of ``serial://PORT[,PORT...]`` (module docstring)."""
    if not url.startswith("serial://"):
        raise DeviceError(f"serial device URL: expected serial://PORT[,PORT...], got {url!r}")
    specs = url[len("serial://"):].split(",")
    if any(not s.strip() for s in specs):
        raise DeviceError(f"serial device URL {url!r}: expected one port per controller, "
                          f"separated by commas, got an empty port")
    return [s.strip() for s in specs]


class SerialPort:
    """One controller's port: latest wanted pulses, a writer thread, a reader thread.

    ``index`` is the controller's place in the device file (its channels are
    ``split.members[index]``); ``spec`` a pyserial URL or path, or a ready serial-like object.
    """

    def __init__(self, index: int, name: str, spec: str | Any, options: SerialOptions,
                 clock: Clock, split: ChannelSplit, policy: WritePolicy) -> None:
        self.index = index
        self.name = name
        self.options = options
        self.clock = clock
        self.split = split
        self.spec = spec if isinstance(spec, str) else getattr(spec, "name", repr(spec))
        self.serial: Any = None if isinstance(spec, str) else spec
        self.cond = threading.Condition()
        # held around every serial.write: two threads writing one port could interleave the
        # bytes of two frames, and an LSC frame has no checksum to catch it
        self.write_lock = threading.Lock()
        # what goes on this port, and when (the policy; read and changed under ``cond``)
        self.writes = PortWrites(len(split.members[index]), policy)
        self.reports_backlog = True  # until out_waiting proves unsupported
        self.writing_since: float | None = None
        self.error: BaseException | None = None
        self.stopping = False
        self.frames_written = 0
        self.bytes_written = 0
        self.battery_mv: int | None = None
        self.battery_replies = 0  # battery answers the reader thread decoded (heartbeats)
        self.decoder = FrameDecoder(Direction.BOARD)
        self.threads: list[threading.Thread] = []

    @property
    def label(self) -> str:
        return f"controller {self.name} on {self.spec}"

    # -- opening -------------------------------------------------------------------------

    def open(self) -> None:
        options = self.options
        if self.serial is None:
            try:
                self.serial = serial_for_spec(
                    self.spec, baudrate=options.baud, bytesize=serial.EIGHTBITS,
                    parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                    timeout=options.read_timeout_s, write_timeout=options.write_timeout_s,
                    # a second program on the same board (a `device neutral` run during a
                    # session) would interleave its frames with ours: lock the port (flock)
                    exclusive=True,
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                raise DeviceError(f"{self.label}: cannot open the port: {exc}") from None

    def query_battery(self) -> int | None:
        """Ask the board for its voltage; None when it does not answer in time."""
        options = self.options
        try:
            self.serial.reset_input_buffer()
            query = get_battery_voltage()
            self.serial.write(query)
            with self.cond:  # on the wire ahead of any frame
                self.writes.written(self.clock.now(), len(query))
            deadline = time.monotonic() + options.battery_timeout_s
            while time.monotonic() < deadline:
                data = self.serial.read(max(1, self.serial.in_waiting))
                # a read that times out empty: the line is quiet, the reply (if any) is in;
                # the decoder decides a frame it held back behind a possible false header
                for frame in self.decoder.feed(data) if data else self.decoder.idle():
                    if isinstance(frame.message, BatteryVoltage):
                        return frame.message.millivolts
        except Exception as exc:  # noqa: BLE001 - pyserial raises several kinds
            raise DeviceError(f"{self.label}: port failed during the battery check: {exc}"
                              ) from None
        return None

    def start(self) -> None:
        for target, kind in ((self._write_loop, "writer"), (self._read_loop, "reader")):
            thread = threading.Thread(target=target, name=f"lsc-{kind}-{self.name}", daemon=True)
            thread.start()
            self.threads.append(thread)

    # -- writing -------------------------------------------------------------------------

    def _write_loop(self) -> None:
        """Write what the policy (:attr:`writes`) decides, when it decides it."""
        clock, options, writes = self.clock, self.options, self.writes
        byte_s = BITS_PER_BYTE / options.baud
        draining_since: float | None = None  # real time the backlog was first seen too long
        while True:
            with self.cond:
                while True:
                    if self.stopping or self.error is not None:
                        return  # close() waited for the neutral pose before stopping
                    now = clock.now()
                    # a waiting frame goes once the wire is free (or at once, unpaced)
                    at = (writes.next_write_at() - options.lead_s) if options.pace else (
                        now if writes.pending else math.inf)
                    if at <= now:
                        break
                    # a hand-over, a stop or (a stepping clock in tests) the time moving
                    # on notifies the condition
                    self.cond.wait(min(at - now, MAX_WAIT_S))
            # the model says the wire is free; the port may know better (a wire slower than
            # nominal): wait for its output buffer to drain, the wanted frame merging meanwhile
            backlog = self._backlog() if options.pace else 0
            if backlog > OUT_WAITING_LOW_BYTES:
                if draining_since is None:
                    draining_since = time.monotonic()
                elif time.monotonic() - draining_since > options.write_timeout_s:
                    with self.cond:
                        self.error = TimeoutError(
                            f"output not draining: {backlog} bytes still waiting after "
                            f"{time.monotonic() - draining_since:.2f} s (write_timeout_s)")
                        self.cond.notify_all()
                    return
                time.sleep(min(max((backlog - OUT_WAITING_LOW_BYTES) * byte_s, 1e-3), 0.02))
                continue
            draining_since = None
            with self.cond:
                now = clock.now()
                write = writes.take(now)
                data = b"" if write is None else self.split.write_bytes(self.index, write)
                self.writing_since = now if data else None
            if not data:
                continue
            try:
                with self.write_lock:
                    self.serial.write(data)
            except Exception as exc:  # noqa: BLE001 - SerialException, OSError, timeouts
                with self.cond:
                    self.error = exc
                    self.writing_since = None
                    self.cond.notify_all()
                return
            with self.cond:
                self.writing_since = None
                self.frames_written += 1
                self.bytes_written += len(data)
                self.cond.notify_all()

    def _backlog(self) -> int:
        """Bytes the port still holds for the wire (``out_waiting``); 0 where it cannot say."""
        if not self.reports_backlog:
            return 0
        try:
            return int(self.serial.out_waiting)
        except (AttributeError, NotImplementedError):
            self.reports_backlog = False  # e.g. socket://: pace by the model alone
            return 0
        except Exception:  # noqa: BLE001 - a failing port: the write that follows says why
            return 0

    def _read_loop(self) -> None:
        while True:
            with self.cond:
                if self.stopping or self.error is not None:
                    return
            try:
                data = self.serial.read(max(1, self.serial.in_waiting))
            except Exception as exc:  # noqa: BLE001 - a vanished port raises several kinds
                with self.cond:
                    if not self.stopping:
                        self.error = exc
                    self.cond.notify_all()
                return
            for frame in self.decoder.feed(data) if data else self.decoder.idle():
                if isinstance(frame.message, BatteryVoltage):
                    with self.cond:
                        self.battery_mv = frame.message.millivolts
                        self.battery_replies += 1
                        self.cond.notify_all()

    # -- the heartbeat ---------------------------------------------------------------------

    def ask_battery(self) -> int:
        """Write GET_BATTERY_VOLTAGE between two frames (never inside one); returns how many
        answers had come before, for :meth:`battery_answer`."""
        query = get_battery_voltage()
        with self.cond:
            before = self.battery_replies
        try:
            with self.write_lock:
                self.serial.write(query)
        except Exception as exc:  # noqa: BLE001 - SerialException, OSError, timeouts
            raise DeviceError(f"{self.label}: port failed asking for the battery: {exc}"
                              ) from None
        with self.cond:  # the pacing model counts the query's bytes on the wire
            self.writes.written(self.clock.now(), len(query))
            self.cond.notify_all()
        return before

    def battery_answer(self, before: int, deadline: float) -> int | None:
        """The battery answer after the ``before``-th, once the reader thread decodes it;
        None when none comes by ``deadline`` (``time.monotonic``) or the port failed."""
        with self.cond:
            while self.battery_replies == before and self.error is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(min(left, 0.05))
            return self.battery_mv if self.battery_replies > before else None

    # -- status and shutdown ---------------------------------------------------------------

    def check(self, now: float) -> None:
        """Raise DeviceError if this port failed or its writer is stuck."""
        if self.error is not None:
            raise DeviceError(f"{self.label}: port failed: {self.error}")
        stuck = self.options.write_timeout_s + 0.5
        if self.writing_since is not None and now - self.writing_since > stuck:
            raise DeviceError(f"{self.label}: a write has not finished for "
                              f"{now - self.writing_since:.2f} s (port stalled)")
        if self.threads and not all(t.is_alive() for t in self.threads) and not self.stopping:
            raise DeviceError(f"{self.label}: the port's I/O thread stopped")

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait (real time) until what was handed over has been written; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while (self.writes.pending or self.writing_since is not None) \
                    and self.error is None:
                left = deadline - time.monotonic()
                if left <= 0 or not any(t.is_alive() for t in self.threads[:1]):
                    return False
                self.cond.wait(min(left, 0.05))
            return self.error is None

    def stop(self) -> None:
        with self.cond:
            self.stopping = True
            self.cond.notify_all()
        for thread in self.threads:
            thread.join(timeout=self.options.write_timeout_s + 1.0)

    def close(self) -> None:
        if self.serial is not None:
            try:
                self.serial.close()
            except Exception:  # noqa: BLE001 - closing a vanished port may fail; it is gone
                pass
