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
keys); ``q`` or a lone Escape asks for a safe pause (as Ctrl-C); arrow and function keys
(escape sequences, decoded by :class:`~.keys.KeyDecoder`: a numeric keypad with NumLock off
sends arrows) and anything else are ignored, the screen saying so. At an experimenter prompt,
Space or Enter continues; keys that arrived before the prompt was shown do not.

What the people in the room see is a :class:`~crs_study.session.screen.TerminalScreen`
(status line, instruction, state), on the output stream or split between a participant's and
an experimenter's stream.
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
from dataclasses import replace
from typing import TextIO

from crs_study.clock import Clock
from crs_study.errors import ConfigError, SessionError
from crs_study.protocol.plan import PlannedTrial, TrialPlan
from crs_study.session.responders.base import PAUSE_KEYS, Responder, Response, StimulusRecord
from crs_study.session.responders.keys import Key, KeyDecoder
from crs_study.session.screen import TerminalScreen
from crs_study.stimuli.sets import default_set
from crs_study.stimuli.strokes import Symbol

QUIT_KEYS = PAUSE_KEYS
CONTINUE_KEYS = frozenset({" ", "\r", "\n"})


class PauseRequested(KeyboardInterrupt):
    """The quit key was pressed: handled exactly like Ctrl-C (a safe pause)."""


