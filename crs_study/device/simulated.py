"""SimulatedDevice: the serial device's bytes, decoded by virtual LSC-24 boards, on any clock.

The device turns setpoints into LSC frames exactly as :class:`SerialDevice` does (the same
calibration, write policy and codec), "puts them on a wire" that takes ``10 / baud`` seconds
a byte, and hands each frame's bytes to a :class:`~.virtual_controller.VirtualController`
(one per controller in the device file) at the time its last byte arrives. The boards decode
the bytes and move model servos; :meth:`SimulatedDevice.displayed_setpoints` reads the servo
positions back through the inverse calibration, which is what the participant's skin meets.

No threads, no sleeping: the wire and the servos are computed, so the device runs on a
:class:`~crs_study.clock.VirtualClock` as fast as the computer allows, and on a
:class:`~crs_study.clock.RealClock` in step with wall time.

The wire (per controller port)
    What goes on each wire, and when, is the host's write policy (:mod:`~.writes`), the very
    code that drives the serial device's writer threads: a frame sent while the wire is busy
    waits, a newer one replaces it (*merged*, ``FrameReport.merged``), never queued; when the
    wire frees, the channels whose latest wanted pulse differs from the last sent by more than
    the dead-band go out as one frame; the full refresh rides on the first frame written
    ``refresh_s`` after the last full one. A write of ``b`` bytes occupies the wire for
    ``b * 10 / baud`` s and reaches the board when its last byte does. Latency therefore never
    exceeds two frame times. ``FrameReport.wire_done_at`` of a waiting frame is its predicted
    end.

The battery
    :meth:`SimulatedDevice.open` and :meth:`SimulatedDevice.battery_mv` ask every board as the
    serial device does: GET_BATTERY_VOLTAGE goes on the wire once it is free, the board
    answers bytes, which travel back (the wire's garbage and a vanished port apply both ways)
    and the host's streaming decoder reads them, the line then going quiet. The clock waits
    for the replies. No readable answer: None and a :class:`~.base.DeviceWarning` on open;
    below :data:`LOW_BATTERY_MV`: a DeviceError.

The options (the ``sim://`` URL's faults and timings) are :class:`~.sim_options.SimOptions`.

Faults, as the caller sees them
    * disconnect: :meth:`send` at or after the time raises ``DeviceError("... port vanished
      ...")`` at once (bytes of a frame still on the wire at that moment are cut off and the
      board counts the stub as a bad frame); :meth:`close` still attempts the neutral pose,
      swallows the failure and releases everything.
    * garbage: the boards' decoders resynchronise; bad frames are counted per board
      (:attr:`VirtualController.bad_frames`). No checksum protects an LSC frame, so garbage
      inside a frame can move a servo wrongly until the next frame for it (as on hardware).
    * stall: the servo stays where it was; :meth:`displayed_setpoints` shows it there. Nothing
      is raised (a PWM servo gives no feedback).
    * brown-out: servos go limp and sink to base, the board ignores moves and reports
      :data:`~.virtual_controller.BROWNOUT_BATTERY_MV`; the next :meth:`send` raises
      ``DeviceError("... brown-out ...")`` (the decision: a fault is an exception, like a
      vanished port, so the runner's one ``except DeviceError`` records ``device_fault``).
    * hang: the board stops reading; nothing is raised on :meth:`send` (the LSC protocol
      acknowledges no move), only the heartbeat (:meth:`heartbeat_ask`), which the runner
      asks at every trial boundary, finds the board silent and raises.
      Every fault met is also appended to :attr:`SimulatedDevice.faults`.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from crs_study.clock import Clock
from crs_study.device.base import (
    BITS_PER_BYTE,
    LOW_BATTERY_MV,
    Device,
    DeviceWarning,
    FrameReport,
    default_move_ms,
    servo_move_bytes,
)
from crs_study.device.calibration import PulseMap
from crs_study.device.codec import BatteryVoltage, Direction, get_battery_voltage
from crs_study.device.decoder import FrameDecoder
from crs_study.device.schedule import warn_if_unbalanced
from crs_study.device.sim_options import SimOptions, controller_names
from crs_study.device.virtual_boards import board_specs
from crs_study.device.virtual_controller import (
    ServoBank,
    VirtualController,
    clear_decode_cache,
)
from crs_study.device.writes import (
    ChannelSplit,
    PortWrites,
    Write,
    WritePolicy,
)
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout

#: The battery reply ``55 55 04 0F lo hi`` (LSC protocol): how long the host waits for it.
BATTERY_REPLY_BYTES = 6


class _Wire:
    """One port: the write policy's state, what is on the wire, and the board at the far end."""

    def __init__(self, board: VirtualController, writes: PortWrites) -> None:
        self.board = board
        self.writes = writes  # what goes on this wire, and when (the policy)
        self.flying: bytes = b""  # the bytes on the wire, not yet delivered
        self.start_at = -math.inf  # when their first byte went out
        self.end_at = -math.inf  # when their last byte arrives
        self.vanish_at = math.inf
        self.cut = False  # the port vanished
        self.inbox: list[tuple[float, bytes]] = []  # the board's replies: (arrival, bytes)
        self.decoder = FrameDecoder(Direction.BOARD)  # the host's end of the port


