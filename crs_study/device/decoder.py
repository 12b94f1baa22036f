"""LSC bytes back to frames: one frame (:func:`decode_frame`) or a stream (:class:`FrameDecoder`).

The frames and their encoding are :mod:`crs_study.device.codec`; a candidate frame is checked
against the same value ranges, which is how the stream decoder resynchronises.

Decoder guarantee (tested): bytes that are a concatenation of valid frames and garbage runs
come back as exactly those frames, with each garbage run reported as skipped at its stream
offset, whenever no garbage run contains ``55 55`` or ends in ``55`` (then no header can start
in garbage). Garbage that does hold a header is resolved by checking the candidate frame's
length, command and values; a candidate that fails is dropped one byte at a time, so the
decoder resynchronises on the next real header. For any input at all the decoder never raises,
accounts for every byte (frames + skipped + pending = bytes fed) and gives the same result
however the stream is cut into chunks.

False headers (no checksum can expose them): garbage such as ``55 55 05 06`` right before the
battery reply ``55 55 04 0F 4C 1D`` makes a candidate (action group running, group 0x55) that
passes every check by taking the first three bytes of the real reply, which would be lost. So
a valid candidate inside which another header starts (a *rival*) is taken only when the bytes
decide for it: it is dropped (one byte, as above) when a rival is a valid frame that ends where
the candidate ends, or when the candidate is not followed by a header and a rival is (a real
frame is followed by the next frame's header, or by silence). The decoder waits for the bytes
that decide; :meth:`FrameDecoder.idle` (the line went quiet: what has come is the end of a
burst) and :meth:`FrameDecoder.flush` (end of stream) decide with what there is, silence
counting as a boundary. What the bytes cannot decide is still lost, in two cases: a real
frame followed by garbage (not by a header or silence) behind a false header that takes its
first bytes, and a real frame followed by garbage that holds a header starting another valid
frame which is followed by a header or silence. A third case is the mirror of the one the rule
fixes: a real frame whose own payload holds ``55 55``, followed by garbage, where that inner
header starts a valid frame followed by a header (e.g. ``ActionGroupRun(group=0x55,
times=0x0555)``, then ``06 01 02 03``, then a battery reply: the rule keeps the inner
``ActionGroupRun(1, 770)``). The traffic this project sends cannot hold ``55 55`` in a frame
except a SERVO_MOVE whose move time is exactly 21845 ms (channels are <= 24, pulses <= 2500),
and the boards' replies would need a battery of 21.845 V, so this case is left to the bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from crs_study.device.codec import (
    HEADER,
    SERVO_ID_MAX,
    SERVO_TRIPLES,
    ActionGroupComplete,
    ActionGroupRun,
    ActionGroupRunning,
    ActionGroupSpeed,
    ActionGroupStop,
    ActionGroupStopped,
    BatteryVoltage,
    Command,
    Direction,
    GetBatteryVoltage,
    Message,
    MultServoPosRead,
    MultServoUnload,
    Reply,
    ServoMove,
    ServoPositions,
    servo_values_ok,
)
from crs_study.errors import DeviceError


class _Invalid(Exception):
    """A candidate frame that cannot be what it claims."""


def _expect_length(length: int, want: int, what: str) -> None:
    if length != want:
        raise _Invalid(f"bad length {length} for {what} (expected {want})")


def _n_servos(length: int, per: int, extra: int, what: str) -> int:
    n, rest = divmod(length - extra, per)
    if rest or n < 1 or n > SERVO_ID_MAX + 1:
        raise _Invalid(f"bad length {length} for {what}")
    return n


_HOST_FIXED_LENGTH = {Command.ACTION_GROUP_RUN: 5, Command.ACTION_GROUP_STOP: 2,
                      Command.ACTION_GROUP_SPEED: 5, Command.GET_BATTERY_VOLTAGE: 2}
_BOARD_FIXED_LENGTH = {Reply.ACTION_GROUP_RUNNING: 5, Reply.ACTION_GROUP_STOPPED: 2,
                       Reply.ACTION_GROUP_COMPLETE: 5, Reply.BATTERY_VOLTAGE: 4}
_SERVO_MOVE_CODE = int(Command.SERVO_MOVE)


def _check_length(direction: Direction, code: int, length: int) -> None:
    """Check a candidate's Length byte against its command code; raise _Invalid if wrong."""
    if direction is Direction.HOST:
        fixed = _HOST_FIXED_LENGTH
        if code == _SERVO_MOVE_CODE:
            _n_servos(length, 3, 5, "SERVO_MOVE")
        elif code in (Command.MULT_SERVO_UNLOAD, Command.MULT_SERVO_POS_READ):
            _n_servos(length, 1, 3, Command(code).name)
        elif code in fixed:
            _expect_length(length, fixed[code], Command(code).name)
        else:
            raise _Invalid(f"unknown command 0x{code:02X}")
    else:
        fixed = _BOARD_FIXED_LENGTH
        if code == Reply.SERVO_POSITIONS:
            _n_servos(length, 3, 3, "SERVO_POSITIONS")
        elif code in fixed:
            _expect_length(length, fixed[code], Reply(code).name)
        else:
            raise _Invalid(f"unknown reply 0x{code:02X}")