class KeypadResponder(Responder):
    """Single keypresses from a terminal, timed on :func:`time.monotonic`; what the people in
    the room see goes to ``screen`` (default: a :class:`TerminalScreen` on ``output``,
    stderr by default)."""

    name = "keypad"
    needs_real_clock = True
    simulated = False

    def __init__(self, fd: int | None = None, output: TextIO | None = None,
                 poll_s: float = 0.02, keys: dict[str, Symbol] | None = None,
                 screen: TerminalScreen | None = None, instruction: str | None = None
                 ) -> None:
        self.keys = dict(keys) if keys is not None else \
            {key: symbol for symbol, key in default_set().keys.items()}
        clash = sorted(set(self.keys) & QUIT_KEYS)
        if clash:
            raise ConfigError(f"keypad: response key {clash[0]!r} is also the pause key; "
                              f"choose another (pause keys: q, Q, Escape)")
        self.fd = fd  # None: stdin, looked up when the keypad opens
        self.output = output if output is not None else sys.stderr
        self.screen = screen if screen is not None else TerminalScreen(self.output)
        # the participant's instruction: the stimulus set's (the default set's without one)
        self.screen.state = replace(self.screen.state, instruction=instruction or
                                    default_set().instructions)
        self.poll_s = poll_s
        self._keys: queue.Queue[Key] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: list | None = None
        self._onset: float | None = None
        self._plan: TrialPlan | None = None
        self._next = 0  # the plan's next trial (0-based): a prompt shows its status line
        self._blocks: tuple[int, ...] = ()

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

    def __exit__(self, *exc_info: object) -> None:
        if isinstance(exc_info[1], KeyboardInterrupt):  # q, Escape or Ctrl-C: a safe pause
            self._show_paused()
        self.close()

    def _read_keys(self) -> None:
        decoder = KeyDecoder()
        while not self._stop.is_set():
            deadline = decoder.deadline()
            wait = self.poll_s if deadline is None else \
                max(0.0, min(self.poll_s, deadline - time.monotonic()))
            try:
                ready, _, _ = select.select([self.fd], [], [], wait)
                data = os.read(self.fd, 64) if ready else None
            except OSError:
                return
            now = time.monotonic()
            if data == b"":
                return
            keys = decoder.flush(now) if data is None else \
                decoder.feed(data.decode("utf-8", errors="replace"), now)
            for key in keys:
                self._keys.put(key)

    def _next_key(self, deadline: float | None, since: float | None = None) -> Key | None:
        """The next key (arrived at or after ``since``), or None at ``deadline`` (monotonic)."""
        while True:
            timeout = None if deadline is None else deadline - time.monotonic()
            if timeout is not None and timeout <= 0:
                return None
            try:
                key = self._keys.get(timeout=0.1 if timeout is None else min(timeout, 0.1))
            except queue.Empty:
                continue
            if since is None or key.time >= since:
                return key

    def _show_paused(self) -> None:
        self.screen.show(state="Paused: the display goes to its neutral pose",
                         experimenter="the session is paused; run the same command to resume")

    def _pause(self) -> PauseRequested:
        self._show_paused()
        return PauseRequested()

    # --- the responder interface -------------------------------------------------------------
    def start_session(self, participant: str, session: int, plan: TrialPlan,
                      first: int = 0) -> None:
        """Show the status line: participant, session, and where the plan stands."""
        self._plan = plan
        self._next = first
        self._blocks = tuple(sorted({t.block for t in plan.trials}))
        self.screen.clear()
        self.screen.show(participant=participant, session=session, n_trials=len(plan.trials),
                         n_blocks=len(self._blocks) or None)

    def _show_trial(self, index: int) -> None:
        """The status line of trial ``index`` of the plan (the one about to play)."""
        if self._plan is None or not 0 <= index < len(self._plan.trials):
            return
        trial = self._plan.trials[index]
        block = self._blocks.index(trial.block) + 1 if trial.block in self._blocks else None
        practice = " (practice)" if trial.trial_type == "practice" else ""
        self.screen.show(trial=index + 1, block=block, condition=trial.condition + practice)

    def begin_trial(self, trial: PlannedTrial, onset_time: float, clock: Clock) -> None:
        self.open()
        self._onset = onset_time  # keys typed before the onset do not answer this trial
        if self._plan is None:  # no session around it (a test): what the trial says
            self.screen.show(trial=trial.index + 1, condition=trial.condition)
        self._show_trial(trial.index)
        self.screen.show(state="Stimulus playing: feel the shape", note="", experimenter="")

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        self.open()
        onset = stimulus.onset_time if self._onset is None else self._onset
        deadline = None if time_limit_s is None else stimulus.offset_time + time_limit_s
        choices = set(stimulus.symbol_choices)
        limit = "" if time_limit_s is None else f" (within {time_limit_s:g} s)"
        self.screen.show(state=f"ANSWER NOW: press the key of what you felt{limit}")
        while True:
            key = self._next_key(deadline, since=onset)
            if key is None:
                self.screen.show(state="No answer in time")
                return Response(None, float(deadline - onset))
            if key.text in QUIT_KEYS:
                raise self._pause()
            if key.sequence:
                self.screen.show(note="an arrow or function key was ignored (is NumLock "
                                 "off?); answer with a response key")
                continue
            symbol = self.keys.get(key.text)
            if symbol is not None and symbol in choices:
                self.screen.show(state=f"Answer received: {key.text}", note="")
                return Response(symbol, key.time - onset)

    def end_trial(self) -> None:
        self._onset = None
        trial = self.screen.state.trial
        self._next = trial if trial is not None else self._next  # 0-based: the one after

    def feedback(self, trial: PlannedTrial, response: Response, correct: bool) -> None:
        if response.symbol is None:
            note = f"no answer in time: it was {trial.symbol}"
        elif correct:
            note = "correct"
        else:
            note = f"{response.symbol} is wrong: it was {trial.symbol}"
        self.screen.show(note=note)

    def prompt(self, text: str, clock: Clock, rest_s: float | None = None) -> None:
        """Show an experimenter prompt and wait for Space or Enter (q or Escape pauses); at a
        break (``rest_s``) the state counts the rest down, second by second. Keys that arrived
        before the prompt was shown do not count."""
        self.open()
        self._show_trial(self._next)
        shown = time.monotonic()
        action = "Space or Enter continues, q pauses"
        self.screen.show(experimenter=f"{text} -- {action}", note="",
                         state="Break" if rest_s else "Waiting for the experimenter")
        while True:
            deadline = None
            if rest_s:
                left = shown + rest_s - time.monotonic()
                if left > 0:
                    whole = int(left) + (left % 1 > 0)
                    self.screen.show(state=f"Break: rest {whole // 60}:{whole % 60:02d} left "
                                     f"(of {rest_s:g} s)")
                    deadline = time.monotonic() + min(1.0, left - (whole - 1))
                else:
                    self.screen.show(state="Break over: continue when ready")
            key = self._next_key(deadline, since=shown)
            if key is None:
                continue
            if key.text in QUIT_KEYS:
                raise self._pause()
            if key.text in CONTINUE_KEYS:
                self.screen.show(state="Continuing", experimenter="")
                return
