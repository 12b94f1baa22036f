"""The options of the simulated device: what a ``sim://`` URL (or keyword arguments) set.

URL syntax (options may also be given as keyword arguments; keywords win)::

    sim://[?key=value[&key=value...]]

    baud=9600            bits per second on every port (10 bits a byte, 8N1)
    move_ms=67           SERVO_MOVE time when send() is given none (default: one full frame
                         of the busiest controller on the wire, as the serial device)
    neutral_move_ms=500  move time of the neutral pose sent on close()
    refresh_s=1.0        the first frame this long after the last full one carries every
                         channel (0: never; device/writes.py)
    deadband_us=1        resend a channel when its pulse moved by more than this (schedule.py)
    battery_mv=7400      what each board reports while healthy
    seed=0               seed of the garbage generator
    garbage_rate=0.01    probability, per byte sent, that one random byte is inserted before it
    disconnect_at=3.5    every port vanishes 3.5 s after open(); ``B@3.5``: only port B
    stall=A:3@2.0        channel A:3 stalls 2.0 s after open(); several: ``A:3@2,B:1@4``
    brownout_at=5.0      the servo supply browns out 5.0 s after open(); ``A@5``: board A only
    hang_at=B@2.0        board B stops reading 2.0 s after open(): bytes lost, no answers,
                         servos hold their last command (seen only by a heartbeat)
    fault_period=20      the timed faults (disconnect_at, stall, brownout_at, hang_at) come
                         back on every resumed run of a session, the first of them 20 s after
                         the device opens (their spacing kept); without it they fire once per
                         session
    faults_met=0         set by the session runner: the device faults the session has met
                         (its sidecar's Faults); with one or more and no fault_period, the
                         timed faults are not injected again

Times are seconds after :meth:`SimulatedDevice.open`. A malformed or unknown option is a
one-line :class:`~crs_study.errors.DeviceError`.

Once per session: a session that met a timed fault is resumed by running the same command
again, which opens the device anew. Were the faults armed again on every open, the resumed
run would meet the same fault at the same time after its start and never progress; so
without ``fault_period`` a session meets each example fault once and then runs to the end.

The faults these options inject, as the caller sees them, are described in
:mod:`crs_study.device.simulated`.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, fields, replace
from urllib.parse import parse_qsl, urlsplit

from crs_study.device.base import BAUD_RATE
from crs_study.device.virtual_controller import NORMAL_BATTERY_MV
from crs_study.device.writes import (
    DEFAULT_DEADBAND_US,
    DEFAULT_REFRESH_S,
)
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout


@dataclass(frozen=True)
class SimOptions:
    """Options of a ``sim://`` URL (module docstring)."""

    baud: int = BAUD_RATE
    move_ms: int | None = None  # None: one full frame's wire time (SerialDevice's default)
    neutral_move_ms: int = 500
    refresh_s: float = DEFAULT_REFRESH_S
    deadband_us: int = DEFAULT_DEADBAND_US
    battery_mv: int = NORMAL_BATTERY_MV
    seed: int = 0
    garbage_rate: float = 0.0
    disconnect_at: tuple[tuple[str | None, float], ...] = ()  # (controller or None = all, s)
    stall: tuple[tuple[str, int, float], ...] = ()  # (controller, channel, s)
    brownout_at: tuple[tuple[str | None, float], ...] = ()
    hang_at: tuple[tuple[str | None, float], ...] = ()
    fault_period: float | None = None
    faults_met: int = 0

    def fault_shift(self) -> float | None:
        """How much later than written the timed faults fire on this opening: 0 on a
        session's first run (or before it met a fault); with ``fault_period``, so that the
        first comes that long after the open; None: not injected (once per session)."""
        if self.faults_met <= 0:
            return 0.0
        if self.fault_period is None:
            return None
        times = [at for _, at in self.disconnect_at] + [at for *_, at in self.stall] + \
            [at for _, at in self.brownout_at] + [at for _, at in self.hang_at]
        return self.fault_period - min(times, default=0.0)

    @classmethod
    def parse(cls, url: str, layout: Layout, **overrides: object) -> SimOptions:
        """Options from ``url`` and keyword ``overrides``; one-line DeviceError when malformed."""
        parts = urlsplit(url)
        if parts.scheme != "sim" or parts.netloc or parts.path not in ("", "/"):
            raise DeviceError(f"simulated device URL {url!r}: expected sim://[?key=value&...]")
        pairs: list[tuple[str, object]] = parse_qsl(parts.query, keep_blank_values=True,
                                                   strict_parsing=False)
        pairs += list(overrides.items())
        valid = [f.name for f in fields(cls)]
        values: dict[str, object] = {}
        for key, raw in pairs:
            if key not in valid:
                raise DeviceError(
                    f"{url!r}: unknown option {key!r}; valid: {', '.join(valid)}"
                )
            parsed = _PARSERS[key](url, key, raw, layout)
            if key in ("stall", "disconnect_at", "brownout_at", "hang_at"):
                # repeated keys add up (``stall=A:1@1&stall=A:2@2``)
                parsed = values.get(key, ()) + parsed  # type: ignore[operator]
            values[key] = parsed
        return replace(cls(), **values)


