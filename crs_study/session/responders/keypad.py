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
keys). ``p`` pauses in place: the display goes neutral, the screen says PAUSED, Space goes on
(a trial whose stimulus had begun is played again, its row saying ``rerun = 1``). ``q`` or a
lone Escape ends the session safely for a later resume (as Ctrl-C), at once, even during a
stimulus (the display goes neutral first). Arrow and function keys (escape sequences,
decoded by :class:`~.keys.KeyDecoder`: a numeric keypad with NumLock off sends arrows) and
any other key that answers nothing get a visible hint. At an experimenter prompt, Space or
Enter continues; keys that arrived before the prompt was shown do not; during a break's rest
a single Space does not end it (a second within two seconds does, on purpose). A terminal
that goes away (closed, its SSH link cut) ends the session as a clean interruption.

What the people in the room see is a :class:`~crs_study.session.screen.TerminalScreen`
(status line, instruction, state), on the output stream or split between a participant's and
an experimenter's stream. What the participant reads comes from the stimulus set
(:class:`~crs_study.stimuli.screens.ScreenTexts`: English unless the set translates it); the
experimenter's lines are in English.
"""

from __future__ import annotations

import math
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
from crs_study.session.responders.base import (
    PAUSE_KEYS,
    PauseInPlace,
    Responder,
    Response,
    StimulusRecord,
)
from crs_study.session.responders.keys import Key, KeyDecoder
from crs_study.session.screen import TerminalScreen
from crs_study.stimuli.screens import ScreenTexts
from crs_study.stimuli.sets import default_set
from crs_study.stimuli.strokes import Symbol

#: Keys that end the session safely for a later resume (as Ctrl-C).
QUIT_KEYS = frozenset({"q", "Q", "\x1b"})
#: Keys that pause the session in place (Space goes on).
PAUSE_IN_PLACE_KEYS = PAUSE_KEYS - QUIT_KEYS
CONTINUE_KEYS = frozenset({" ", "\r", "\n"})
#: A second Space within this long (s) ends a break's rest early; one Space alone does not.
EARLY_END_S = 2.0


class PauseRequested(KeyboardInterrupt):
    """The quit key was pressed: handled exactly like Ctrl-C (a safe pause)."""


class TerminalClosed(KeyboardInterrupt):
    """The keypad's terminal went away (closed, its SSH link cut): a clean interruption."""