def _u16_at(params: bytes, i: int) -> int:
    return params[i] | (params[i + 1] << 8)


def _triples(params: bytes, start: int, n: int) -> tuple[tuple[int, int], ...]:
    return tuple((params[start + 3 * k], _u16_at(params, start + 3 * k + 1)) for k in range(n))


def _parse(direction: Direction, code: int, params: bytes) -> Message:
    """Typed message for a complete candidate. Raise _Invalid when a value is impossible."""
    try:
        if direction is Direction.HOST:
            if code == _SERVO_MOVE_CODE:
                n = params[0]
                if 3 * n + 3 != len(params):
                    raise _Invalid(f"servo count {n} does not match length {len(params) + 2}")
                time_ms = _u16_at(params, 1)
                flat = SERVO_TRIPLES[n].unpack_from(params, 3) if n <= SERVO_ID_MAX + 1 else ()
                ids, pulses = list(flat[0::2]), list(flat[1::2])
                if servo_values_ok(ids, pulses, time_ms):
                    return ServoMove._checked(tuple(zip(ids, pulses, strict=True)), time_ms)
                # a bad value: the element-wise checks name it
                return ServoMove(_triples(params, 3, n), time_ms)
            if code == Command.ACTION_GROUP_RUN:
                return ActionGroupRun(params[0], _u16_at(params, 1))
            if code == Command.ACTION_GROUP_STOP:
                return ActionGroupStop()
            if code == Command.ACTION_GROUP_SPEED:
                return ActionGroupSpeed(params[0], _u16_at(params, 1))
            if code == Command.GET_BATTERY_VOLTAGE:
                return GetBatteryVoltage()
            n = params[0]
            if n + 1 != len(params):
                raise _Invalid(f"servo count {n} does not match length {len(params) + 2}")
            kind = MultServoUnload if code == Command.MULT_SERVO_UNLOAD else MultServoPosRead
            return kind(tuple(params[1:]))
        if code == Reply.ACTION_GROUP_RUNNING:
            return ActionGroupRunning(params[0], _u16_at(params, 1))
        if code == Reply.ACTION_GROUP_STOPPED:
            return ActionGroupStopped()
        if code == Reply.ACTION_GROUP_COMPLETE:
            return ActionGroupComplete(params[0], _u16_at(params, 1))
        if code == Reply.BATTERY_VOLTAGE:
            return BatteryVoltage(_u16_at(params, 0))
        n = params[0]
        if 3 * n + 1 != len(params):
            raise _Invalid(f"servo count {n} does not match length {len(params) + 2}")
        return ServoPositions(_triples(params, 1, n))
    except DeviceError as exc:
        raise _Invalid(str(exc).removeprefix("LSC frame: ")) from None


def decode_frame(data: bytes, direction: Direction | str = Direction.HOST) -> Message:
    """The message in ``data``, which must be exactly one valid frame; else :class:`DeviceError`."""
    direction = Direction(direction)
    if len(data) < 4 or data[:2] != HEADER or data[2] + 2 != len(data):
        raise DeviceError(f"LSC frame: expected one frame 55 55 LEN CMD ..., got {data.hex(' ')!r}")
    try:
        _check_length(direction, data[3], data[2])
        return _parse(direction, data[3], bytes(data[4:]))
    except _Invalid as exc:
        raise DeviceError(f"LSC frame {data.hex(' ')!r}: {exc}") from None


