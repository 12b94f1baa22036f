"""A device file's boards as virtual LSC-24 boards on pseudo-terminals: rehearsal without
hardware (``crs-study device boards``).

:class:`VirtualBoards` starts one :class:`~.virtual_pty.VirtualControllerPty` per controller
of a layout, each board's servos resting and moving as the layout's calibration says (as
:class:`~.simulated.SimulatedDevice` models them), its wire drained at the baud rate. Its
:attr:`~VirtualBoards.url` (``serial:///dev/pts/N,/dev/pts/M``) works wherever a real
device's URL does, and each board has a tap (:attr:`~VirtualBoards.taps`) for ``device
monitor``. What every board receives is decoded into :class:`Heard` events
(:meth:`~VirtualBoards.heard`).

A pseudo-terminal has no USB serial number or by-id path: nothing tells two of them apart
but their paths (``device check`` says so).
"""

from __future__ import annotations

import queue
import time
from dataclasses import dataclass

from crs_study.device.base import BAUD_RATE
from crs_study.device.codec import Direction, Message
from crs_study.device.decoder import FrameDecoder
from crs_study.device.virtual_controller import ServoSpec, VirtualController, speed_us_per_s
from crs_study.device.virtual_pty import VirtualControllerPty
from crs_study.geometry.layout import Layout


@dataclass(frozen=True)
class Heard:
    """A frame a board received (``message`` None: ``skipped`` bytes that made no frame)."""

    board: str
    time: float  # time.monotonic() when its last byte arrived
    message: Message | None
    skipped: int = 0


def board_specs(layout: Layout, name: str) -> list[ServoSpec]:
    """The servos of controller ``name``: rest and speed from the layout's calibration."""
    controller = next(c for c in layout.controllers if c.name == name)
    specs = [ServoSpec() for _ in range(controller.channels)]
    for a in layout.actuators:
        if a.controller == name:
            cal = a.calibration
            specs[a.channel - controller.channel_base] = ServoSpec(
                rest_us=cal.zero_us,
                max_speed_us_s=speed_us_per_s(cal.zero_us, cal.full_us, cal.travel_mm,
                                              layout.servo_speed_s_per_mm))
    return specs


class VirtualBoards:
    """The layout's boards on ptys (module docstring); a context manager."""

    def __init__(self, layout: Layout, baud: int | None = BAUD_RATE, tap: bool = True) -> None:
        self.layout = layout
        self._heard: queue.Queue[Heard] = queue.Queue()
        self._decoders: dict[str, FrameDecoder] = {}
        self.ptys: list[VirtualControllerPty] = []
        try:
            for c in layout.controllers:
                board = VirtualController(c.name, c.channels, c.channel_base,
                                          board_specs(layout, c.name), t0=time.monotonic())
                self._decoders[c.name] = FrameDecoder(Direction.HOST)
                self.ptys.append(VirtualControllerPty(board, baud=baud, tap=tap,
                                                      listener=self._listener(c.name)))
        except BaseException:
            self.close()
            raise

    def _listener(self, name: str):
        decoder = self._decoders[name]

        def hear(data: bytes, arrived: float) -> None:  # the board's thread
            for frame in decoder.feed(data):
                self._heard.put(Heard(name, arrived, frame.message))
            for run in decoder.take_skipped():
                self._heard.put(Heard(name, arrived, None, len(run.data)))
        return hear

    @property
    def ports(self) -> list[str]:
        """The boards' port paths, in device-file order."""
        return [p.port for p in self.ptys]

    @property
    def taps(self) -> list[str | None]:
        """Each board's tap path (what it receives, for ``device monitor --port``)."""
        return [p.tap_port for p in self.ptys]

    @property
    def url(self) -> str:
        """``serial://PORT_A,PORT_B``: the device URL of these boards."""
        return "serial://" + ",".join(self.ports)

    def heard(self, timeout: float | None = None) -> list[Heard]:
        """What the boards received since the last call (waits up to ``timeout`` for one)."""
        out: list[Heard] = []
        try:
            out.append(self._heard.get(timeout=timeout) if timeout else
                       self._heard.get_nowait())
            while True:
                out.append(self._heard.get_nowait())
        except queue.Empty:
            return out

    def close(self) -> None:
        for bridge in self.ptys:
            bridge.close()

    def __enter__(self) -> VirtualBoards:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