class KeypadResponder(Responder):
    """Single keypresses from a terminal, timed on :func:`time.monotonic`; what the people in
    the room see goes to ``screen`` (default: a :class:`TerminalScreen` on ``output``,
    stderr by default), what the participant reads from ``texts`` (the stimulus set's)."""

    name = "keypad"
    needs_real_clock = True
    simulated = False

    def __init__(self, fd: int | None = None, output: TextIO | None = None,
                 poll_s: float = 0.02, keys: dict[str, Symbol] | None = None,
                 screen: TerminalScreen | None = None, instruction: str | None = None,
                 texts: ScreenTexts | None = None) -> None:
        self.keys = dict(keys) if keys is not None else \
            {key: symbol for symbol, key in default_set().keys.items()}
        clash = sorted(set(self.keys) & PAUSE_KEYS)
        if clash:
            raise ConfigError(f"keypad: response key {clash[0]!r} is also a pause key; "
                              f"choose another (pause keys: p, P, q, Q, Escape)")
        self.fd = fd  # None: stdin, looked up when the keypad opens
        self.output = output if output is not None else sys.stderr
        self.screen = screen if screen is not None else TerminalScreen(self.output)
        self.texts = texts if texts is not None else default_set().screens
        # the participant's instruction: the stimulus set's (the default set's without one)
        self.screen.state = replace(self.screen.state, instruction=instruction or
                                    default_set().instructions)
        self.poll_s = poll_s
        self._keys: queue.Queue[Key] = queue.Queue()
        # p, q, Escape and the terminal's end: acted on wherever the session is
        self._control: queue.Queue[str] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: list | None = None
        self._onset: float | None = None
        self._plan: TrialPlan | None = None
        self._next = 0  # the plan's next trial (0-based): a prompt shows its status line
        self._blocks: tuple[int, ...] = ()
        self._practised = False  # the practice-over screen is shown once

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
            except (termios.error, OSError):
                pass  # the terminal is gone (closed): nothing left to restore
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
                data = b""  # EIO: the terminal was closed under us
            now = time.monotonic()
            if data == b"":
                self._control.put("closed")
                return
            keys = decoder.flush(now) if data is None else \
                decoder.feed(data.decode("utf-8", errors="replace"), now)
            for key in keys:
                if key.text in QUIT_KEYS:
                    self._control.put("quit")
                elif key.text in PAUSE_IN_PLACE_KEYS:
                    self._control.put("pause")
                else:
                    self._keys.put(key)

    def _pause_asked(self) -> bool:
        """True when ``p`` was pressed (taken); raises for q, Escape or a closed terminal."""
        paused = False
        while True:
            try:
                control = self._control.get_nowait()
            except queue.Empty:
                return paused
            if control == "quit":
                raise self._pause()
            if control == "closed":
                raise TerminalClosed("the keypad's terminal was closed")
            paused = True

    def _next_key(self, deadline: float | None, since: float | None = None,
                  pausable: bool = False) -> Key | None:
        """The next key (arrived at or after ``since``), or None at ``deadline`` (monotonic).
        q, Escape and a closed terminal raise; ``p`` raises :class:`PauseInPlace` when
        ``pausable``, else pauses here and goes on."""
        while True:
            if self._pause_asked():
                if pausable:
                    raise PauseInPlace("the keypad's p key")
                self.pause(None)
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

    def _hint(self, key: Key, answers: list[str]) -> None:
        """Say on screen that ``key`` answers nothing, and what does."""
        if key.sequence:
            self.screen.show(note="an arrow or function key was ignored (is NumLock off?); "
                             "answer with a response key")
            return
        shown = "Space" if key.text == " " else "Enter" if key.text in "\r\n" else \
            repr(key.text) if not key.text.isprintable() else key.text
        self.screen.show(note=self.texts.unmapped.format(key=shown, keys=" ".join(answers)))

    # --- the responder interface -------------------------------------------------------------
    def start_session(self, participant: str, session: int, plan: TrialPlan,
                      first: int = 0) -> None:
        """Show the status line: participant, session, and where the plan stands."""
        self._plan = plan
        self._next = first
        self._blocks = tuple(sorted({t.block for t in plan.trials}))
        self._practised = any(t.trial_type == "practice" for t in plan.trials[:first]) or \
            not any(t.trial_type == "practice" for t in plan.trials)
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

    def poll(self) -> None:
        """Between the frames of a stimulus: q or Escape end the session now, ``p`` pauses
        it in place (:class:`PauseInPlace`; the runner turns the display neutral first)."""
        if self._pause_asked():
            raise PauseInPlace("the keypad's p key")

    def pause(self, clock: Clock | None) -> None:
        """Paused in place: the PAUSED screen until Space or Enter (q or Escape end the
        session; keys pressed while paused answer nothing)."""
        self.open()
        before = self.screen.state
        self.screen.show(state=self.texts.paused, note="",
                         experimenter="paused (p) -- Space or Enter goes on, q ends the "
                                      "session for a later resume")
        shown = time.monotonic()
        while True:
            key = self._next_key(None, since=shown)
            if key.text in CONTINUE_KEYS:
                break
        self.screen.show(state=before.state if before.state != self.texts.paused else "",
                         experimenter=before.experimenter, note="")

    def end_session(self) -> None:
        """The thank-you screen."""
        self.screen.show(state=self.texts.thank_you, note="",
                         experimenter="the session is complete")

    def begin_trial(self, trial: PlannedTrial, onset_time: float, clock: Clock) -> None:
        self.open()
        self._next = trial.index
        if self._practice_just_ended():  # no prompt came between: say so, wait for Space
            self._wait("practice is over: the test trials begin (no feedback)",
                       self.texts.practice_over, None)
            onset_time = max(onset_time, time.monotonic())
        if self._pause_asked():  # p during the inter-trial interval: pause before this one
            self.pause(clock)
            onset_time = max(onset_time, time.monotonic())
        self._onset = onset_time  # keys typed before the onset do not answer this trial
        if self._plan is None:  # no session around it (a test): what the trial says
            self.screen.show(trial=trial.index + 1, condition=trial.condition)
        self._show_trial(trial.index)
        self.screen.show(state=self.texts.stimulus, note="", experimenter="")

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        self.open()
        onset = stimulus.onset_time if self._onset is None else self._onset
        deadline = None if time_limit_s is None else stimulus.offset_time + time_limit_s
        choices = set(stimulus.symbol_choices)
        answers = sorted(k for k, s in self.keys.items() if s in choices)
        if deadline is None:  # else the first count-down draws the call to answer with it
            self.screen.show(state=self.texts.answer)
        while True:
            self._count_down(deadline)
            tick = None if deadline is None else min(deadline, time.monotonic() + 1.0)
            key = self._next_key(tick, since=onset, pausable=True)
            if key is None:
                if deadline is not None and time.monotonic() >= deadline:
                    self.screen.show(state=self.texts.no_answer, note="")
                    return Response(None, float(deadline - onset))
                continue
            symbol = self.keys.get(key.text)
            if symbol is not None and symbol in choices:
                self.screen.show(state=self.texts.received.format(key=key.text), note="")
                return Response(symbol, key.time - onset)
            self._hint(key, answers)

    def _count_down(self, deadline: float | None) -> None:
        """The time left to answer, whole seconds, beside the call to answer."""
        if deadline is None:
            return
        left = max(0, math.ceil(deadline - time.monotonic()))
        self.screen.show(state=f"{self.texts.answer} -- "
                               f"{self.texts.time_left.format(seconds=left)}")

    def end_trial(self) -> None:
        self._onset = None
        trial = self.screen.state.trial
        self._next = trial if trial is not None else self._next  # 0-based: the one after

    def feedback(self, trial: PlannedTrial, response: Response, correct: bool) -> None:
        if response.symbol is None:
            note = self.texts.too_late.format(symbol=trial.symbol)
        elif correct:
            note = self.texts.correct
        else:
            note = self.texts.wrong.format(answer=response.symbol, symbol=trial.symbol)
        self.screen.show(note=note)

    def prompt(self, text: str, clock: Clock, rest_s: float | None = None) -> None:
        """Show an experimenter prompt and wait for Space or Enter (``p`` pauses, q or
        Escape end the session); at a break (``rest_s``) the state counts the rest down,
        second by second, and a single Space does not end the rest (a second within
        :data:`EARLY_END_S` does). Keys that arrived before the prompt was shown do not
        count. The first prompt after the practice trials says that practice is over."""
        self.open()
        self._show_trial(self._next)
        waiting = self.texts.practice_over if self._practice_just_ended() else self.texts.wait
        self._wait(text, waiting, rest_s)

    def _wait(self, text: str, waiting: str, rest_s: float | None) -> None:
        shown = time.monotonic()
        action = "Space or Enter continues, p pauses, q ends"
        self.screen.show(experimenter=f"{text} -- {action}", note="", state=waiting)
        early: float | None = None  # when a Space asked to end the rest early
        while True:
            deadline = None
            resting = False
            if rest_s:
                left = shown + rest_s - time.monotonic()
                if left > 0:
                    resting = True
                    whole = int(left) + (left % 1 > 0)
                    self.screen.show(state=self.texts.rest.format(
                        time=f"{whole // 60}:{whole % 60:02d}"))
                    deadline = time.monotonic() + min(1.0, left - (whole - 1))
                else:
                    self.screen.show(state=self.texts.rest_over)
            key = self._next_key(deadline, since=shown)
            if key is None:
                continue
            if key.text not in CONTINUE_KEYS:
                self.screen.show(note="Space or Enter continues (p pauses, q ends)")
                continue
            if resting and (early is None or key.time - early > EARLY_END_S):
                early = key.time
                self.screen.show(note=f"the rest is not over: press Space again within "
                                      f"{EARLY_END_S:g} s to end it early")
                continue
            self.screen.show(state="Continuing", experimenter="", note="")
            return

    def _practice_just_ended(self) -> bool:
        """True once, at the first prompt before a test trial after the practice trials."""
        if self._practised or self._plan is None or self._next >= len(self._plan.trials):
            return False
        if self._plan.trials[self._next].trial_type != "test":
            return False
        self._practised = True
        return True
