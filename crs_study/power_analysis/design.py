"""What a simulated study of a protocol looks like, and how ``analyze`` would test it.

:class:`PowerDesign` is the protocol's design as the analysis meets it (its conditions in the
analysis plan's order with the reference first, its digits and levels, and the test trials
each participant has in every (condition, digit, level) cell, practice excluded, read from
the protocol's own trial plan) together with the plan's primary test: random effects,
method, quadrature points and alpha. :func:`parse_range` reads the ``--participants`` and
``--repetitions`` ranges.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crs_study.analysis.plan import AnalysisPlan, default_plan_path, load_plan
from crs_study.analysis.report import order_conditions
from crs_study.errors import CrsStudyError
from crs_study.paths import resolve_protocol
from crs_study.protocol import analysis_plan_path, load_protocol
from crs_study.protocol.plan import make_plan


class PowerError(CrsStudyError):
    """A power analysis cannot be run as asked (the message names the option at fault)."""


@dataclass(frozen=True)
class PowerDesign:
    """A protocol's design and its analysis plan's primary test.

    ``conditions`` start with ``reference``; ``repetitions`` is the protocol's (test trials
    per participant in each (condition, digit, level) cell); ``levels`` is ``(None,)`` for a
    protocol without ``[levels]``. ``random_effects``, ``method``, ``n_quadrature`` and
    ``alpha`` are the plan's: the test :func:`crs_study.analysis.primary.primary_test` runs;
    ``exclusions`` the plan's exclusion rules (for a pilot's and a dry-run's trials).
    """

    conditions: tuple[str, ...]
    reference: str
    digits: tuple[int, ...]
    levels: tuple[float | None, ...]
    repetitions: int
    random_effects: tuple[str, ...] = ("participant", "digit")
    method: str = "laplace"
    n_quadrature: int = 25
    alpha: float = 0.05
    protocol: str = ""
    plan: str = ""
    protocol_path: str | None = None
    exclusions: Any = field(default=None, compare=False, repr=False)   # the plan's

    def __post_init__(self) -> None:
        if self.reference != self.conditions[0] or len(self.conditions) < 2:
            raise PowerError(f"the design needs the reference condition first and another "
                             f"one, got {self.conditions!r} (reference {self.reference!r})")

    @property
    def comparisons(self) -> tuple[str, ...]:
        """The conditions tested against the reference, in order."""
        return self.conditions[1:]

    @property
    def digit_effect(self) -> bool:
        """The fitted model has a random intercept of digit (fit_glmm drops a factor with a
        single level, so a one-digit protocol has none)."""
        return "digit" in self.random_effects and len(self.digits) > 1

    def cell_trials(self, repetitions: int) -> np.ndarray:
        """Trials per participant in each (digit, condition) cell, levels pooled (D, C)."""
        return np.full((len(self.digits), len(self.conditions)),
                       float(repetitions * len(self.levels)))

    def fixed_design(self) -> np.ndarray:
        """Treatment coding, one row per condition: ``Intercept`` and an indicator of each
        non-reference condition (:func:`crs_study.analysis.primary.design`)."""
        C = len(self.conditions)
        return np.column_stack([np.ones(C), np.eye(C)[:, 1:]])

    def to_dict(self) -> dict[str, Any]:
        return {"protocol": self.protocol, "plan": self.plan,
                "conditions": list(self.conditions), "reference": self.reference,
                "digits": list(self.digits), "levels": list(self.levels),
                "repetitions": self.repetitions, "random_effects": list(self.random_effects),
                "method": self.method, "n_quadrature": self.n_quadrature, "alpha": self.alpha}


def design_from_protocol(protocol: Any, plan: Any = None) -> PowerDesign:
    """The :class:`PowerDesign` of a protocol (a path, a shipped name or a loaded
    :class:`~crs_study.protocol.Protocol`) under an analysis plan (a path or a loaded
    :class:`~crs_study.analysis.plan.AnalysisPlan`; default: the one the protocol names, else
    the shipped default, as ``analyze`` chooses)."""
    import pandas as pd


    if not hasattr(protocol, "design"):
        protocol = load_protocol(resolve_protocol(protocol))
    if plan is None:
        plan = analysis_plan_path(protocol) or default_plan_path()
    if not isinstance(plan, AnalysisPlan):
        plan = load_plan(plan)
    conditions, reference, _ = order_conditions(
        pd.DataFrame({"condition": list(protocol.conditions)}), plan)
    repetitions = _test_trials_per_cell(protocol)
    primary = plan.primary
    return PowerDesign(
        conditions=tuple(conditions), reference=reference,
        digits=tuple(int(d) for d in protocol.symbols),
        levels=tuple(protocol.level_values), repetitions=repetitions,
        random_effects=tuple(primary.random_effects), method=primary.method,
        n_quadrature=int(primary.n_quadrature), alpha=float(plan.alpha),
        protocol=f"{protocol.study_id} {protocol.version}", plan=plan.name,
        protocol_path=str(Path(protocol.path)), exclusions=plan.exclusions)


def _test_trials_per_cell(protocol: Any) -> int:
    """The test trials of each (condition, digit, level) cell in the protocol's own plans
    (two counterbalance positions), checked to be one number for every cell."""
    from collections import Counter


    counts = set()
    for counterbalance in (0, 1):
        plan = make_plan(protocol, "powerdesign", 1, counterbalance)
        cells = Counter((t.condition, t.symbol, t.level) for t in plan.trials
                        if t.trial_type == "test")
        expected = {(c, d, lv) for c in protocol.conditions for d in protocol.symbols
                    for lv in protocol.level_values}
        if set(cells) != expected:
            raise PowerError(f"{protocol.path}: the trial plan does not show every (condition, "
                             "digit, level) cell; the power analysis needs a complete design")
        counts |= set(cells.values())
    if len(counts) != 1:
        raise PowerError(f"{protocol.path}: the cells of the trial plan have different numbers "
                         f"of test trials ({sorted(counts)}); the power analysis needs a "
                         "balanced design")
    return counts.pop()


_RANGE = re.compile(r"^\s*(\d+)\s*(?::\s*(\d+)\s*(?::\s*(\d+)\s*)?)?$")


def parse_range(text: str | int | list | tuple, option: str, minimum: int) -> tuple[int, ...]:
    """``"4:40:4"`` (start:stop:step, stop included), ``"3:10"`` (step 1), ``"12"`` or
    ``"4,8,16"`` (items of either form) as sorted distinct whole numbers >= ``minimum``; a
    list of integers is taken as it is. Errors name ``option``."""
    if isinstance(text, int | np.integer) and not isinstance(text, bool):
        values = [int(text)]
    elif isinstance(text, list | tuple):
        if not text or not all(isinstance(v, int | np.integer) and not isinstance(v, bool)
                               for v in text):
            raise PowerError(f"{option}: expected whole numbers, got {text!r}")
        values = [int(v) for v in text]
    elif isinstance(text, str):
        values = []
        for item in text.split(","):
            match = _RANGE.match(item)
            if not match:
                raise PowerError(f"{option}: expected N, A:B or A:B:STEP with whole numbers "
                                 f"(e.g. 4:40:4), got {text!r}")
            start, stop, step = (None if g is None else int(g) for g in match.groups())
            stop = start if stop is None else stop
            step = 1 if step is None else step
            if step < 1 or stop < start:
                raise PowerError(f"{option}: expected A:B:STEP with A <= B and STEP >= 1, "
                                 f"got {item.strip()!r}")
            values += list(range(start, stop + 1, step))
    else:
        raise PowerError(f"{option}: expected a range such as 4:40:4, got {text!r}")
    low = min(values)
    if low < minimum:
        what = {"--participants": "at least 2 participants (the participant variance needs "
                                  "two)"}.get(option, f"values of at least {minimum}")
        raise PowerError(f"{option}: expected {what}, got {low}")
    if len(set(values)) > 200:
        raise PowerError(f"{option}: at most 200 values, got {len(set(values))}")
    return tuple(sorted(set(values)))
