"""The terminal keypad: a person answers with one keypress (no Enter).

The terminal on stdin is put in cbreak mode (``tty.setcbreak``: no line buffering, no echo,
but Ctrl-C still interrupts, so it stays the safe pause) for the whole session and restored
in ``finally`` / on exit. A reader thread timestamps every key on :func:`time.monotonic` the
moment it arrives, so keys typed during the stimulus are accepted with their true time (a
response before the stimulus offset has a negative response time from offset), and response
times are exact to the millisecond on the same monotonic clock the runner uses
(:class:`~crs_study.clock.RealClock`).

Keys: the protocol's response keys answer (each names a symbol of its stimulus set: the keys
``0``-``9`` for digits, the letters for the letter set; without a protocol, the default set's
keys); ``q`` (or Escape) asks for a safe pause (as Ctrl-C); anything else is ignored. At an
experimenter prompt, Space or Enter continues.
"""

from __future__ import annotations

import os
import queue
import select
import sys
import termios
import threading
import time
import tty
from typing import TextIO

from crs_study.clock import Clock
from crs_study.errors import ConfigError, SessionError
from crs_study.protocol.plan import PlannedTrial
from crs_study.session.responders.base import PAUSE_KEYS, Responder, Response, StimulusRecord
from crs_study.stimuli.sets import default_set
from crs_study.stimuli.strokes import Symbol

QUIT_KEYS = PAUSE_KEYS
CONTINUE_KEYS = frozenset({" ", "\r", "\n"})


class PauseRequested(KeyboardInterrupt):
    """The quit key was pressed: handled exactly like Ctrl-C (a safe pause)."""


class KeypadResponder(Responder):
    """Single keypresses from a terminal, timed on :func:`time.monotonic`."""

    name = "keypad"
    needs_real_clock = True
    simulated = False

    def __init__(self, fd: int | None = None, output: TextIO | None = None,
                 poll_s: float = 0.02, keys: dict[str, Symbol] | None = None) -> None:
        self.keys = dict(keys) if keys is not None else \
            {key: symbol for symbol, key in default_set().keys.items()}
        clash = sorted(set(self.keys) & QUIT_KEYS)
        if clash:
            raise ConfigError(f"keypad: response key {clash[0]!r} is also the pause key; "
                              f"choose another (pause keys: q, Q, Escape)")
        self.fd = fd  # None: stdin, looked up when the keypad opens
        self.output = output if output is not None else sys.stderr
        self.poll_s = poll_s
        self._keys: queue.Queue[tuple[float, str]] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: list | None = None
        self._onset: float | None = None

    # --- terminal and reader thread ------------------------------------------------------
    def check_ready(self) -> None:
        """A terminal on stdin (or the given fd), else one-line :class:`SessionError`."""
        if self.fd is None:
            try:
                self.fd = sys.stdin.fileno()
            except (OSError, ValueError, AttributeError):
                self.fd = -1
        if self.fd < 0 or not os.isatty(self.fd):
            raise SessionError("the keypad responder needs a terminal on stdin; use "
                               "--responder scripted:FILE or random without one")

    def open(self) -> None:
        if self._thread is not None:
            return
        self.check_ready()
        self._saved = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd)
        self._stop.clear()
        self._thread = threading.Thread(target=self._read_keys, name="keypad", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._saved is not None:
            try:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            finally:
                self._saved = None

    def __enter__(self) -> KeypadResponder:
        self.open()
        return self

    def _read_keys(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], self.poll_s)
                if not ready:
                    continue
                data = os.read(self.fd, 64)
            except OSError:
                return
            now = time.monotonic()
            if not data:
                return
            for char in data.decode("utf-8", errors="replace"):
                self._keys.put((now, char))

    def _drain(self) -> None:
        while True:
            try:
                self._keys.get_nowait()
            except queue.Empty:
                return

    def _next_key(self, deadline: float | None) -> tuple[float, str] | None:
        """The next key and its time, or None at ``deadline`` (monotonic)."""
        while True:
            timeout = None if deadline is None else deadline - time.monotonic()
            if timeout is not None and timeout <= 0:
                return None
            try:
                return self._keys.get(timeout=0.1 if timeout is None else min(timeout, 0.1))
            except queue.Empty:
                continue

    def _say(self, text: str) -> None:
        self.output.write(text + "\r\n")
        self.output.flush()

    # --- the responder interface -------------------------------------------------------------
    def begin_trial(self, trial: PlannedTrial, onset_time: float, clock: Clock) -> None:
        self.open()
        self._drain()  # keys typed between trials do not answer this one
        self._onset = onset_time

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        self.open()
        onset = stimulus.onset_time if self._onset is None else self._onset
        deadline = None if time_limit_s is None else stimulus.offset_time + time_limit_s
        choices = set(stimulus.symbol_choices)
        while True:
            key = self._next_key(deadline)
            if key is None:
                return Response(None, float(deadline - onset))
            when, char = key
            if when < onset:
                continue
            if char in QUIT_KEYS:
                raise PauseRequested()
            symbol = self.keys.get(char)
            if symbol is not None and symbol in choices:
                return Response(symbol, when - onset)

    def end_trial(self) -> None:
        self._onset = None

    def feedback(self, trial: PlannedTrial, response: Response, correct: bool) -> None:
        if response.symbol is None:
            self._say(f"  no answer in time: it was {trial.symbol}")
        elif correct:
            self._say("  correct")
        else:
            self._say(f"  {response.symbol} is wrong: it was {trial.symbol}")

    def prompt(self, text: str, clock: Clock) -> None:
        """Show an experimenter prompt and wait for Space or Enter (q pauses)."""
        self.open()
        self._drain()
        self._say(f"{text} -- press Space or Enter to continue, q to pause")
        while True:
            key = self._next_key(None)
            if key is None:  # pragma: no cover - no deadline
                continue
            _, char = key
            if char in QUIT_KEYS:
                raise PauseRequested()
            if char in CONTINUE_KEYS:
                return
