"""QUEST+ (Watson 2017, J Vis 17(3):10) through the ``questplus`` package.

:class:`QuestPlusEngine` is the thin wrapper: a :class:`QuestPlusDesign` (stimulus grid,
parameter grids, guess rate, the function's scale, how the final estimate is taken) becomes a
``questplus.QuestPlus`` with the Weibull function, the outcomes ``Correct`` and
``Incorrect`` and stimulus selection by minimum expected entropy (deterministic: no random
draw, so the state is a pure function of the responses). Watson's worked examples replay
through it (tests/test_adaptive_quest_plus.py).

:class:`QuestPlusTrack` is the procedure of a protocol's ``[adaptive]`` block: the design
on the difficulty axis ``u`` (:mod:`crs_study.adaptive.spec`), with questplus's ``log10``
parametrisation of the Weibull,

    psi(u) = 1 - delta - (1 - gamma - delta) exp(-10^(beta (u - t)))

(questplus ``psychometric_function.weibull``; Watson 2017 Eq. 15 with the stimulus in log
units), gamma = 1 / number of digits. On a log scale it is the Weibull of the level; on a
linear one a Gumbel of it. The threshold reported is the level where psi equals the target
rate,

    u_r = t + log10(-ln((1 - delta - r) / (1 - gamma - delta))) / beta,

averaged over the posterior (every grid cell's u_r weighted by its posterior probability),
with the 2.5 % and 97.5 % posterior quantiles of u_r as its 95 % credible interval.
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.adaptive.staircase import TrialUpdate

OUTCOMES = ("Correct", "Incorrect")


def _grids_equal():
    """xarray's arithmetic with the operands' coordinates required to be equal
    (``arithmetic_join="exact"``) instead of joined: questplus only combines arrays on the
    same grids, so every number is the same, without the copies xarray makes to align them
    (a fifth of a QUEST+ trial's CPU time, measured; tests/test_adaptive_quest_plus.py replays
    Watson's examples through it). The setting is xarray's global one for the duration: a
    track is driven from one thread."""
    import xarray

    return xarray.set_options(arithmetic_join="exact")


@dataclass(frozen=True)
class QuestPlusDesign:
    """Grids and options of one QUEST+ run (see :class:`QuestPlusEngine`)."""

    intensities: tuple[float, ...]
    thresholds: tuple[float, ...]
    slopes: tuple[float, ...]
    lapse_rates: tuple[float, ...]
    guess_rate: float
    scale: Literal["log10", "dB", "linear"] = "log10"
    estimation: Literal["mean", "mode"] = "mean"


@functools.lru_cache(maxsize=16)
def _fresh_engine(design: QuestPlusDesign):
    """A ``questplus.QuestPlus`` of ``design`` before any response, and its first intensity.

    Every track of a design starts from the same state (the likelihood table and the prior
    are functions of the grids alone, the first choice a function of those): a track takes a
    deep copy of this one instead of computing both again (9 and 13 ms, against 0.6 ms for
    the copy; every block of every session, and every replay, starts a track)."""
    # imported here: questplus imports scipy.stats (~0.9 s), and protocols import this
    # package whether or not a QUEST+ track ever runs
    from questplus.qp import QuestPlus

    with _grids_equal():
        fresh = QuestPlus(
            stim_domain={"intensity": np.asarray(design.intensities, float)},
            param_domain={"threshold": np.asarray(design.thresholds, float),
                          "slope": np.asarray(design.slopes, float),
                          "lower_asymptote": np.asarray([design.guess_rate], float),
                          "lapse_rate": np.asarray(design.lapse_rates, float)},
            outcome_domain={"response": list(OUTCOMES)}, func="weibull",
            stim_scale=design.scale, stim_selection_method="min_entropy",
            param_estimation_method=design.estimation)
        first = float(fresh.next_stim["intensity"])
    return fresh, first


class QuestPlusEngine:
    """``questplus.QuestPlus`` for a :class:`QuestPlusDesign`; responses are booleans."""

    def __init__(self, design: QuestPlusDesign) -> None:
        self.design = design
        fresh, first = _fresh_engine(design)
        self.qp = copy.deepcopy(fresh)
        self._next: float | None = first

    @property
    def next_intensity(self) -> float:
        """The intensity of minimum expected entropy (cached until the next update)."""
        if self._next is None:
            with _grids_equal():
                self._next = float(self.qp.next_stim["intensity"])
        return self._next

    def update(self, intensity: float, correct: bool) -> None:
        with _grids_equal():
            self.qp.update(stim={"intensity": intensity},
                           outcome={"response": OUTCOMES[0] if correct else OUTCOMES[1]})
        self._next = None

    @property
    def estimate(self) -> dict[str, float]:
        """questplus's parameter estimate (posterior mean or mode, per the design)."""
        with _grids_equal():
            return {k: float(v) for k, v in self.qp.param_estimate.items()}

    def posterior(self) -> np.ndarray:
        """The posterior over (threshold, slope, guess, lapse), in that axis order."""
        return np.asarray(self.qp.posterior.transpose(
            "threshold", "slope", "lower_asymptote", "lapse_rate").values)


def level_at_rate(thresholds: np.ndarray, slopes: np.ndarray, guess: float,
                  lapses: np.ndarray, rate: float) -> np.ndarray:
    """u_r of every (threshold, slope, lapse) cell (module docstring), shape (t, s, 1, l)."""
    t = np.asarray(thresholds, float)[:, None, None, None]
    b = np.asarray(slopes, float)[None, :, None, None]
    d = np.asarray(lapses, float)[None, None, None, :]
    q = (1.0 - d - rate) / (1.0 - guess - d)
    return t + np.log10(-np.log(q)) / b


def weighted_quantiles(values: np.ndarray, weights: np.ndarray, qs: tuple[float, ...]
                       ) -> list[float]:
    """Quantiles of a discrete distribution (the smallest value whose cumulative weight
    reaches q)."""
    order = np.argsort(values, kind="stable")
    v, w = values[order], weights[order]
    cumulative = np.cumsum(w) / w.sum()
    return [float(v[min(int(np.searchsorted(cumulative, q)), len(v) - 1)]) for q in qs]


class QuestPlusTrack:
    """One QUEST+ track of a protocol's block (see the module docstring)."""

    kind = "quest-plus"

    def __init__(self, spec: AdaptiveSpec, n_choices: int) -> None:
        qspec = spec.quest_plus
        if qspec is None:
            raise ValueError("QUEST+ needs adaptive.quest_plus")
        self.spec = spec
        self.levels = spec.grid()
        self.axis = spec.grid_axis()
        low, high = spec.axis_bounds
        thresholds = tuple(float(v) for v in np.linspace(low, high, qspec.thresholds))
        self.guess = 1.0 / n_choices
        self.engine = QuestPlusEngine(QuestPlusDesign(
            self.axis, thresholds, qspec.slopes, qspec.lapse_rates, self.guess))
        self._u_rate = level_at_rate(np.asarray(thresholds), np.asarray(qspec.slopes),
                                     self.guess, np.asarray(qspec.lapse_rates), spec.rate)
        self.results: list[bool] = []
        self.levels_shown: list[float] = []
        self.reversal_count = 0
        self._direction = 0

    @property
    def next_level(self) -> float:
        u = self.engine.next_intensity
        return self.levels[self.axis.index(u)]

    @property
    def trials(self) -> int:
        return len(self.results)

    @property
    def reversals(self) -> int:
        """Changes of direction of the level (for the record; QUEST+ does not use them)."""
        return self.reversal_count

    @property
    def finished(self) -> bool:
        return self.trials >= self.spec.trials

    def update(self, correct: bool) -> TrialUpdate:
        level = self.next_level
        u = self.axis[self.levels.index(level)]
        self.engine.update(u, bool(correct))
        self.results.append(bool(correct))
        self.levels_shown.append(level)
        step = self.next_level - level
        direction = 0 if step == 0 else (1 if step > 0 else -1)
        reversal = bool(direction and self._direction and direction != self._direction)
        if direction:
            self._direction = direction
        self.reversal_count += int(reversal)
        estimate, low, high = self.estimate()
        return TrialUpdate(level, bool(correct), reversal, self.reversal_count, estimate,
                           low, high)

    def estimate(self) -> tuple[float, float, float]:
        """``(level at the target rate, 95 % credible interval)`` from the posterior."""
        weights = self.engine.posterior().ravel()  # (threshold, slope, guess, lapse)
        values = self._u_rate.ravel()
        mean = float(np.sum(weights * values) / np.sum(weights))
        low, high = weighted_quantiles(values, weights, (0.025, 0.975))
        ends = sorted((self.spec.from_axis(low), self.spec.from_axis(high)))
        return self.spec.from_axis(mean), ends[0], ends[1]

    def state(self) -> dict:
        estimate = self.estimate()[0] if self.results else math.nan
        return {"kind": self.kind, "results": [int(r) for r in self.results],
                "levels": self.levels_shown, "next": self.next_level,
                "estimate": None if math.isnan(estimate) else float(f"{estimate:.9g}")}
