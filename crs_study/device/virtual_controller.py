"""A virtual Hiwonder LSC-24 board: it decodes the bytes it receives and moves model servos.

The board is driven by bytes and time only, so the same object sits behind
:class:`~crs_study.device.simulated.SimulatedDevice` (bytes handed over with the clock time
their last bit arrives), behind a pyserial URL (``lscsim://``, :mod:`.protocol_lscsim`) and
behind a pseudo-terminal (:mod:`.virtual_pty`).

What it models (LSC protocol)
    * Framing: the streaming :class:`~crs_study.device.decoder.FrameDecoder` of the real
      codec; skipped garbage and malformed frames are counted as bad frames and beep.
    * SERVO_MOVE: each servo moves from where it is to the commanded pulse width along a
      straight line in time, taking ``max(T, |dp| / v)`` where ``T`` is the frame's move time
      and ``v`` the servo's speed limit in us/s (0.08 s/cm of stroke, converted through the
      channel's calibration). Motion is analytic (:class:`ServoBank`), so positions can be
      read at any time without stepping.
    * GET_BATTERY_VOLTAGE: replies ``55 55 04 0F lo hi`` (millivolts).
    * MULT_SERVO_UNLOAD: the servos go limp and sink to their rest (base) position.
    * Faults: a stalled channel (frozen where it is from a time on, commands ignored), a
      brown-out (the servo rail sags: every servo goes limp and sinks to rest, commands are
      ignored, the battery reads :data:`BROWNOUT_BATTERY_MV`) and a hang (the board stops
      reading: from a time on every byte is lost unread, nothing is answered, and the servos
      hold their last command; :meth:`VirtualController.hang`).

Times are seconds on whatever clock the caller uses; calls must come in non-decreasing time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from crs_study.device.codec import (
    Direction,
    GetBatteryVoltage,
    Message,
    MultServoPosRead,
    MultServoUnload,
    ServoMove,
    battery_voltage_reply,
    servo_positions_reply,
)
from crs_study.device.decoder import FrameDecoder

#: What a healthy 2S pack reads (mV); the value the board reports unless told otherwise.
NORMAL_BATTERY_MV = 7400
#: What the board reports after a brown-out (mV): well below a 2S pack's cut-off of 6.0 V.
BROWNOUT_BATTERY_MV = 4800
#: Pulse width an unknown channel rests at (us): the centre of the LSC range.
CENTRE_US = 1500.0


class ServoBank:
    """Positions (us) of ``n`` servos, piecewise linear in time with a speed limit.

    Each servo holds one segment: it is at ``target`` from ``arrive`` on, and before that
    at ``target - slope * (arrive - t)``. A command at time ``t`` starts a new segment at the
    servo's current position; the move lasts ``max(T, |target - p(t)| / v_max)``.

    Parameters
    ----------
    rest_us : pulse widths (us) the servos sit at before any command (and sink to when limp).
    max_speed_us_s : speed limit of each servo in pulse-width units per second.
    t0 : time the bank starts at.
    """

    def __init__(self, rest_us: np.ndarray, max_speed_us_s: np.ndarray, t0: float = 0.0) -> None:
        self.rest_us = np.array(rest_us, dtype=float)
        self.max_speed = np.array(max_speed_us_s, dtype=float)
        n = len(self.rest_us)
        if self.max_speed.shape != (n,) or np.any(self.max_speed <= 0):
            raise ValueError(f"max_speed_us_s must be {n} positive speeds, got {max_speed_us_s!r}")
        self.target = self.rest_us.copy()
        self.slope = np.zeros(n)
        self.arrive = np.full(n, float(t0))
        self.s_per_us = 1.0 / self.max_speed
        self.frozen = np.zeros(n, dtype=bool)
        self.any_frozen = False

    @classmethod
    def joined(cls, banks: Sequence[ServoBank]) -> ServoBank:
        """One bank holding ``banks``' servos end to end; each of ``banks`` becomes a view into
        it (same numbers, shared storage), so all positions are read with one computation."""
        joined = object.__new__(cls)
        for name in ("rest_us", "max_speed", "target", "slope", "arrive", "s_per_us",
                     "frozen"):
            setattr(joined, name, np.concatenate([getattr(b, name) for b in banks]))
        joined.any_frozen = any(b.any_frozen for b in banks)
        start = 0
        for bank in banks:
            stop = start + len(bank)
            for name in ("rest_us", "max_speed", "target", "slope", "arrive", "s_per_us",
                         "frozen"):
                setattr(bank, name, getattr(joined, name)[start:stop])
            start = stop
        return joined

    def __len__(self) -> int:
        return len(self.target)

    def position(self, t: float) -> np.ndarray:
        """Pulse widths (us) of every servo at time ``t``."""
        return self.target - self.slope * np.maximum(self.arrive - t, 0.0)

    def position_of(self, index: np.ndarray, t: float) -> np.ndarray:
        """Pulse widths (us) of the servos ``index`` at time ``t``."""
        return self.target[index] - self.slope[index] * np.maximum(self.arrive[index] - t, 0.0)

    def command(self, index: np.ndarray, target_us: np.ndarray, move_s: float, t: float) -> None:
        """Move servos ``index`` to ``target_us`` starting at ``t`` over ``move_s`` (or slower).

        Frozen (stalled or limp) servos ignore the command.
        """
        self.command_arrays(np.asarray(index, dtype=np.intp), np.asarray(target_us, dtype=float),
                            float(move_s), t)

    def command_arrays(self, index: np.ndarray, target_us: np.ndarray, move_s: float, t: float
                       ) -> None:
        """:meth:`command` for an intp ``index`` and a float ``target_us`` (the per-frame path).

        The arithmetic of :meth:`position`, term for term, over fewer numpy calls.
        """
        if self.any_frozen:
            live = ~self.frozen[index]
            index, target_us = index[live], target_us[live]
        here = self.position(t)[index]
        delta = target_us - here
        duration = np.abs(delta)
        duration *= self.s_per_us[index]
        np.maximum(duration, move_s, out=duration)
        # duration == 0 only when move_s == 0 and delta == 0: the slope is then 0
        self.slope[index] = delta / (duration if move_s > 0.0
                                     else np.where(duration > 0.0, duration, 1.0))
        self.target[index] = target_us
        duration += t
        self.arrive[index] = duration

    def freeze(self, index: np.ndarray, t: float) -> None:
        """Stop servos ``index`` where they are at ``t``; later commands are ignored (a stall)."""
        index = np.asarray(index, dtype=np.intp)
        self.target[index] = self.position_of(index, t)
        self.slope[index] = 0.0
        self.arrive[index] = t
        self.frozen[index] = True
        self.any_frozen = True

    def go_limp(self, index: np.ndarray, t: float) -> None:
        """Servos ``index`` lose drive at ``t``: they sink to rest at their speed limit.

        A stalled (jammed) servo stays where it is.
        """
        index = np.asarray(index, dtype=np.intp)
        self.command(index, self.rest_us[index], 0.0, t)


@dataclass(frozen=True)
class ServoSpec:
    """How one board channel's servo responds: where it rests and how fast it can go."""

    rest_us: float = CENTRE_US
    max_speed_us_s: float = 1000.0 / (9.0 * 0.008)  # 1000 us over a 9 mm stroke at 0.08 s/cm


