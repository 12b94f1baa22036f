"""Signals that end a command as Ctrl-C does: SIGTERM (a kill) and SIGHUP (a closed terminal),
and the parent-death signal that ends a worker process with the command that started it.

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
import ctypes
import os
import signal
import sys
import threading
import time
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


#: How often a worker's watchdog looks whether its parent is still alive (s).
WATCHDOG_S = 0.5


def die_with_parent(parent: int) -> None:
    """A worker's initializer: the worker ends when the process that started it does.

    On Linux the kernel sends SIGKILL to the worker when its parent dies
    (``prctl(PR_SET_PDEATHSIG)``, through ctypes); elsewhere, and should that call fail, a
    daemon thread checks every :data:`WATCHDOG_S` whether the parent is still the worker's
    parent (an orphan is adopted by another process) and kills the worker otherwise. So a
    SIGKILL of ``crs-study dry-run --jobs N`` leaves no worker writing into the dataset or
    holding its stdout open (a ``| tee`` ends; a session cut so resumes on the next run),
    and one of ``crs-study power --jobs N`` no worker computing for nobody.
    """
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass  # the watchdog below still ends the worker
    if os.getppid() != parent:  # the parent died before the call above took effect
        os.kill(os.getpid(), signal.SIGKILL)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCHDOG_S)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


#: prctl option: the signal a process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
