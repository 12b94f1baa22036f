"""The Hiwonder/LOBOT LSC-series controller protocol: frames as typed data, bytes, and back.

Pure code, no I/O (Hiwonder's LSC-series servo controller communication protocol)::

    0x55 0x55  Length  Command  parameters...     Length = len(parameters) + 2

so a frame is ``Length + 2`` bytes; no ID byte, no checksum; 16-bit values little-endian.

Host to board (commands)          code  Length   parameters
    SERVO_MOVE                       3  3n + 5   n, time lo, time hi, n x (id, pos lo, pos hi)
    ACTION_GROUP_RUN                 6  5        group, times lo, times hi (0 = forever)
    ACTION_GROUP_STOP                7  2        -
    ACTION_GROUP_SPEED              11  5        group (0xFF = all), percent lo, percent hi
    GET_BATTERY_VOLTAGE             15  2        -
    MULT_SERVO_UNLOAD               20  n + 3    n, ids
    MULT_SERVO_POS_READ             21  n + 3    n, ids

Board to host (replies and notices)
    action group running             6  5        group, times lo, times hi
    action group stopped             7  2        -
    action group complete            8  5        group, times lo, times hi
    battery voltage                 15  4        millivolts lo, hi
    servo positions                 21  3n + 3   n, n x (id, pos lo, pos hi)

The 0x06/0x07/0x08 notices and their lengths are the vendor's: Hiwonder's "LSC Series
Controller Communication Protocol", section 2.2 "Data Sent by the Controller to User"
(public copy: github.com/Hiwonder-docs/32-Channel-Servo-Controller,
source/docs/2_Communication_Protocol.md) gives Length 5, 2, 5 with the examples
``55 55 05 06 08 01 00`` (group 8 started, once), ``55 55 02 07`` (stopped) and
``55 55 05 08 08 01 00`` (group 8 done); Hiwonder's Arduino LobotServoController receive
handler reads the same layout (group, times lo, times hi). Those vectors, and the sheet's
command examples (``55 55 05 06 02 00 00``, ``55 55 05 0B 08 32 00``, ``55 55 05 0B FF 2C
01``), are in tests/test_codec.py.

Value ranges enforced by the encoders (and by the decoder, which is how it resynchronises):
pulse width 500..2500 us, move time 0..30000 ms (LSC protocol), servo ids 0..32 (the largest
channel a device file may name: ``channel_base`` <= 1 and at most 32 channels), ids unique in a
frame, at least one servo per multi-servo frame, 8- and 16-bit fields in range.

Decoding (bytes back to frames, one frame or a stream with garbage in it) is
:mod:`crs_study.device.decoder`.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from numbers import Integral
from typing import ClassVar

import numpy as np

from crs_study.errors import DeviceError

HEADER = b"\x55\x55"
PULSE_MIN_US = 500
PULSE_MAX_US = 2500
MOVE_TIME_MAX_MS = 30000
SERVO_ID_MAX = 32


class Command(IntEnum):
    """Command codes, host to board."""

    SERVO_MOVE = 3
    ACTION_GROUP_RUN = 6
    ACTION_GROUP_STOP = 7
    ACTION_GROUP_SPEED = 11
    GET_BATTERY_VOLTAGE = 15
    MULT_SERVO_UNLOAD = 20
    MULT_SERVO_POS_READ = 21


class Reply(IntEnum):
    """Codes of frames the board sends."""

    ACTION_GROUP_RUNNING = 6
    ACTION_GROUP_STOPPED = 7
    ACTION_GROUP_COMPLETE = 8
    BATTERY_VOLTAGE = 15
    SERVO_POSITIONS = 21


class Direction(Enum):
    """Which way the bytes travel: decides how command codes are read."""

    HOST = "host"  # host -> board: commands
    BOARD = "board"  # board -> host: replies and notices


# ---------------------------------------------------------------------------------------------
# checks


def _check_int(name: str, value: object, low: int, high: int) -> int:
    """``value`` as an int if it is a whole number in [low, high] (numpy integers too)."""
    if isinstance(value, bool) or not isinstance(value, Integral) or not low <= value <= high:
        raise DeviceError(
            f"LSC frame: {name}: expected a whole number {low}..{high}, got {value!r}"
        )
    return int(value)


def _check_ids(ids: Iterable[int]) -> tuple[int, ...]:
    ids = tuple(_check_int("servo id", i, 0, SERVO_ID_MAX) for i in ids)
    if not ids:
        raise DeviceError("LSC frame: expected at least one servo id, got none")
    if len(set(ids)) != len(ids):
        raise DeviceError(f"LSC frame: servo ids repeat in {list(ids)!r}")
    return ids


def _u16(value: int) -> bytes:
    return bytes((value & 0xFF, value >> 8))


def _frame(code: int, params: bytes) -> bytes:
    return HEADER + bytes((len(params) + 2, code)) + params


# ---------------------------------------------------------------------------------------------
# messages: host -> board


@dataclass(frozen=True)
class ServoMove:
    """Move servos to pulse widths (us) over ``time_ms``: ``positions`` = ((id, pulse), ...)."""

    positions: tuple[tuple[int, int], ...]
    time_ms: int
    code: ClassVar[int] = Command.SERVO_MOVE

    def __post_init__(self) -> None:
        positions = tuple((_check_int("servo id", i, 0, SERVO_ID_MAX),
                           _check_int(f"servo {i} pulse width (us)", p, PULSE_MIN_US, PULSE_MAX_US))
                          for i, p in self.positions)
        _check_ids(i for i, _ in positions)
        object.__setattr__(self, "time_ms", _check_int("move time (ms)", self.time_ms, 0,
                                                      MOVE_TIME_MAX_MS))
        object.__setattr__(self, "positions", positions)

    def encode(self) -> bytes:
        ids = [servo for servo, _ in self.positions]
        pulses = [pulse for _, pulse in self.positions]
        return _pack_servo_move(ids, pulses, self.time_ms)

    @classmethod
    def _checked(cls, positions: tuple[tuple[int, int], ...], time_ms: int) -> ServoMove:
        """A ServoMove from values the caller has already checked as ``__post_init__`` would
        (plain ints, ids 0..32 unique, pulses 500..2500, time 0..30000): no second check."""
        move = object.__new__(cls)
        object.__setattr__(move, "positions", positions)
        object.__setattr__(move, "time_ms", time_ms)
        return move


#: struct layouts of a SERVO_MOVE for n servos: header, length, code, n, time, n x (id, pulse).
_SERVO_MOVE_STRUCTS = [struct.Struct("<5BH" + "BH" * n) for n in range(SERVO_ID_MAX + 2)]
#: ... and of its n x (id, pulse) part alone (decoding).
SERVO_TRIPLES = [struct.Struct("<" + "BH" * n) for n in range(SERVO_ID_MAX + 2)]


def _pack_servo_move(ids: list[int], pulses: list[int], time_ms: int) -> bytes:
    """SERVO_MOVE bytes from checked plain-int values (``55 55 3n+5 03 n time (id pulse)*n``)."""
    n = len(ids)
    flat = [0] * (2 * n)
    flat[0::2] = ids
    flat[1::2] = pulses
    return _SERVO_MOVE_STRUCTS[n].pack(0x55, 0x55, 3 * n + 5, Command.SERVO_MOVE, n, time_ms,
                                       *flat)


def servo_values_ok(ids: list[int], pulses: list[int], time_ms: object) -> bool:
    """True when plain-int ``ids``/``pulses`` and ``time_ms`` pass every ServoMove check."""
    return (0 < len(ids) <= SERVO_ID_MAX + 1 and type(time_ms) is int
            and 0 <= time_ms <= MOVE_TIME_MAX_MS
            and min(ids) >= 0 and max(ids) <= SERVO_ID_MAX
            and min(pulses) >= PULSE_MIN_US and max(pulses) <= PULSE_MAX_US
            and len(set(ids)) == len(ids))


def servo_move_arrays(ids: np.ndarray, pulses_us: np.ndarray, time_ms: int) -> bytes:
    """SERVO_MOVE bytes for integer arrays of servo ids and pulse widths (us).

    The same bytes and the same checks (the same :class:`DeviceError` for the same first bad
    value) as ``servo_move(zip(ids, pulses_us), time_ms)``, checked over the whole vectors at
    once: the per-frame path of the serial and the simulated devices.
    """
    ids_a, pulses_a = np.asarray(ids), np.asarray(pulses_us)
    if ids_a.ndim != 1 or pulses_a.shape != ids_a.shape:
        raise DeviceError(f"LSC frame: expected one pulse width per servo id (two equal 1-D "
                          f"vectors), got shapes {ids_a.shape!r} and {pulses_a.shape!r}")
    id_list, pulse_list = ids_a.tolist(), pulses_a.tolist()  # plain Python numbers
    if ids_a.dtype.kind in "iu" and pulses_a.dtype.kind in "iu":
        time = int(time_ms) if isinstance(time_ms, np.integer) else time_ms
        if servo_values_ok(id_list, pulse_list, time):
            return _pack_servo_move(id_list, pulse_list, time)
    # something is wrong (or unusual): the element-wise checks name the first bad value
    return ServoMove(tuple(zip(id_list, pulse_list, strict=True)), time_ms).encode()


@dataclass(frozen=True)
class _NoParams:
    """Frames without parameters: ``55 55 02 CODE``."""

    def encode(self) -> bytes:
        return _frame(self.code, b"")


@dataclass(frozen=True)
class _ServoIds:
    """Frames whose parameters are a count and that many servo ids."""

    ids: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", _check_ids(self.ids))

    def encode(self) -> bytes:
        return _frame(self.code, bytes((len(self.ids), *self.ids)))


@dataclass(frozen=True)
class _GroupTimes:
    """Frames whose parameters are an action group and a 16-bit repetition count."""

    group: int
    times: int

    def __post_init__(self) -> None:
        _check_int("action group", self.group, 0, 255)
        _check_int("repetitions", self.times, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _frame(self.code, bytes((self.group,)) + _u16(self.times))


@dataclass(frozen=True)
class ActionGroupRun(_GroupTimes):
    """Run stored action group ``group`` ``times`` times (0 = forever)."""

    code: ClassVar[int] = Command.ACTION_GROUP_RUN


@dataclass(frozen=True)
class ActionGroupStop(_NoParams):
    """Stop the running action group."""

    code: ClassVar[int] = Command.ACTION_GROUP_STOP


@dataclass(frozen=True)
class ActionGroupSpeed:
    """Set action group ``group``'s speed in percent (group 0xFF = all groups)."""

    group: int
    percent: int
    code: ClassVar[int] = Command.ACTION_GROUP_SPEED

    def __post_init__(self) -> None:
        _check_int("action group", self.group, 0, 255)
        _check_int("speed (%)", self.percent, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _frame(self.code, bytes((self.group,)) + _u16(self.percent))


@dataclass(frozen=True)
class GetBatteryVoltage(_NoParams):
    """Ask for the supply voltage; the board answers with :class:`BatteryVoltage`."""

    code: ClassVar[int] = Command.GET_BATTERY_VOLTAGE


@dataclass(frozen=True)
class MultServoUnload(_ServoIds):
    """Switch the listed servos off (no holding torque)."""

    code: ClassVar[int] = Command.MULT_SERVO_UNLOAD


@dataclass(frozen=True)
class MultServoPosRead(_ServoIds):
    """Ask for the listed servos' positions; the board answers with :class:`ServoPositions`."""

    code: ClassVar[int] = Command.MULT_SERVO_POS_READ


# ---------------------------------------------------------------------------------------------
# messages: board -> host


@dataclass(frozen=True)
class ActionGroupRunning(_GroupTimes):
    """Notice: action group ``group`` started, to run ``times`` times."""

    code: ClassVar[int] = Reply.ACTION_GROUP_RUNNING


@dataclass(frozen=True)
class ActionGroupStopped(_NoParams):
    """Notice: the action group was stopped."""

    code: ClassVar[int] = Reply.ACTION_GROUP_STOPPED


@dataclass(frozen=True)
class ActionGroupComplete(_GroupTimes):
    """Notice: action group ``group`` finished its ``times`` runs."""

    code: ClassVar[int] = Reply.ACTION_GROUP_COMPLETE


@dataclass(frozen=True)
class BatteryVoltage:
    """Reply to :class:`GetBatteryVoltage`: ``55 55 04 0F lo hi``, millivolts."""

    millivolts: int
    code: ClassVar[int] = Reply.BATTERY_VOLTAGE

    def __post_init__(self) -> None:
        _check_int("battery voltage (mV)", self.millivolts, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _frame(self.code, _u16(self.millivolts))


@dataclass(frozen=True)
class ServoPositions:
    """Reply to :class:`MultServoPosRead`: ((id, position), ...)."""

    positions: tuple[tuple[int, int], ...]
    code: ClassVar[int] = Reply.SERVO_POSITIONS

    def __post_init__(self) -> None:
        positions = tuple((_check_int("servo id", i, 0, SERVO_ID_MAX),
                           _check_int(f"servo {i} position", p, 0, 0xFFFF))
                          for i, p in self.positions)
        _check_ids(i for i, _ in positions)
        object.__setattr__(self, "positions", positions)

    def encode(self) -> bytes:
        body = bytes((len(self.positions),))
        for servo, pos in self.positions:
            body += bytes((servo,)) + _u16(pos)
        return _frame(self.code, body)


HostMessage = (ServoMove | ActionGroupRun | ActionGroupStop | ActionGroupSpeed
               | GetBatteryVoltage | MultServoUnload | MultServoPosRead)
BoardMessage = (ActionGroupRunning | ActionGroupStopped | ActionGroupComplete | BatteryVoltage
                | ServoPositions)
Message = HostMessage | BoardMessage


# ---------------------------------------------------------------------------------------------
# encoder functions


def servo_move(positions: Mapping[int, int] | Iterable[tuple[int, int]], time_ms: int) -> bytes:
    """SERVO_MOVE frame: ``servo_move({1: 2000}, 1000)`` = ``55 55 08 03 01 E8 03 01 D0 07``."""
    items = positions.items() if isinstance(positions, Mapping) else positions
    return ServoMove(tuple(items), time_ms).encode()


def action_group_run(group: int, times: int = 1) -> bytes:
    return ActionGroupRun(group, times).encode()


def action_group_stop() -> bytes:
    return ActionGroupStop().encode()


def action_group_speed(group: int, percent: int) -> bytes:
    return ActionGroupSpeed(group, percent).encode()


def get_battery_voltage() -> bytes:
    return GetBatteryVoltage().encode()


def mult_servo_unload(ids: Iterable[int]) -> bytes:
    return MultServoUnload(tuple(ids)).encode()


def mult_servo_pos_read(ids: Iterable[int]) -> bytes:
    return MultServoPosRead(tuple(ids)).encode()


def battery_voltage_reply(millivolts: int) -> bytes:
    """The board's reply ``55 55 04 0F lo hi``."""
    return BatteryVoltage(millivolts).encode()


def servo_positions_reply(positions: Mapping[int, int] | Iterable[tuple[int, int]]) -> bytes:
    items = positions.items() if isinstance(positions, Mapping) else positions
    return ServoPositions(tuple(items)).encode()