class SimulatedDevice(Device):
    """A CRS display on virtual LSC-24 boards (module docstring). Build with :meth:`from_url`."""

    def __init__(self, layout: Layout, clock: Clock | None = None,
                 options: SimOptions | None = None, record: bool = False) -> None:
        super().__init__(layout, clock)
        self.options = options or SimOptions()
        self.url = "sim://"
        self.record = record
        self.pulse_map = PulseMap.from_layout(layout)
        self.split = ChannelSplit(layout, cache=True)
        self.policy = WritePolicy(self.options.deadband_us, self.options.refresh_s,
                                  self.options.baud)
        self.default_move_ms = (self.options.move_ms if self.options.move_ms is not None else
                                default_move_ms(layout, self.options.baud))
        self.byte_s = BITS_PER_BYTE / self.options.baud
        self.boards: list[VirtualController] = []
        self._wires: list[_Wire] = []
        self.opened_at: float | None = None
        self.closed = False
        self.neutral_attempted = False
        self._rng = np.random.default_rng(self.options.seed)
        names = controller_names(layout)
        offsets = np.cumsum([0] + [c.channels for c in layout.controllers])
        # actuator -> position in the boards' concatenated channel arrays
        self._flat = np.array(
            [offsets[names.index(a.controller)] + a.channel
             - layout.controllers[names.index(a.controller)].channel_base
             for a in layout.actuators], dtype=np.intp)
        self._fault_at = math.inf  # earliest scheduled disconnect or brown-out
        self._battery: list[int | None] = [None] * len(layout.controllers)  # last read

    @classmethod
    def from_url(cls, url: str, layout: Layout, clock: Clock | None = None,
                 **options: object) -> SimulatedDevice:
        record = bool(options.pop("record", False))
        device = cls(layout, clock, SimOptions.parse(url, layout, **options), record=record)
        device.url = url
        return device

    # -- lifecycle ----------------------------------------------------------------------------

    def open(self) -> None:
        if self.opened_at is not None:
            return
        warn_if_unbalanced(self.layout)  # as the serial device: channels are pinned
        t0 = self.clock.now()
        self.opened_at = t0
        opts = self.options
        self.boards = []
        for c in self.layout.controllers:
            specs = board_specs(self.layout, c.name)
            board = VirtualController(c.name, c.channels, c.channel_base, specs,
                                      opts.battery_mv, t0, record=self.record)
            self.boards.append(board)
        self._wires = [_Wire(board, writes) for board, writes
                       in zip(self.boards, self.split.ports(self.policy), strict=True)]
        # every board's servos in one bank (boards hold views): one read per displayed frame
        self._servos = ServoBank.joined([b.servos for b in self.boards])
        names = controller_names(self.layout)
        shift = opts.fault_shift()  # None: the session met its faults already (once each)
        disconnects = opts.disconnect_at if shift is not None else ()
        stalls = opts.stall if shift is not None else ()
        brownouts = opts.brownout_at if shift is not None else ()
        t_faults = t0 + (shift or 0.0)
        for name, at in disconnects:
            for i, wire in enumerate(self._wires):
                if name in (None, names[i]):
                    wire.vanish_at = min(wire.vanish_at, t_faults + at)
        for name, channel, at in stalls:
            self.boards[names.index(name)].stall(channel, t_faults + at)
        for name, at in brownouts:
            for i, board in enumerate(self.boards):
                if name in (None, names[i]):
                    board.brownout(t_faults + at)
        for name, at in (opts.hang_at if shift is not None else ()):
            for i, board in enumerate(self.boards):
                if name in (None, names[i]):
                    board.hang(t_faults + at)
        times = [w.vanish_at for w in self._wires] + [t_faults + at for _, at in brownouts]
        self._fault_at = min(times, default=math.inf)
        self._check_batteries(t0)

    def _check_batteries(self, t: float) -> None:
        """Ask every board for its battery voltage over the wire, as the serial device does on
        open: a board that does not answer (a vanished port, garbage) gives a
        :class:`DeviceWarning`; one below :data:`LOW_BATTERY_MV` is a DeviceError."""
        for wire, mv in zip(self._wires, self._ask_batteries(), strict=True):
            if mv is None:
                warnings.warn(f"{self.url}: controller {wire.board.name}: no answer to "
                              f"GET_BATTERY_VOLTAGE; battery unknown", DeviceWarning,
                              stacklevel=3)
            elif mv < LOW_BATTERY_MV:
                raise DeviceError(f"{self.url}: controller {wire.board.name}: battery reads "
                                  f"{mv} mV, below {LOW_BATTERY_MV} mV; charge or check it")

    def _ask_batteries(self, wait: bool = True):  # -> list, or (arrival, list) without wait
        """GET_BATTERY_VOLTAGE on every wire, the boards' reply bytes back, decoded.

        Each query goes out once its wire is free (frames on it or waiting for it go first),
        takes its bytes' time, and meets the wire's faults: garbage in both directions, a port
        that vanishes. The host's decoder reads what came back; the clock waits, as a host
        reading the ports would, until the last reply is in (or would have been). None where
        no reply could be read.
        """
        t = self.clock.now()
        self._advance(t)
        query = get_battery_voltage()
        answers: list[int | None] = []
        waited_until = t
        for k, wire in enumerate(self._wires):
            writes = wire.writes
            while not wire.cut and (wire.flying or writes.pending):  # frames for the wire first
                self._advance_wire(k, wire, max(t, wire.end_at if wire.flying else t,
                                                writes.next_write_at()
                                                if writes.pending else t))
            if wire.cut:
                answers.append(None)
                continue
            start = max(t, writes.free_at)
            end = writes.written(start, len(query))
            wire.flying, wire.start_at, wire.end_at = query, start, end
            self._advance_wire(k, wire, end)  # delivered, unless the port vanished
            expected = end + BATTERY_REPLY_BYTES * self.byte_s
            arrived = max([expected, *(at for at, _ in wire.inbox)])
            waited_until = max(waited_until, arrived)
            answers.append(self._read_battery(wire, arrived))
        self._battery = answers
        if not wait:
            return waited_until, answers
        # the ports are asked concurrently; the answer is in once the slowest reply is
        self.clock.sleep_until(waited_until)
        return answers

    @staticmethod
    def _read_battery(wire: _Wire, until: float) -> int | None:
        """The host reads the board's replies that arrived by ``until``; the line then goes
        quiet. The last battery reply, or None."""
        mv = None
        arrived = [data for at, data in wire.inbox if at <= until]
        wire.inbox = [(at, data) for at, data in wire.inbox if at > until]
        frames = wire.decoder.feed(b"".join(arrived)) + wire.decoder.idle()
        for frame in frames:
            if isinstance(frame.message, BatteryVoltage):
                mv = frame.message.millivolts
        return mv

    def close(self) -> None:
        if self.closed or self.opened_at is None:
            self.closed = True
            return
        try:
            self.neutral_attempted = True
            self._send(self.layout.neutral_setpoints(), self.options.neutral_move_ms,
                       check_faults=False, full=True)
        except DeviceError as exc:
            self.faults.append(f"close: neutral pose not reached: {exc}")
        else:
            for wire in self._wires:
                if wire.cut:  # the healthy boards got it; this one could not
                    self.faults.append(f"close: neutral pose not reached: {self.url}: "
                                       f"controller {wire.board.name}: port vanished")
        finally:
            # like a flushed port: whatever is on or waiting for the wire still goes out
            self._advance(max(max(w.end_at, w.writes.free_at) for w in self._wires)
                          + self._frame_s_bound())
            for wire in self._wires:
                if wire.cut:
                    wire.board.end_of_stream()
            self.closed = True

    def _frame_s_bound(self) -> float:
        return max(servo_move_bytes(len(m)) for m in self.split.members) * self.byte_s

    # -- sending ------------------------------------------------------------------------------

    def send(self, setpoints_mm: np.ndarray, move_ms: int | None = None) -> FrameReport:
        return self._send(setpoints_mm, move_ms, check_faults=True)

    def _send(self, setpoints_mm: np.ndarray, move_ms: int | None, check_faults: bool,
              full: bool = False) -> FrameReport:
        if self.opened_at is None or self.closed:
            state = "closed" if self.closed else "not open"
            raise DeviceError(f"{self.url}: cannot send: the device is {state}")
        t = self.clock.now()
        self._advance(t)
        if t >= self._fault_at and check_faults:
            self._raise_faults(t)
        pulses = self.pulse_map.to_pulses(setpoints_mm)
        if move_ms is None:
            move_ms = self.default_move_ms
        elif isinstance(move_ms, bool) or not isinstance(move_ms, int | np.integer) \
                or not 0 <= move_ms <= 30000:
            raise DeviceError(f"{self.url}: move_ms: expected a whole number 0..30000, "
                              f"got {move_ms!r}")
        done_at = t
        bytes_sent = []
        channels = 0
        merged = False
        split = self.split
        for k, wire in enumerate(self._wires):
            if wire.cut:  # only close() gets here: the other boards still get their frame
                bytes_sent.append(0)
                continue
            writes = wire.writes
            merged |= writes.want(t, pulses[split.members[k]], move_ms, full)
            if writes.free_at <= t:  # the wire is free (next_write_at() <= t): it goes now
                _, done, local, mine, _, _, size = writes.take(t)
                n = len(local)
                if size:  # _put, inline (once per frame and board)
                    wire.flying = split.encode(k, mine, local, move_ms)
                    wire.start_at, wire.end_at = t, done
            else:  # it waits for the wire (a newer frame may replace it)
                n, size, done = writes.predict(t)
            bytes_sent.append(size)
            channels += n
            done_at = max(done_at, done)
        return FrameReport(t, done_at, tuple(bytes_sent), channels, merged)

    def _put(self, k: int, wire: _Wire, write: Write) -> None:
        """Put ``write``'s bytes on wire ``k`` (the previous ones have arrived)."""
        data = self.split.encode(k, write.pulses, write.local, write.move_ms)
        if data:
            wire.flying, wire.start_at, wire.end_at = data, write.start, write.done

    def _advance(self, t: float) -> None:
        """Deliver every write whose last byte has arrived by ``t``; make the writes due."""
        for k, wire in enumerate(self._wires):
            # nothing arrives, waits or vanishes by t (the common case: a frame still flying)
            if (not wire.flying or wire.end_at > t) and not wire.writes.pending \
                    and t < wire.vanish_at:
                continue
            self._advance_wire(k, wire, t)

    def _advance_wire(self, k: int, wire: _Wire, t: float) -> None:
        """:meth:`_advance` for wire ``k`` alone."""
        horizon = t if t < wire.vanish_at else wire.vanish_at
        writes = wire.writes
        while True:
            if wire.flying and wire.end_at <= horizon:
                self._deliver(wire, wire.flying, wire.end_at)
                wire.flying = b""
            if not writes.pending:  # nothing waits for the wire (the common case)
                break
            at = writes.next_write_at()
            if at > horizon:
                break
            self._put(k, wire, writes.take(at))
        if t >= wire.vanish_at and not wire.cut:
            wire.cut = True
            if wire.flying and wire.end_at > wire.vanish_at:
                arrived = int((wire.vanish_at - wire.start_at) / self.byte_s)
                if arrived > 0:
                    self._deliver(wire, wire.flying[:arrived],
                                  wire.start_at + arrived * self.byte_s)
            wire.flying = b""

    def _deliver(self, wire: _Wire, data: bytes, t: float) -> None:
        """``data`` reaches the board at ``t`` (garbled on the way); its reply, if any, sets
        off back at once, garbled too, and waits in the wire's inbox for the host."""
        rate = self.options.garbage_rate
        if rate > 0.0:
            data = self._garble(data, rate)
        reply = wire.board.receive(data, t)
        if reply:
            if rate > 0.0:
                reply = self._garble(reply, rate)
            wire.inbox.append((t + len(reply) * self.byte_s, reply))

    def _garble(self, data: bytes, rate: float) -> bytes:
        """Insert one random byte before each byte of ``data`` with probability ``rate``."""
        count = int(self._rng.binomial(len(data), rate))
        if not count:
            return data
        where = np.sort(self._rng.integers(0, len(data) + 1, count))
        noise = self._rng.integers(0, 256, count).tolist()
        out = bytearray()
        previous = 0
        for position, value in zip(where.tolist(), noise, strict=True):
            out += data[previous:position]
            out.append(value)
            previous = position
        out += data[previous:]
        return bytes(out)

    def _raise_faults(self, t: float) -> None:
        for wire in self._wires:
            if wire.cut:
                self._fault(f"{self.url}: controller {wire.board.name}: port vanished at "
                            f"{wire.vanish_at - self.opened_at:.3f} s after open")
        for board in self.boards:
            board.battery_mv(t)  # fires the board's events up to t
            if board.browned_out_at is not None:
                self._fault(
                    f"{self.url}: controller {board.name}: brown-out at "
                    f"{board.browned_out_at - self.opened_at:.3f} s after open: battery "
                    f"reads {board.battery_mv()} mV, servos limp"
                )

    def _fault(self, message: str) -> None:
        if message not in self.faults:
            self.faults.append(message)
        raise DeviceError(message)

    def clear_caches(self) -> None:
        """Forget remembered encodings and decodings (benchmarks of a first presentation)."""
        self.split.clear_cache()
        clear_decode_cache()

    # -- what the skin meets ------------------------------------------------------------------

    def displayed_setpoints(self, t: float | None = None) -> np.ndarray:
        """Modelled actuator positions at ``t`` (default now), mm in actuator order.

        Servo pulse widths from the boards, through the inverse calibration. ``t`` should not
        precede a frame already delivered (the model keeps only each servo's current move).
        """
        if not self.boards:
            return np.zeros(self.layout.n_actuators)  # before open: the servos rest at base
        if t is None:
            t = self.clock.now()
        self._advance(t)
        for board in self.boards:
            board.advance(t)
        return self.pulse_map.to_mm(self._servos.position(t)[self._flat], check=False)

    def heartbeat_ask(self) -> tuple[float, list[int | None]]:
        """GET_BATTERY_VOLTAGE over every wire now (:meth:`_ask_batteries`), the clock not
        waiting: the replies' arrival is computed and kept for :meth:`heartbeat_check`. A
        fault already due (a vanished port, a brown-out) is raised as :meth:`send` raises it."""
        if self.opened_at is None or self.closed:
            raise DeviceError(f"{self.url}: cannot ask the boards: the device is "
                              f"{'closed' if self.closed else 'not open'}")
        t = self.clock.now()
        self._advance(t)
        if t >= self._fault_at:
            self._raise_faults(t)
        return self._ask_batteries(wait=False)

    def heartbeat_check(self, asked: object) -> None:
        """Every board answered (the clock waits for the replies if they are not in yet; a
        board whose reply did not come is asked once more, as a garbled reply on a noisy line
        is no hung board), or a :class:`DeviceError` names those that did not (a hung board,
        a vanished port) or read below :data:`LOW_BATTERY_MV`."""
        arrived, answers = asked  # type: ignore[misc]
        self.clock.sleep_until(max(self.clock.now(), arrived))
        if None in answers:  # asked once more: a reply garbled on the wire is no hung board
            again = self._ask_batteries()
            answers = [mv if mv is not None else other
                       for mv, other in zip(answers, again, strict=True)]
        silent = [w.board.name for w, mv in zip(self._wires, answers, strict=True) if mv is None]
        if silent:
            self._fault(f"{self.url}: controller(s) {', '.join(silent)} did not answer "
                        "GET_BATTERY_VOLTAGE: the board stopped reading (or its port failed), "
                        "so its servos may hold their last position rather than neutral")
        low = [f"{w.board.name} {mv} mV" for w, mv in zip(self._wires, answers, strict=True)
               if mv is not None and mv < LOW_BATTERY_MV]
        if low:
            self._fault(f"{self.url}: battery below {LOW_BATTERY_MV} mV: {', '.join(low)}")

    def battery_mv(self) -> list[float | None]:
        """Each board's voltage, asked over its wire now (:meth:`_ask_batteries`; the clock
        waits for the replies); None where none could be read. Before open: None; after
        close: what was read last."""
        if self.opened_at is None or self.closed:
            return [None if mv is None else float(mv) for mv in self._battery]
        return [None if mv is None else float(mv) for mv in self._ask_batteries()]
