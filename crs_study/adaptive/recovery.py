"""Recovery: simulated observers with a known psychometric function, tracked by a procedure.

Each simulated session draws a true threshold ``t`` (uniform over the middle half of the
grid's range on the difficulty axis) and answers each trial correctly with probability

    psi(u) = 1 - delta - (1 - gamma - delta) exp(-10^(beta (u - t)))

(the Weibull QUEST+ assumes, :mod:`crs_study.adaptive.quest_plus`; gamma = 1 / choices). The
truth the procedure must recover is the level where psi equals the target rate. A session
*covers* the truth when it lies in the procedure's 95 % interval; the bias is the mean of
(estimate - truth) on the difficulty axis, with its t interval over the sessions.

Seeds belong to the session (``numpy.random.default_rng([seed, session])``), so a result
does not depend on how sessions are split between processes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from crs_study.adaptive.replay import make_track
from crs_study.adaptive.spec import AdaptiveSpec


@dataclass(frozen=True)
class Observer:
    """A known psychometric function on the difficulty axis (threshold drawn per session)."""

    slope: float = 4.0
    lapse: float = 0.02

    def p_correct(self, u: float, threshold: float, guess: float) -> float:
        return 1.0 - self.lapse - (1.0 - guess - self.lapse) * math.exp(
            -10.0 ** (self.slope * (u - threshold)))

    def level_at(self, rate: float, threshold: float, guess: float) -> float:
        """``u`` where ``p_correct`` equals ``rate``."""
        q = (1.0 - self.lapse - rate) / (1.0 - guess - self.lapse)
        return threshold + math.log10(-math.log(q)) / self.slope


@dataclass(frozen=True)
class RecoveryResult:
    """Coverage and bias of a procedure's estimates over simulated sessions."""

    procedure: str
    sessions: int
    covered: int
    bias: float  # mean (estimate - truth) on the difficulty axis
    bias_ci95: tuple[float, float]
    missing: int  # sessions without an estimate (a staircase with < 2 reversals)
    median_width: float  # of the 95 % intervals, on the difficulty axis

    @property
    def coverage(self) -> float:
        return self.covered / self.sessions

    def to_dict(self) -> dict:
        return {**asdict(self), "coverage": self.coverage}


def simulate_session(spec: AdaptiveSpec, n_choices: int, observer: Observer, seed: int,
                     session: int) -> tuple[float, float, float, float]:
    """One track against the observer: ``(truth, estimate, ci_low, ci_high)`` on the axis."""
    rng = np.random.default_rng([seed, session])
    low, high = spec.axis_bounds
    threshold = float(rng.uniform(low + (high - low) / 4, high - (high - low) / 4))
    guess = 1.0 / n_choices
    track = make_track(spec, n_choices)
    while not track.finished:
        u = spec.to_axis(track.next_level)
        track.update(bool(rng.random() < observer.p_correct(u, threshold, guess)))
    estimate, ci_low, ci_high = track.estimate()
    axis = [spec.to_axis(v) if np.isfinite(v) else math.nan for v in (estimate, ci_low, ci_high)]
    ends = sorted(axis[1:])  # (a speed's axis runs the other way)
    return observer.level_at(spec.rate, threshold, guess), axis[0], ends[0], ends[1]


def recovery(spec: AdaptiveSpec, n_choices: int = 10, sessions: int = 200,
             observer: Observer = Observer(), seed: int = 0) -> RecoveryResult:
    """Simulate ``sessions`` tracks (module docstring) and summarise coverage and bias."""
    rows = np.array([simulate_session(spec, n_choices, observer, seed, k)
                     for k in range(sessions)])
    truth, estimate = rows[:, 0], rows[:, 1]
    low, high = rows[:, 2], rows[:, 3]
    ok = np.isfinite(estimate)
    covered = int(np.sum(ok & (low <= truth) & (truth <= high)))
    error = estimate[ok] - truth[ok]
    half = float(stats.t.ppf(0.975, len(error) - 1) * error.std(ddof=1) / math.sqrt(len(error)))
    bias = float(error.mean())
    return RecoveryResult(spec.procedure, sessions, covered, bias, (bias - half, bias + half),
                          int(np.sum(~ok)), float(np.median((high - low)[ok])))