@dataclass(frozen=True)
class Frame:
    """A decoded frame: where it started in the stream, its bytes, and what it says."""

    offset: int
    raw: bytes
    message: Message


@dataclass(frozen=True)
class Skipped:
    """A run of bytes the decoder could not frame, at stream ``offset``."""

    offset: int
    data: bytes
    reason: str


@dataclass
class FrameDecoder:
    """Streaming LSC decoder: ``feed(bytes) -> list[Frame]``; garbage goes to :attr:`skipped`.

    Adjacent skipped bytes are merged into one :class:`Skipped` run (the reason is the first
    one's). :meth:`take_skipped` hands the runs over and forgets them. A reader that sees the
    line go quiet (a read timed out empty) calls :meth:`idle`, which decides frames held back
    for the bytes after them (false headers, module docstring); :meth:`flush` ends the stream,
    returning those frames and reporting an unfinished frame as skipped ("truncated").
    """

    direction: Direction | str = Direction.HOST
    skipped: list[Skipped] = field(default_factory=list)
    skipped_bytes: int = 0
    frames_decoded: int = 0
    _buffer: bytearray = field(default_factory=bytearray, repr=False)
    _offset: int = 0  # stream offset of _buffer[0]

    def __post_init__(self) -> None:
        self.direction = Direction(self.direction)

    @property
    def pending(self) -> bytes:
        """Bytes held back: the start of a frame that may still complete."""
        return bytes(self._buffer)

    @property
    def has_pending(self) -> bool:
        """Whether bytes are held back (cheaper than ``bool(pending)``)."""
        return bool(self._buffer)

    @property
    def position(self) -> int:
        """Stream offset of the first byte not yet framed or skipped."""
        return self._offset

    def feed(self, data: bytes) -> list[Frame]:
        if not self._buffer and len(data) >= 4 and data[2] + 2 == len(data) \
                and data[:2] == HEADER and data.find(HEADER, 2) < 0 and data[-1] != 0x55:
            # nothing held back and ``data`` is one candidate frame (the usual chunk) with no
            # header inside it: decode it directly; the general loop gives the same result,
            # only slower
            try:
                _check_length(self.direction, data[3], data[2])
                message = _parse(self.direction, data[3], bytes(data[4:]))
            except _Invalid:
                pass  # not a frame after all: the general loop resynchronises and reports
            else:
                frame = Frame(self._offset, bytes(data), message)
                self._offset += len(data)
                self.frames_decoded += 1
                return [frame]
        self._buffer += data
        return self._scan(quiet=False)

    def idle(self) -> list[Frame]:
        """The line went quiet: frames held back for the bytes after them are decided now,
        the silence counting as a frame boundary. An unfinished frame stays pending."""
        return self._scan(quiet=True) if self._buffer else []

    def _scan(self, quiet: bool) -> list[Frame]:
        """Frame what the buffer holds; ``quiet``: no more bytes follow for now."""
        frames: list[Frame] = []
        buf = self._buffer
        pos = 0
        while True:
            start = buf.find(HEADER, pos)
            if start < 0:
                # keep a trailing 0x55: it may be the first half of a header
                keep = len(buf) - 1 if buf.endswith(b"\x55") and len(buf) > pos else len(buf)
                self._skip(pos, keep, "no frame header")
                pos = keep
                break
            self._skip(pos, start, "no frame header")
            pos = start
            if len(buf) - pos < 4:
                break
            length, code = buf[pos + 2], buf[pos + 3]
            try:
                _check_length(self.direction, code, length)
            except _Invalid as exc:
                self._skip(pos, pos + 1, str(exc))
                pos += 1
                continue
            end = pos + length + 2
            if len(buf) < end:
                # unfinished: wait for the rest, unless the line is quiet and a frame that
                # starts inside it is complete (a false header cut off the reply after it)
                verdict = self._rivals(buf, pos, end, quiet) if quiet else None
                if not verdict:
                    break
                self._skip(pos, pos + 1, verdict)
                pos += 1
                continue
            try:
                message = _parse(self.direction, code, bytes(buf[pos + 4:end]))
            except _Invalid as exc:
                self._skip(pos, pos + 1, str(exc))
                pos += 1
                continue
            verdict = self._rivals(buf, pos, end, quiet)
            if verdict is None:
                break  # the bytes that decide have not come yet
            if verdict:
                self._skip(pos, pos + 1, verdict)
                pos += 1
                continue
            frames.append(Frame(self._offset + pos, bytes(buf[pos:end]), message))
            pos = end
        del buf[:pos]
        self._offset += pos
        self.frames_decoded += len(frames)
        return frames

    def flush(self) -> list[Frame]:
        """End of stream: the frames still held back are decided (as by :meth:`idle`) and
        returned; whatever else is pending can no longer complete and is reported skipped."""
        frames = self.idle()
        self._skip(0, len(self._buffer), "truncated frame")
        self._offset += len(self._buffer)
        self._buffer.clear()
        return frames

    # -- false headers (module docstring) ----------------------------------------------------

    def _anchored(self, buf: bytearray, at: int, quiet: bool) -> bool | None:
        """Whether a frame ending at ``at`` is followed by a header (None: not known yet)."""
        if len(buf) >= at + 2:
            return buf[at] == 0x55 and buf[at + 1] == 0x55
        if len(buf) == at:
            return True if quiet else None  # silence after it is a boundary
        return None if buf[at] == 0x55 and not quiet else False

    def _rival(self, buf: bytearray, j: int, quiet: bool) -> tuple[int, bool | None] | None:
        """The frame a header at ``j`` would start: (its end, whether it is followed by a
        header); None when it cannot be a valid frame; (-1, None) when not known yet."""
        n = len(buf)
        if j + 1 >= n or (buf[j + 1] == 0x55 and j + 4 > n):
            return None if quiet else (-1, None)
        if buf[j + 1] != 0x55:
            return None
        length, code = buf[j + 2], buf[j + 3]
        try:
            _check_length(self.direction, code, length)
            end = j + length + 2
            if end > n:
                return None if quiet else (-1, None)
            _parse(self.direction, code, bytes(buf[j + 4:end]))
        except _Invalid:
            return None
        return end, self._anchored(buf, end, quiet)

    def _rivals(self, buf: bytearray, pos: int, end: int, quiet: bool) -> str | None:
        """Decide the valid candidate ``buf[pos:end]``: "" takes it, a reason drops its first
        byte, None waits for more bytes (module docstring, "False headers"). A candidate not
        complete yet (``end`` beyond the buffer) is only ever dropped or waited for."""
        j = buf.find(b"\x55", pos + 2, end)
        if j < 0:
            return "" if end <= len(buf) else None  # no header inside: nothing to weigh
        rivals = []
        while j >= 0:
            rival = self._rival(buf, j, quiet)
            if rival is not None:
                if rival[0] == end:
                    return (f"false header: a frame at offset {self._offset + j} ends where "
                            f"this one does")
                rivals.append((j, rival))
            j = buf.find(b"\x55", j + 1, end)
        if end > len(buf):
            anchored: bool | None = False if quiet else None  # cut off by the silence
        elif not rivals:
            return ""
        else:
            anchored = self._anchored(buf, end, quiet)
        if anchored:
            return ""
        if anchored is False:
            for j, (_, rival_anchored) in rivals:
                if rival_anchored:
                    return (f"false header: not followed by a header, unlike the frame at "
                            f"offset {self._offset + j} inside it")
        if end <= len(buf) and all(rival_anchored is False for _, (_, rival_anchored) in rivals):
            return ""
        return None

    def take_skipped(self) -> list[Skipped]:
        runs, self.skipped = self.skipped, []
        return runs

    def _skip(self, start: int, stop: int, reason: str) -> None:
        if stop <= start:
            return
        offset = self._offset + start
        data = bytes(self._buffer[start:stop])
        self.skipped_bytes += len(data)
        last = self.skipped[-1] if self.skipped else None
        if last is not None and last.offset + len(last.data) == offset:
            self.skipped[-1] = Skipped(last.offset, last.data + data, last.reason)
        else:
            self.skipped.append(Skipped(offset, data, reason))


def decode_all(data: bytes, direction: Direction | str = Direction.HOST
               ) -> tuple[list[Frame], list[Skipped]]:
    """Decode a complete byte string: its frames, and every skipped run (tail included)."""
    decoder = FrameDecoder(direction)
    frames = decoder.feed(data)
    frames += decoder.flush()
    return frames, decoder.skipped