def speed_us_per_s(zero_us: float, full_us: float, travel_mm: float,
                   speed_s_per_mm: float) -> float:
    """Speed limit in pulse-width units: |full - zero| / travel (us/mm) over s/mm.

    The paper's servos (Methods): 0.08 s/cm = 0.008 s/mm; a 1000 us, 9 mm stroke takes 72 ms
    (13 889 us/s).
    """
    return abs(full_us - zero_us) / travel_mm / speed_s_per_mm


def default_specs(n: int) -> Sequence[ServoSpec]:
    return [ServoSpec()] * n


@dataclass(frozen=True)
class Received:
    """One frame the board acted on: when its last byte arrived, and what it said."""

    t: float
    message: Message


@dataclass(frozen=True)
class _Action:
    """A decoded message and, for SERVO_MOVE, the servo indices and targets it commands."""

    message: Message
    index: np.ndarray | None = None
    target: np.ndarray | None = None
    move_s: float = 0.0
    unknown: int = 0  # servo ids that are not this board's


#: Decoded chunks by (channel_base, channels, bytes): a dry-run replays each stimulus many
#: times, and a look-up costs a fraction of decoding, checking and planning the frame again.
_DECODED: dict[tuple[int, int, bytes], list[_Action]] = {}
DECODE_CACHE_SIZE = 1 << 15


def clear_decode_cache() -> None:
    """Forget every remembered decoding (for benchmarks of first presentations)."""
    _DECODED.clear()


