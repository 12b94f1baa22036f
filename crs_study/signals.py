"""Signals that end a command as Ctrl-C does: SIGTERM (a kill) and SIGHUP (a closed terminal).

Python turns SIGINT (Ctrl-C) into :class:`KeyboardInterrupt`, so ``finally`` blocks and context
managers run: a device goes to its neutral pose and releases its ports, a session pauses
safely. SIGTERM and SIGHUP would otherwise end the process on the spot, servos wherever the
last frame left them. Within :func:`terminate_as_interrupt` they raise :class:`SignalInterrupt`
(a :class:`KeyboardInterrupt`, so every ``except KeyboardInterrupt`` treats them alike) in the
main thread; :func:`deferred` holds all three back while something must finish whole.

Handlers can only be installed from the main thread; elsewhere these context managers do
nothing (the signals keep whatever handling they had).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from typing import Any

#: Signals that end a command as Ctrl-C does: Ctrl-C, a kill, a closed terminal or SSH.
PAUSE_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class SignalInterrupt(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised as a :class:`KeyboardInterrupt`; :attr:`signum` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def describe(interrupt: BaseException) -> str:
    """What stopped the command, for a message: ``"Ctrl-C"``, ``"SIGTERM"`` or ``"SIGHUP"``."""
    return (signal.Signals(interrupt.signum).name if isinstance(interrupt, SignalInterrupt)
            else "Ctrl-C")


@contextlib.contextmanager
def handling(handler: Callable[[int, Any], Any] | int, signums: tuple[int, ...]
             ) -> Iterator[None]:
    """Within the block ``handler`` serves ``signums``; restored after (main thread only)."""
    old = {}
    if threading.current_thread() is threading.main_thread():
        for signum in signums:
            old[signum] = signal.signal(signum, handler)
    try:
        yield
    finally:
        for signum, previous in old.items():
            signal.signal(signum, previous)


def _raise_interrupt(signum: int, frame: object) -> None:
    raise SignalInterrupt(signum)


def terminate_as_interrupt() -> contextlib.AbstractContextManager[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`SignalInterrupt` (as Ctrl-C would)."""
    return handling(_raise_interrupt, PAUSE_SIGNALS[1:])


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP back until the block ends, then raise the first.

    For work that must not be cut in two (a trial being stored, a device being put to rest):
    the block finishes, then the interrupt arrives as it would have.
    """
    caught: list[int] = []
    with handling(lambda signum, frame: caught.append(signum), PAUSE_SIGNALS):
        yield
    if caught:
        raise KeyboardInterrupt if caught[0] == signal.SIGINT else SignalInterrupt(caught[0])
