"""The responder interface: who answers a trial (a person at the keypad or a simulation).

The runner plays a stimulus, then asks its :class:`Responder` for a :class:`Response`. The
responder sees only what a participant could sense (:class:`StimulusRecord`: the displayed
setpoints frame by frame and the symbols to choose from), never the true symbol.

Times: ``Response.response_time_s`` is measured from stimulus onset on the runner's clock.
Simulated responders advance a :class:`~crs_study.clock.VirtualClock` by their simulated
response time (``clock.sleep_until(stimulus.onset_time + rt)``); the keypad waits for a key.
Simulated responders draw their randomness from ``np.random.default_rng([seed, trial.index])``
so a resumed session reproduces an uninterrupted one exactly.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from crs_study.clock import Clock
from crs_study.geometry.layout import Layout
from crs_study.protocol.plan import PlannedTrial, TrialPlan
from crs_study.stimuli.strokes import Symbol
from crs_study.stimuli.symbol_set import PAUSE_KEYS as SET_PAUSE_KEYS


@dataclass(frozen=True)
class StimulusRecord:
    """What was displayed in one trial, as a participant could sense it.

    Attributes
    ----------
    layout : the device's layout.
    condition : display condition (``pixel-only``, ``crs``, ...).
    frame_times : (n,) s from onset: when each row of ``setpoints`` was displayed.
    setpoints : (n, n_actuators) mm: the displayed setpoints (``device.displayed_setpoints``).
    symbol_choices : the symbols a response may name.
    onset_time : clock time of the stimulus onset (first frame commanded).
    offset_time : clock time of the stimulus offset (last frame commanded).
    """

    layout: Layout
    condition: str
    frame_times: np.ndarray
    setpoints: np.ndarray
    symbol_choices: tuple[Symbol, ...]
    onset_time: float = 0.0
    offset_time: float = 0.0

    @property
    def duration_s(self) -> float:
        """Stimulus duration: offset minus onset (s)."""
        return self.offset_time - self.onset_time


@dataclass(frozen=True)
class Response:
    """A participant's answer: the symbol (None when timed out) and the time from onset (s)."""

    symbol: Symbol | None
    response_time_s: float

    @property
    def timed_out(self) -> bool:
        return self.symbol is None


#: Keys that pause a session at the keypad (so never response keys): p, P pause in place; q,
#: Q, Escape end the session safely. Defined with the stimulus sets, whose keys (and the
#: protocol's) may not be them.
PAUSE_KEYS = SET_PAUSE_KEYS


class PauseInPlace(Exception):  # noqa: N818  (a request, not a failure)
    """The session pauses in place (the keypad's ``p``): raised from
    :meth:`Responder.poll` during a stimulus or from :meth:`Responder.respond`; the runner
    turns the display neutral, lets :meth:`Responder.pause` wait, and plays the trial again
    (its row then says ``rerun = 1``)."""


class Responder(ABC):
    """Answers trials. Subclasses set :attr:`name` and implement :meth:`respond`.

    Optional hooks: :meth:`begin_trial` is called just before the first frame (the keypad
    starts listening there, so keys typed during the stimulus count), :meth:`end_trial` after
    the response. A responder is a context manager for the whole session (the keypad puts the
    terminal in cbreak mode on enter and restores it on exit).
    """

    name: str = "responder"
    #: True when the responder needs real (wall) time: a person answers.
    needs_real_clock: bool = False
    #: True when the responder is a simulation (prompts to the experimenter auto-continue).
    simulated: bool = True

    @abstractmethod
    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        """The response to ``trial``; ``time_limit_s`` counts from stimulus offset."""

    def check_ready(self) -> None:
        """Refuse now (one line) what opening the responder would refuse, before a session
        writes anything; the default has nothing to check."""
        return None

    def start_session(self, participant: str, session: int, plan: TrialPlan,
                      first: int = 0) -> None:
        """Called once the device and the responder are open, before trial ``first`` (the
        first to play: not 0 when resumed); the keypad's screen shows where the session
        stands."""
        return None

    def begin_trial(self, trial: PlannedTrial, onset_time: float, clock: Clock) -> None:
        """Called just before the stimulus onset (clock time ``onset_time``)."""
        return None

    def end_trial(self) -> None:
        """Called after the response (and feedback) of each trial."""
        return None

    def feedback(self, trial: PlannedTrial, response: Response, correct: bool) -> None:
        """Feedback after a practice trial; the default does nothing."""
        return None

    def poll(self) -> None:
        """Called between the frames of a stimulus: a person's keypad raises
        :class:`KeyboardInterrupt` to end the session or :class:`PauseInPlace` to pause it
        (the display goes neutral first); the default asks nothing."""
        return None

    def pause(self, clock: Clock | None) -> None:
        """Paused in place after :class:`PauseInPlace`: returns when the session goes on."""
        return None

    def end_session(self) -> None:
        """Called once every trial is played (the keypad thanks the participant)."""
        return None

    def prompt(self, text: str, clock: Clock, rest_s: float | None = None) -> None:
        """An experimenter prompt (a break, mount the skeleton); simulations continue at once.
        ``rest_s``: the break's intended rest (the keypad counts it down)."""
        return None

    def __enter__(self) -> Responder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Release what the responder holds (terminal modes, files). Idempotent."""
        return None


def trial_rng(seed: int, trial_index: int) -> np.random.Generator:
    """The generator of one trial: ``default_rng([seed, trial_index])`` (resume-safe)."""
    return np.random.default_rng([int(seed), int(trial_index)])


def respond_at(clock: Clock, stimulus: StimulusRecord, response_time_s: float,
               time_limit_s: float | None, symbol: Symbol | None) -> Response:
    """Advance ``clock`` to ``onset + response_time_s`` and answer, honouring the time limit.

    A simulated response later than ``offset + time_limit_s`` becomes a time-out at that
    deadline (symbol None, response time = the deadline from onset).
    """
    if time_limit_s is not None:
        deadline = stimulus.duration_s + time_limit_s
        if response_time_s > deadline:
            clock.sleep_until(stimulus.onset_time + deadline)
            return Response(None, deadline)
    clock.sleep_until(stimulus.onset_time + response_time_s)
    return Response(symbol, response_time_s)
