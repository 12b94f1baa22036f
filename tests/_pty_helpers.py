"""Shared by the device tests: pseudo-terminal boards, and a base-0, reversed layout.

The far end of each pty decodes what the host writes with the codec (host direction) and
answers GET_BATTERY_VOLTAGE like a board (hardware.md: reply ``55 55 04 0F lo hi``). Test
modules take the ``boards`` fixture by importing ``boards_fixture``.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time

import pytest

from crs_study.device import codec


class PtyBoard:
    """The board end of a pty pair: decodes host frames, answers battery requests."""

    def __init__(self, battery_mv: int | None = 7400, garbage: bytes = b"") -> None:
        self.master, slave = pty.openpty()
        self.path = os.ttyname(slave)
        self._slave = slave  # kept open so the master sees no hang-up before the device opens
        self.battery_mv = battery_mv
        self.garbage = garbage
        self.raw = bytearray()
        self.frames: list[codec.Frame] = []
        self.decoder = codec.FrameDecoder(codec.Direction.HOST)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.01)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            self.raw += data
            for frame in self.decoder.feed(data):
                self.frames.append(frame)
                if isinstance(frame.message, codec.GetBatteryVoltage) and self.battery_mv:
                    os.write(self.master, self.garbage + codec.battery_voltage_reply(
                        self.battery_mv))

    def moves(self) -> list[codec.ServoMove]:
        return [f.message for f in self.frames if isinstance(f.message, codec.ServoMove)]

    def wait_for(self, count: int, timeout: float = 2.0) -> list[codec.ServoMove]:
        deadline = time.monotonic() + timeout
        while len(self.moves()) < count and time.monotonic() < deadline:
            time.sleep(0.005)
        return self.moves()

    def vanish(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self.master)

    def close(self) -> None:
        if not self._stop.is_set():
            self._stop.set()
            self._thread.join()
            os.close(self.master)
        os.close(self._slave)


@pytest.fixture(name="boards")
def boards_fixture():
    made: list[PtyBoard] = []

    def make(n: int, **kwargs) -> list[PtyBoard]:
        made.extend(PtyBoard(**kwargs) for _ in range(n))
        return made[-n:]

    yield make
    for board in made:
        board.close()


def url_of(boards: list[PtyBoard]) -> str:
    """``serial://`` URL of the boards' ttys, in controller order."""
    return "serial://" + ",".join(b.path for b in boards)


def base0_reversed(layout):
    """``layout`` with its first controller counting channels from 0 (hardware.md leaves 0 or
    1 open) and actuator 2's calibration reversed (zero_us > full_us)."""
    from dataclasses import replace

    first = layout.controllers[0]
    acts = [replace(a, channel=a.channel - 1) if a.controller == first.name else a
            for a in layout.actuators]
    cal = acts[2].calibration
    acts[2] = replace(acts[2], calibration=replace(cal, zero_us=cal.full_us, full_us=cal.zero_us))
    controllers = (replace(first, channel_base=0), *layout.controllers[1:])
    return replace(layout, controllers=controllers, actuators=tuple(acts))
