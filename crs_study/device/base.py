"""The device seam: one interface, a serial and a simulated implementation, chosen by URL.

``open_device("serial:///dev/ttyUSB0,/dev/ttyUSB1", layout)`` (one port per controller, in
device-file order) or ``open_device("sim://?faults...", layout, clock)``: the URL's scheme is
looked up in a registry (:func:`register_scheme`), which :mod:`crs_study.device` fills with
its two implementations, so this module never imports them. Both take setpoint
vectors in millimetres in :class:`~crs_study.geometry.Layout` actuator order and turn them into
LSC SERVO_MOVE frames (LSC protocol); the simulated device decodes those very bytes.

Wire arithmetic (LSC protocol): 9600 baud 8N1 is 10 bits a byte, 1.0417 ms; a SERVO_MOVE for
n servos is 3 n + 7 bytes.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Self

import numpy as np

from crs_study.clock import Clock, RealClock
from crs_study.errors import CrsStudyWarning, DeviceError
from crs_study.geometry.layout import Layout

BAUD_RATE = 9600
BITS_PER_BYTE = 10  # start + 8 data + stop
BYTE_TIME_S = BITS_PER_BYTE / BAUD_RATE


class DeviceWarning(CrsStudyWarning):
    """Something odd but not fatal about the device (no battery answer, unbalanced channels);
    the command line prints it in one line, like every message of ours."""


#: A board reporting less than this on open is refused (2S pack cut-off, 3.0 V a cell); both
#: devices use it (``min_battery_mv`` of the serial device; 0 turns its check off).
LOW_BATTERY_MV = 6000


def servo_move_bytes(n_servos: int) -> int:
    """Bytes on the wire for a SERVO_MOVE frame of ``n_servos``: 3 n + 7 (LSC protocol)."""
    return 3 * n_servos + 7


def channels_per_controller(layout: Layout) -> dict[str, int]:
    """How many actuators each controller drives."""
    counts = {c.name: 0 for c in layout.controllers}
    for actuator in layout.actuators:
        counts[actuator.controller] += 1
    return counts


def full_frame_wire_time_s(layout: Layout) -> float:
    """Time for a frame that moves every channel: the busiest controller's SERVO_MOVE.

    Controllers have their own ports and are written concurrently, so the slowest one bounds
    the frame. 19 servos: 64 bytes, 66.7 ms (LSC protocol).
    """
    busiest = max(channels_per_controller(layout).values(), default=0)
    return servo_move_bytes(busiest) * BYTE_TIME_S if busiest else 0.0


def default_move_ms(layout: Layout, baud: int = BAUD_RATE) -> int:
    """SERVO_MOVE time when a frame is sent without one: one full frame of the busiest
    controller on the wire (ms, rounded up; 67 ms on the shipped 2D device), so a servo
    moves over the time until the next frame can arrive."""
    busiest = max(channels_per_controller(layout).values(), default=0)
    return math.ceil(servo_move_bytes(busiest) * BITS_PER_BYTE / baud * 1000)


def full_frame_rate_hz(layout: Layout) -> float:
    """Highest frame rate the wire allows when every channel changes in every frame."""
    wire = full_frame_wire_time_s(layout)
    return 1.0 / wire if wire else float("inf")


@dataclass(frozen=True)
class FrameReport:
    """What happened to one frame handed to :meth:`Device.send`."""

    commanded_at: float  # clock time the frame was handed over (s)
    wire_done_at: float  # clock time its last byte leaves (or left) the port (s)
    bytes_sent: tuple[int, ...]  # per controller, in device-file order (0 = nothing sent)
    channels_sent: int  # channels that went on the wire for this frame
    merged: bool = False  # the wire was busy: the frame replaced a pending one (no queueing)

    @property
    def latency_s(self) -> float:
        return self.wire_done_at - self.commanded_at


class Device(ABC):
    """A CRS display behind one or more LSC controllers: the interface the runner and the
    ``device`` commands use (implementations: :class:`~.serial_device.SerialDevice`,
    :class:`~.simulated.SimulatedDevice`; chosen by URL with :func:`open_device`).

    Use as a context manager: ``__exit__`` always calls :meth:`close`, which moves every
    actuator to the safe neutral pose and releases the ports, on success, error or Ctrl-C.
    Faults met on the way (a neutral pose that could not be sent) are appended to
    :attr:`faults`.
    """

    def __init__(self, layout: Layout, clock: Clock | None = None) -> None:
        self.layout = layout
        self.clock: Clock = clock or RealClock()
        self.faults: list[str] = []

    @abstractmethod
    def open(self) -> None:
        """Open ports (and check the battery where the board reports it)."""

    @abstractmethod
    def send(self, setpoints_mm: np.ndarray, move_ms: int | None = None) -> FrameReport:
        """Command one frame; never blocks longer than one frame period, never queues.

        Raises :class:`DeviceError` for a setpoint outside a channel's calibrated range
        (nothing reaches the wire) or a port that failed.
        """

    @abstractmethod
    def close(self) -> None:
        """Move to the neutral pose (best effort) and release every port. Idempotent."""

    @abstractmethod
    def displayed_setpoints(self, t: float | None = None) -> np.ndarray:
        """Where the actuators are at clock time ``t`` (mm, actuator order).

        The simulated device returns modelled servo positions; a real device, which gets no
        feedback from PWM servos, returns the last commanded setpoints.
        """

    def battery_mv(self) -> list[float | None]:
        """Battery voltage per controller in millivolts (None where unknown)."""
        return [None] * len(self.layout.controllers)

    def heartbeat_ask(self) -> object:
        """Put the heartbeat's question on the wire now and return what
        :meth:`heartbeat_check` needs; nothing waits for the answer.

        The LSC boards acknowledge no move, but they answer GET_BATTERY_VOLTAGE
        (docs/device.md), and a board reads its bytes in order: an answer to a question asked
        after a trial's last frame says the board read the whole trial. The runner asks right
        after the stimulus (so a person's response is never delayed by the wait) and checks
        after the response. A device that cannot be asked (the default) does nothing.
        """
        return None

    def heartbeat_check(self, asked: object) -> None:
        """Raise :class:`DeviceError` naming each board that gave no answer to the question
        :meth:`heartbeat_ask` put (it stopped reading: the frames since its last answer may
        never have moved its servos) or reports a battery below :data:`LOW_BATTERY_MV`."""
        return None

    def heartbeat(self) -> None:
        """Ask, then check at once (:meth:`heartbeat_ask`, :meth:`heartbeat_check`)."""
        self.heartbeat_check(self.heartbeat_ask())

    def neutral(self) -> FrameReport:
        """Send the neutral pose (every pixel at base, no boundary feed)."""
        return self.send(self.layout.neutral_setpoints())

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


#: Makes a device from its URL: ``factory(url, layout, clock, **options)``.
DeviceFactory = Callable[..., Device]

#: URL scheme (``"serial"`` for ``serial://...``) -> factory. The package registers its own
#: (:mod:`crs_study.device`: ``serial``, ``sim``); :func:`register_scheme` adds more.
_SCHEMES: dict[str, DeviceFactory] = {}


def register_scheme(scheme: str, factory: DeviceFactory) -> None:
    """Let :func:`open_device` make ``scheme://...`` URLs with ``factory``."""
    _SCHEMES[scheme] = factory


def open_device(url: str, layout: Layout, clock: Clock | None = None, **options: object
                ) -> Device:
    """Device for a URL: ``serial://PORT[,PORT...]`` or ``sim://[?options]`` (or a scheme
    added with :func:`register_scheme`), not yet opened."""
    scheme, sep, _ = url.partition("://")
    factory = _SCHEMES.get(scheme) if sep else None
    if factory is None:
        raise DeviceError(
            f"unknown device URL {url!r}; expected serial:///dev/ttyUSB0[,/dev/ttyUSB1] or sim://"
        )
    return factory(url, layout, clock, **options)
