"""Clocks: real (monotonic) time for sessions with people, virtual time for dry-runs.

Everything that waits or timestamps inside a session (runner, simulated device, responders)
takes a :class:`Clock`, so a dry-run on :class:`VirtualClock` runs as fast as the computer
allows while keeping every recorded time exactly as a real session would have it.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Seconds on a monotonic time line, and a way to wait on it."""

    def now(self) -> float:
        """Current time in seconds (monotonic; the origin is arbitrary)."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (no-op for zero or negative values)."""
        ...

    def sleep_until(self, deadline: float) -> None:
        """Wait until ``now() >= deadline``."""
        ...


class RealClock:
    """Wall time from :func:`time.monotonic`; sleeps really sleep."""

    is_virtual = False

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def sleep_until(self, deadline: float) -> None:
        self.sleep(deadline - self.now())


class VirtualClock:
    """Simulated time: ``sleep`` advances the clock at once instead of waiting.

    Thread-safe, so a simulated device and a runner can share one clock.
    """

    is_virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)

    def sleep_until(self, deadline: float) -> None:
        with self._lock:
            if deadline > self._now:
                self._now = float(deadline)

    def advance(self, seconds: float) -> None:
        """Move the clock forward by ``seconds`` (>= 0)."""
        if seconds < 0:
            raise ValueError(f"a virtual clock cannot go backwards (asked {seconds!r} s)")
        with self._lock:
            self._now += seconds