def _number(url: str, key: str, raw: object, kind: type, low: float, high: float
            ) -> float | int:
    what = "a whole number" if kind is int else "a number"
    try:
        if isinstance(raw, bool):
            raise TypeError
        if kind is int:
            value: float | int = int(raw, 10) if isinstance(raw, str) else operator.index(raw)
        else:
            value = float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        value = math.nan
    if not low <= value <= high:
        raise DeviceError(f"{url!r}: option {key}: expected {what} in [{low}, {high}], "
                          f"got {raw!r}")
    return value


def controller_names(layout: Layout) -> list[str]:
    """The controllers' names, in device-file order."""
    return [c.name for c in layout.controllers]


def _timed(url: str, key: str, raw: object, layout: Layout) -> tuple[tuple[str | None, float], ...]:
    """``T`` (every controller) or ``NAME@T``, comma separated."""
    out: list[tuple[str | None, float]] = []
    for item in str(raw).split(","):
        name, at, when = item.strip().rpartition("@")
        controller = name if at else None
        if controller is not None and controller not in controller_names(layout):
            raise DeviceError(
                f"{url!r}: option {key}: unknown controller {controller!r} in {item!r} "
                f"(controllers: {', '.join(controller_names(layout))})"
            )
        out.append((controller, float(_number(url, key, when, float, 0.0, 1e9))))
    return tuple(out)


def _stalls(url: str, key: str, raw: object, layout: Layout) -> tuple[tuple[str, int, float], ...]:
    """``CONTROLLER:CHANNEL@T``, comma separated; the channel must drive an actuator."""
    known = {(a.controller, a.channel) for a in layout.actuators}
    out = []
    for item in str(raw).split(","):
        ref, at, when = item.strip().partition("@")
        name, colon, channel = ref.partition(":")
        if not (at and colon and channel.isdigit()):
            raise DeviceError(f"{url!r}: option stall: expected CONTROLLER:CHANNEL@SECONDS like "
                              f"'A:3@2.0', got {item!r}")
        if (name, int(channel)) not in known:
            raise DeviceError(f"{url!r}: option stall: {ref!r} drives no actuator of "
                              f"{layout.name}")
        out.append((name, int(channel), float(_number(url, key, when, float, 0.0, 1e9))))
    return tuple(out)


_PARSERS = {
    "baud": lambda u, k, r, lay: _number(u, k, r, int, 300, 10_000_000),
    "move_ms": lambda u, k, r, lay: _number(u, k, r, int, 0, 30000),
    "neutral_move_ms": lambda u, k, r, lay: _number(u, k, r, int, 0, 30000),
    "deadband_us": lambda u, k, r, lay: _number(u, k, r, int, 0, 100),
    "refresh_s": lambda u, k, r, lay: _number(u, k, r, float, 0.0, 3600.0),
    "battery_mv": lambda u, k, r, lay: _number(u, k, r, int, 0, 0xFFFF),
    "seed": lambda u, k, r, lay: _number(u, k, r, int, 0, 2**63 - 1),
    "garbage_rate": lambda u, k, r, lay: _number(u, k, r, float, 0.0, 1.0),
    "fault_period": lambda u, k, r, lay: float(_number(u, k, r, float, 1e-3, 1e9)),
    "faults_met": lambda u, k, r, lay: _number(u, k, r, int, 0, 10**9),
    "disconnect_at": _timed,
    "stall": _stalls,
    "brownout_at": _timed,
    "hang_at": _timed,
}
