"""The device seam: one interface, a serial and a simulated implementation, chosen by URL.

``open_device("serial:///dev/ttyUSB0,/dev/ttyUSB1", layout)`` (one port per controller, in
device-file order) or ``open_device("sim://?faults...", layout, clock)``. Both take setpoint
vectors in millimetres in :class:`~crs_study.layout.Layout` actuator order and turn them into
LSC SERVO_MOVE frames (hardware.md); the simulated device decodes those very bytes.

Wire arithmetic (hardware.md): 9600 baud 8N1 is 10 bits a byte, 1.0417 ms; a SERVO_MOVE for
n servos is 3 n + 7 bytes.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from crs_study.clock import Clock, RealClock
from crs_study.errors import DeviceError
from crs_study.layout import Layout

BAUD_RATE = 9600
BITS_PER_BYTE = 10  # start + 8 data + stop
BYTE_TIME_S = BITS_PER_BYTE / BAUD_RATE


class DeviceWarning(UserWarning):
    """Something odd but not fatal about the device (no battery answer, unbalanced channels)."""


def servo_move_bytes(n_servos: int) -> int:
    """Bytes on the wire for a SERVO_MOVE frame of ``n_servos``: 3 n + 7 (hardware.md)."""
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
    the frame. 19 servos: 64 bytes, 66.7 ms (hardware.md).
    """
    busiest = max(channels_per_controller(layout).values(), default=0)
    return servo_move_bytes(busiest) * BYTE_TIME_S if busiest else 0.0


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
    """A CRS display behind one or more LSC controllers.

    Use as a context manager: ``__exit__`` always calls :meth:`close`, which moves every
    actuator to the safe neutral pose and releases the ports, on success, error or Ctrl-C.
    """

    def __init__(self, layout: Layout, clock: Clock | None = None) -> None:
        self.layout = layout
        self.clock = clock or RealClock()

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

    def displayed_setpoints(self, t: float | None = None) -> np.ndarray:
        """Where the actuators are at clock time ``t`` (mm, actuator order).

        The simulated device returns modelled servo positions; a real device, which gets no
        feedback from PWM servos, returns the last commanded setpoints.
        """
        raise NotImplementedError

    def battery_mv(self) -> list[float | None]:
        """Battery voltage per controller in millivolts (None where unknown)."""
        return [None] * len(self.layout.controllers)

    def neutral(self) -> FrameReport:
        return self.send(self.layout.neutral_setpoints())

    def __enter__(self) -> Device:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def open_device(url: str, layout: Layout, clock: Clock | None = None, **options: object
                ) -> Device:
    """Device for a URL: ``serial://PORT[,PORT...]`` or ``sim://[?options]``."""
    if url.startswith("serial://"):
        from crs_study.device.serial_device import SerialDevice

        return SerialDevice.from_url(url, layout, clock, **options)
    if url.startswith("sim://"):
        from crs_study.device.simulated import SimulatedDevice

        return SimulatedDevice.from_url(url, layout, clock, **options)
    raise DeviceError(
        f"unknown device URL {url!r}; expected serial:///dev/ttyUSB0[,/dev/ttyUSB1] or sim://"
    )
