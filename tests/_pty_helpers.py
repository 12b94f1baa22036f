"""Shared by the device tests: pseudo-terminal boards, a base-0, reversed layout, and a
stepped clock that drives the serial device's writer threads through chosen times.

The far end of each pty decodes what the host writes with the codec (host direction) and
answers GET_BATTERY_VOLTAGE like a board (docs/device.md: reply ``55 55 04 0F lo hi``). Test
modules take the ``boards`` fixture by importing ``boards_fixture``.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
from collections.abc import Callable

import pytest

from crs_study.device import codec, decoder

#: How long a test waits for bytes to be written or to arrive before it calls the wire
#: stuck. A frame takes milliseconds; a worker thread of a machine running the suite beside
#: other work can wait a second or more for a core (a 1 s wait failed once in 2400 tests), so
#: this bounds a hang, never a speed (speed is `crs-study bench device`'s).
STALLED_S = 30.0


class PtyBoard:
    """The board end of a pty pair: decodes host frames, answers battery requests."""

    def __init__(self, battery_mv: int | None = 7400, garbage: bytes = b"") -> None:
        self.master, slave = pty.openpty()
        self.path = os.ttyname(slave)
        self._slave = slave  # kept open so the master sees no hang-up before the device opens
        self.battery_mv = battery_mv
        self.garbage = garbage
        self.raw = bytearray()
        self.frames: list[decoder.Frame] = []
        self.decoder = decoder.FrameDecoder(codec.Direction.HOST)
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

    def wait_until(self, holds: Callable[[list[codec.ServoMove]], bool],
                   timeout: float = STALLED_S) -> list[codec.ServoMove]:
        """The moves decoded so far, once ``holds(moves)`` is true (or at the timeout).

        This end decodes in a thread of its own, so the last frame of a writer that has
        already closed its port can still be on its way to :meth:`moves`: a test that checks
        the last move waits until it is the one expected, not until a count of moves."""
        deadline = time.monotonic() + timeout
        moves = self.moves()
        while not holds(moves) and time.monotonic() < deadline:
            time.sleep(0.005)
            moves = self.moves()
        return moves

    def wait_for_last(self, holds: Callable[[codec.ServoMove], bool], count: int = 1,
                      timeout: float = STALLED_S) -> list[codec.ServoMove]:
        """The moves decoded so far, once there are ``count`` or more and the last one
        satisfies ``holds`` (close()'s neutral pose, as a rule), or at the timeout."""
        return self.wait_until(lambda moves: len(moves) >= count and holds(moves[-1]), timeout)

    def wait_for(self, count: int, timeout: float = STALLED_S) -> list[codec.ServoMove]:
        """The moves decoded so far, once there are ``count`` (or at the timeout)."""
        return self.wait_until(lambda moves: len(moves) >= count, timeout)

    def wait_for_bytes(self, count: int, timeout: float = STALLED_S) -> bool:
        """Wait until ``count`` bytes have arrived; False on timeout."""
        deadline = time.monotonic() + timeout
        while len(self.raw) < count and time.monotonic() < deadline:
            time.sleep(0.002)
        return len(self.raw) >= count

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
    """``layout`` with its first controller counting channels from 0 (docs/device.md leaves 0 or
    1 open) and actuator 2's calibration reversed (zero_us > full_us)."""
    from dataclasses import replace

    first = layout.controllers[0]
    acts = [replace(a, channel=a.channel - 1) if a.controller == first.name else a
            for a in layout.actuators]
    cal = acts[2].calibration
    acts[2] = replace(acts[2], calibration=replace(cal, zero_us=cal.full_us, full_us=cal.zero_us))
    controllers = (replace(first, channel_base=0), *layout.controllers[1:])
    return replace(layout, controllers=controllers, actuators=tuple(acts))


class SteppedClock:
    """A clock that moves only when the test moves it, waking the serial device's writer
    threads when it does (they wait on their port's condition, as for a hand-over).

    With it, the writer threads decide at exactly the times the test steps to, so a
    SerialDevice can be run through the same event times as a SimulatedDevice on a virtual
    clock (:func:`step_serial_device`).
    """

    is_virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)
        self.device = None  # the SerialDevice whose writers to wake

    def now(self) -> float:
        return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.set(self._now + seconds)

    def sleep_until(self, deadline: float) -> None:
        if deadline > self._now:
            self.set(deadline)

    def set(self, t: float) -> None:
        assert t >= self._now, (t, self._now)
        self._now = float(t)
        for port in getattr(self.device, "ports", ()):
            with port.cond:
                port.cond.notify_all()


class RecordingPort:
    """A real pyserial port (here a pty) that records each write with the clock time it was
    made, so a test can compare when bytes went out, not only which."""

    def __init__(self, port, clock) -> None:
        self._port = port
        self._clock = clock
        self.writes: list[tuple[float, bytes]] = []

    def write(self, data: bytes) -> int:
        self.writes.append((self._clock.now(), bytes(data)))
        return self._port.write(data)

    def __getattr__(self, name: str):
        return getattr(self._port, name)


def _settled(device, clock) -> bool:
    """Every writer has done what is due by ``clock.now()`` (nothing due, nothing mid-write)."""
    for port in device.ports:
        with port.cond:
            if port.error is not None:
                raise AssertionError(f"{port.label}: {port.error}")
            if port.writing_since is not None or port.writes.next_write_at() <= clock.now():
                return False
    return True


def settle(device, clock, timeout: float = 5.0) -> None:
    """Wait (real time) until the writer threads have caught up with the stepped clock."""
    deadline = time.monotonic() + timeout
    while not _settled(device, clock):
        if time.monotonic() > deadline:
            raise AssertionError(f"the writer threads did not settle at t={clock.now()!r}")
        time.sleep(0.0002)


def _next_write_at(device) -> float:
    due = []
    for port in device.ports:
        with port.cond:
            due.append(port.writes.next_write_at())
    return min(due)


def step_serial_device(device, clock: SteppedClock, times, frames, until: float) -> float:
    """Hand ``frames[k]`` to the opened ``device`` at ``times[k]``, stepping ``clock`` through
    every time a write falls due in between (a write due at a frame's time goes first, the
    policy's tie rule); then on until every frame is written, and to ``until`` if later.
    Returns the end time, at which every wire is free."""
    for t, frame in zip(times, frames, strict=True):
        while (due := _next_write_at(device)) < t:
            clock.set(due)
            settle(device, clock)
        clock.set(t)
        settle(device, clock)
        device.send(frame)
        settle(device, clock)
    while (due := _next_write_at(device)) < float("inf"):
        clock.set(due)
        settle(device, clock)
    clock.set(max(until, clock.now(), *(port.writes.free_at for port in device.ports)))
    settle(device, clock)
    return clock.now()
