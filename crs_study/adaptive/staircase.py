"""Up/down staircases: the rules of PsychoPy's ``StairHandler``, on the difficulty axis.

The state is a pure function of the responses given (:meth:`Staircase.update`), so replaying
a session's recorded responses rebuilds it exactly (:mod:`crs_study.adaptive.replay`).

Rules (PsychoPy 2026.2 ``psychopy/data/staircase.py``, ``StairHandler.calculateNextIntensity``
with ``applyInitialRule=True``; Levitt 1971, J Acoust Soc Am 49:467):

- until the first reversal, 1-up/1-down: a correct answer makes the next trial harder, an
  error easier; the step at the first reversal follows this rule too;
- then n-down/1-up: ``n`` correct answers in a row (n = 2 or 3, the rule's name) step harder,
  one error steps easier; the run counter restarts after every step;
- a reversal is a change of direction; its level is the level of the trial that caused it;
- the step after k reversals is ``steps[min(k, len(steps) - 1)]``;
- steps are whole numbers of levels of the grid (:meth:`~crs_study.adaptive.spec.
  AdaptiveSpec.grid`, evenly spaced on the difficulty axis ``u``): a step of k levels on a
  log grid spaced s log units apart is PsychoPy's ``stepType = "log"`` step of k s (the level
  multiplied by ``10^(k s)``), on a linear grid its ``"lin"`` step; steps stop at the grid's
  ends as PsychoPy's ``minVal`` and ``maxVal`` clip. The state is a grid index: no rounding
  drifts, and every level shown is one ``validate`` checked.

``weighted`` (Kaernbach 1991, Percept Psychophys 49:227) is 1-up/1-down with the easier
step ``target / (1 - target)`` times the harder one, which converges to ``target``.

Stopping differs from PsychoPy (which stops when both its trial and reversal counts are
reached): a track stops after the block's ``trials``, or earlier at ``stop_reversals``
reversals when that is set. The estimate is the mean on the difficulty axis (a geometric
mean on a log scale) of the last ``estimate_reversals`` reversal levels (Wetherill & Levitt
1965, Br J Math Stat Psychol 18:1). Its 95 % interval is ``mean +- t(n-1) sd / sqrt(n/2)``
over those n levels: a peak and the valley after it belong to one excursion of the track,
so n reversals carry about n/2 independent pieces of information (Wetherill & Levitt
average them in pairs); the plain ``sd / sqrt(n)`` covered the true threshold in 87 % of
200 simulated 60-trial sessions, ``sd / sqrt(n/2)`` in 95 %
(tests/test_adaptive_recovery.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from crs_study.adaptive.spec import AdaptiveSpec, round_level


@dataclass(frozen=True)
class TrialUpdate:
    """What one response did to a track: the level shown and the state after it."""

    level: float
    correct: bool
    reversal: bool
    reversals: int
    estimate: float  # the procedure's threshold estimate after this trial (NaN: none yet)
    ci_low: float
    ci_high: float


@lru_cache(maxsize=256)
def t_quantile(df: int) -> float:
    """Student t's 97.5 % quantile with ``df`` degrees of freedom (scipy).

    scipy.stats is imported here, not at the top: protocols import this package, and
    ``validate`` or ``--help`` should not pay its ~0.75 s import."""
    from scipy import stats

    return float(stats.t.ppf(0.975, df))


class Staircase:
    """One staircase track (see the module docstring)."""

    kind = "staircase"

    def __init__(self, spec: AdaptiveSpec) -> None:
        stair = spec.staircase
        if stair is None:
            raise ValueError("a staircase needs adaptive.staircase")
        self.spec = spec
        self.n_down = stair.n_down
        self.steps = stair.steps
        self.easier_ratio = spec.easier_ratio
        self.grid = spec.grid()
        self.axis = spec.grid_axis()
        self.index = self.grid.index(round_level(stair.start))  # the spec checked it
        self.step = self.steps[0]
        self.results: list[bool] = []
        self.levels_shown: list[float] = []
        self.reversal_axis: list[float] = []
        self.direction = "start"
        self.counter = 0
        self.initial_rule = False

    # --- the procedure's interface ---
    @property
    def next_level(self) -> float:
        """The level of the next trial (a grid level, as the trial file stores it)."""
        return self.grid[self.index]

    @property
    def trials(self) -> int:
        return len(self.results)

    @property
    def reversals(self) -> int:
        return len(self.reversal_axis)

    @property
    def finished(self) -> bool:
        stop = self.spec.staircase.stop_reversals
        return self.trials >= self.spec.trials or bool(stop and self.reversals >= stop)

    def update(self, correct: bool) -> TrialUpdate:
        """Record the response to the trial shown at :attr:`next_level`; step."""
        shown_u = self.axis[self.index]
        level = self.next_level
        correct = bool(correct)
        previous = self.results[-1] if self.results else None
        self.results.append(correct)
        self.levels_shown.append(level)
        if correct:
            self.counter = self.counter + 1 if previous is True else 1
        else:
            self.counter = self.counter - 1 if previous is False else -1
        reversal = self._reversal(correct)
        if reversal:
            if not self.reversal_axis:
                self.initial_rule = True
            self.reversal_axis.append(shown_u)
            self.step = self.steps[min(len(self.reversal_axis), len(self.steps) - 1)]
        if not self.reversal_axis or self.initial_rule:
            self.initial_rule = False
            self._move(harder=correct)
        elif self.counter >= self.n_down:
            self._move(harder=True)
        elif self.counter <= -1:
            self._move(harder=False)
        estimate, low, high = self.estimate()
        return TrialUpdate(level, correct, reversal, self.reversals, estimate, low, high)

    def _reversal(self, correct: bool) -> bool:
        if not self.reversal_axis:  # the initial 1-up/1-down rule
            new = "down" if correct else "up"
        elif self.counter >= self.n_down:
            new = "down"
        elif self.counter <= -1:
            new = "up"
        else:
            return False
        reversal = self.direction not in ("start", new)
        self.direction = new
        return reversal

    def _move(self, harder: bool) -> None:
        delta = -self.step if harder else round(self.step * self.easier_ratio)
        self.index = min(max(self.index + delta, 0), len(self.grid) - 1)
        self.counter = 0

    def estimate(self) -> tuple[float, float, float]:
        """``(estimate, ci_low, ci_high)`` as levels: the mean of the last
        ``estimate_reversals`` reversals on the axis, with its t interval over n/2 effective
        reversals (module docstring; NaN when there are fewer than two reversals)."""
        last = self.reversal_axis[-self.spec.staircase.estimate_reversals:]
        if len(last) < 2:
            return math.nan, math.nan, math.nan
        n = len(last)
        mean = sum(last) / n
        sd = math.sqrt(sum((u - mean) ** 2 for u in last) / (n - 1))
        half = t_quantile(n - 1) * sd / math.sqrt(n / 2)
        ends = sorted((self.spec.from_axis(mean - half), self.spec.from_axis(mean + half)))
        return self.spec.from_axis(mean), ends[0], ends[1]

    def state(self) -> dict:
        """What the fingerprint covers: responses, levels, reversals and the next level."""
        return {"kind": self.kind, "results": [int(r) for r in self.results],
                "levels": self.levels_shown, "reversals": [round(u, 9)
                                                           for u in self.reversal_axis],
                "next": self.next_level, "index": self.index, "step": self.step,
                "counter": self.counter,
                "direction": self.direction}