class VirtualController:
    """A virtual LSC-24: feed it bytes with their arrival time, read servo positions back.

    Parameters
    ----------
    name : the board's name in the device file (for messages).
    channels, channel_base : the board's channel ids are ``channel_base .. channel_base +
        channels - 1``; a SERVO_MOVE id is the channel number (device file ``"A:3"`` -> id 3).
    specs : per channel, in id order, where the servo rests and its speed limit; default: rest
        at 1500 us, 1000 us per 9 mm stroke at 0.08 s/cm.
    battery_mv : what GET_BATTERY_VOLTAGE answers while healthy.
    t0 : time the board powers up.
    record : keep every decoded frame in :attr:`received` (for tests; off for speed).
    """

    def __init__(self, name: str = "A", channels: int = 24, channel_base: int = 1,
                 specs: Sequence[ServoSpec] | None = None, battery_mv: int = NORMAL_BATTERY_MV,
                 t0: float = 0.0, record: bool = False) -> None:
        specs = list(specs) if specs is not None else default_specs(channels)
        if len(specs) != channels:
            raise ValueError(f"expected {channels} servo specs, got {len(specs)}")
        self.name = name
        self.channels = channels
        self.channel_base = channel_base
        self.servos = ServoBank(np.array([s.rest_us for s in specs]),
                                np.array([s.max_speed_us_s for s in specs]), t0)
        self.decoder = FrameDecoder(Direction.HOST)
        self.healthy_battery_mv = battery_mv
        self.record = record
        self.received: list[Received] = []
        self.good_frames = 0
        self.bad_frames = 0  # skipped runs: garbage, malformed or truncated frames (each beeps)
        self.ignored_frames = 0  # valid frames the board does not act on (brown-out, groups)
        self.unknown_ids = 0  # servo ids in valid frames that are not one of this board's
        self.last_time = t0
        self.browned_out_at: float | None = None
        self.hung_at: float | None = None  # stopped reading (hang)
        self.unread_bytes = 0  # bytes that arrived after the hang
        self.stalled: dict[int, float] = {}  # channel id -> time it stalled
        self._events: list[tuple[float, int, str, int]] = []  # (time, order, kind, channel)
        self._skip_end = -1  # stream offset just past the last skipped run

    # -- faults -------------------------------------------------------------------------------

    def stall(self, channel: int, at: float) -> None:
        """From time ``at`` on, servo ``channel`` stays where it is whatever it is told."""
        self._index_of(channel)  # check now, not when the event fires
        self._schedule(at, "stall", channel)

    def brownout(self, at: float) -> None:
        """From time ``at`` on the servo rail is down: servos limp to rest, battery reads low."""
        self._schedule(at, "brownout", -1)

    def hang(self, at: float) -> None:
        """From time ``at`` on the board reads nothing: bytes are lost, queries unanswered,
        servos hold their last command (a hung microcontroller or a dead receive line)."""
        self._schedule(at, "hang", -1)

    def _schedule(self, at: float, kind: str, channel: int) -> None:
        self._events.append((float(at), len(self._events), kind, channel))
        self._events.sort()
        self._fire_events(self.last_time)

    def _fire_events(self, t: float) -> None:
        while self._events and self._events[0][0] <= t:
            at, _, kind, channel = self._events.pop(0)
            if kind == "stall":
                self.servos.freeze(np.array([self._index_of(channel)]), at)
                self.stalled[channel] = at
            elif kind == "hang":
                self.hung_at = at
            else:
                self.browned_out_at = at
                self.servos.go_limp(np.arange(self.channels), at)

    # -- state --------------------------------------------------------------------------------

    @property
    def beeps(self) -> int:
        """The board beeps once per bad frame (LSC protocol)."""
        return self.bad_frames

    def battery_mv(self, t: float | None = None) -> int:
        if t is not None:
            self._advance(t)
        return BROWNOUT_BATTERY_MV if self.browned_out_at is not None else self.healthy_battery_mv

    def positions_us(self, t: float) -> np.ndarray:
        """Pulse width (us) each servo is at, at time ``t``, in channel-id order."""
        self._advance(t)
        return self.servos.position(t)

    def channel_ids(self) -> range:
        return range(self.channel_base, self.channel_base + self.channels)

    def _index_of(self, channel: int) -> int:
        index = channel - self.channel_base
        if not 0 <= index < self.channels:
            raise ValueError(
                f"board {self.name}: no channel {channel!r} "
                f"(channels {self.channel_base}..{self.channel_base + self.channels - 1})"
            )
        return index

    def advance(self, t: float) -> None:
        """Bring the board to time ``t``: fire the faults due by then."""
        self._advance(t)

    def _advance(self, t: float) -> None:
        if t > self.last_time:
            self.last_time = t
        if self._events and self._events[0][0] <= t:
            self._fire_events(t)

    # -- the byte stream ----------------------------------------------------------------------

    def receive(self, data: bytes, t: float) -> bytes:
        """Bytes whose last one arrived at ``t``; returns the board's reply bytes (may be b"")."""
        self._advance(t)
        if self.hung_at is not None:
            self.unread_bytes += len(data)
            return b""
        clean_start = not self.decoder.has_pending
        key = (self.channel_base, self.channels, data)
        actions = _DECODED.get(key) if clean_start else None
        if actions is None:
            frames = self.decoder.feed(data)
            if self.decoder.skipped:
                self._count_bad()
            actions = [self._plan(frame.message) for frame in frames]
            if clean_start and sum(len(f.raw) for f in frames) == len(data):
                # exactly whole frames: the decoder's result depends on these bytes alone
                if len(_DECODED) >= DECODE_CACHE_SIZE:
                    _DECODED.clear()
                _DECODED[key] = actions
        else:
            self._skip_end = -1  # a clean chunk separates runs of garbage
        replies = b""
        for action in actions:
            replies += self._act(action, t)
        return replies

    def end_of_stream(self) -> None:
        """The line went quiet for good: a frame the decoder held back for the bytes after it
        is acted on (nobody hears a reply); an unfinished frame is a bad frame."""
        for frame in self.decoder.flush():
            self._act(self._plan(frame.message), self.last_time)
        if self.decoder.skipped:
            self._count_bad()

    def _count_bad(self) -> None:
        """One bad frame per run of skipped bytes, a run cut across two feeds counted once."""
        for run in self.decoder.take_skipped():
            if run.offset != self._skip_end:
                self.bad_frames += 1
            self._skip_end = run.offset + len(run.data)

    def _plan(self, message: Message) -> _Action:
        """What a message asks of this board, worked out once (SERVO_MOVE: arrays)."""
        if isinstance(message, ServoMove):
            base, n = self.channel_base, self.channels
            servos, pulses = zip(*message.positions, strict=True)
            if min(servos) - base >= 0 and max(servos) - base < n:  # all this board's
                index = np.array(servos, dtype=np.intp)
                index -= base
                return _Action(message, index, np.array(pulses, dtype=float),
                               message.time_ms / 1000.0, 0)
            known = [(servo - base, pulse) for servo, pulse in message.positions
                     if 0 <= servo - base < n]
            index = np.array([i for i, _ in known], dtype=np.intp)
            target = np.array([p for _, p in known], dtype=float)
            return _Action(message, index, target, message.time_ms / 1000.0,
                           len(message.positions) - len(known))
        return _Action(message)

    def _act(self, action: _Action, t: float) -> bytes:
        message = action.message
        self.good_frames += 1
        if self.record:
            self.received.append(Received(t, message))
        if action.index is not None:  # SERVO_MOVE
            if self.browned_out_at is not None:
                self.ignored_frames += 1
                return b""
            self.unknown_ids += action.unknown
            if len(action.index):
                self.servos.command_arrays(action.index, action.target, action.move_s, t)
            return b""
        if isinstance(message, GetBatteryVoltage):
            return battery_voltage_reply(self.battery_mv())
        if isinstance(message, MultServoUnload):
            index = [i - self.channel_base for i in message.ids
                     if 0 <= i - self.channel_base < self.channels]
            self.unknown_ids += len(message.ids) - len(index)
            if index:
                self.servos.go_limp(np.array(index), t)
            return b""
        if isinstance(message, MultServoPosRead):
            # PWM servos give no feedback: the board can only report what it last commanded.
            known = [i for i in message.ids if 0 <= i - self.channel_base < self.channels]
            self.unknown_ids += len(message.ids) - len(known)
            if not known:
                return b""
            return servo_positions_reply(
                [(i, int(round(self.servos.target[i - self.channel_base]))) for i in known]
            )
        self.ignored_frames += 1  # action groups: this board stores none
        return b""
