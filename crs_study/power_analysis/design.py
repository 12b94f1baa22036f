"""What a simulated study of a protocol looks like, and how ``analyze`` would test it.

:class:`PowerDesign` is the protocol's design as the analysis meets it (its conditions in the
analysis plan's order with the reference first, the symbols it shows, whatever its stimulus set
(digits, letters, a lab's set file), and its levels, and the test trials each participant has
in every (condition, symbol, level) cell, practice excluded, read from the protocol's own
trial plan) together with the plan's primary test: random effects, method, quadrature points
and alpha (:func:`~crs_study.power_analysis.protocol_design.design_from_protocol` reads both
from a protocol). :func:`parse_range` reads the ``--participants`` and ``--repetitions``
ranges.

The symbol factor is named as the data name it: ``symbol_column`` is the dataset column of the
protocol's set (``digit`` for the digit set, ``symbol`` for any other,
:attr:`crs_study.stimuli.symbol_set.StimulusSet.column`), which is what ``analyze`` groups the
symbol's random intercept by, whatever the plan calls that intercept (``digit`` or ``symbol``,
:data:`crs_study.analysis.primary_fit.SYMBOL_EFFECTS`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crs_study.analysis.plan import SYMBOL_EFFECTS
from crs_study.analysis.structure import REDUCTION_STEPS, RandomSpec
from crs_study.errors import CrsStudyError
from crs_study.stimuli.strokes import Symbol


class PowerError(CrsStudyError):
    """A power analysis cannot be run as asked (the message names the option at fault)."""


@dataclass(frozen=True)
class PowerDesign:
    """A protocol's design and its analysis plan's primary test.

    ``conditions`` start with ``reference``; ``symbols`` the symbols shown, in the protocol's
    order (ints for the digit set, strings for any other); ``repetitions`` is the protocol's
    (test trials per participant in each (condition, symbol, level) cell); ``levels`` is
    ``(None,)`` for a protocol without ``[levels]``. ``random_effects``, ``method``,
    ``n_quadrature`` and ``alpha`` are the plan's: the test
    :func:`crs_study.analysis.primary.primary_test` runs; ``exclusions`` the plan's exclusion
    rules (for a pilot's and a dry-run's trials). ``symbol_column`` is the dataset column of
    the symbol shown (``digit`` or ``symbol``, module docstring), ``noun`` one symbol in words
    (``digit``, ``letter``), ``symbol_keys`` each symbol's position in its stimulus set (the
    key of its random streams: for the digit set, the digit itself). Left out, as in a design
    built by hand, integer symbols are digits (column ``digit``, their own keys) and any
    others symbols (column ``symbol``, keyed by their order).
    """

    conditions: tuple[str, ...]
    reference: str
    symbols: tuple[Symbol, ...]
    levels: tuple[float | None, ...]
    repetitions: int
    random_effects: tuple[str, ...] = ("participant", "digit")
    method: str = "laplace"
    n_quadrature: int = 25
    alpha: float = 0.05
    structure: str = "maximal"
    singular_fit: str = "keep"
    reduction: tuple[str, ...] = REDUCTION_STEPS
    p_value: str = "chi2"
    bootstrap_below: int = 20
    protocol: str = ""
    plan: str = ""
    protocol_path: str | None = None
    exclusions: Any = field(default=None, compare=False, repr=False)   # the plan's
    symbol_column: str = ""
    noun: str = ""
    symbol_keys: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.reference != self.conditions[0] or len(self.conditions) < 2:
            raise PowerError(f"the design needs the reference condition first and another "
                             f"one, got {self.conditions!r} (reference {self.reference!r})")
        if len(set(self.symbols)) != len(self.symbols) or not self.symbols:
            raise PowerError(f"the design needs distinct symbols, got {self.symbols!r}")
        # a design built by hand: integers are digits, their own keys; others symbols
        digits = all(isinstance(s, int | np.integer) and not isinstance(s, bool)
                     for s in self.symbols)
        for name, value in (("symbol_column", "digit" if digits else "symbol"),
                            ("noun", "digit" if digits else "symbol")):
            if not getattr(self, name):
                object.__setattr__(self, name, value)
        if self.symbol_keys is None:
            keys = self.symbols if digits else range(len(self.symbols))
            object.__setattr__(self, "symbol_keys", tuple(int(k) for k in keys))
        elif len(self.symbol_keys) != len(self.symbols):
            raise PowerError(f"the design needs a stream key per symbol, got "
                             f"{self.symbol_keys!r} for {self.symbols!r}")

    @property
    def random_spec(self) -> RandomSpec:
        """The plan's random part (:mod:`crs_study.analysis.structure`)."""
        return RandomSpec(self.random_effects, self.structure, self.singular_fit,
                          self.reduction)

    def model_options(self) -> dict:
        """The keyword arguments of ``fit_primary`` that describe the random part."""
        return {"structure": self.structure, "singular_fit": self.singular_fit,
                "reduction": self.reduction}

    def bootstrapped(self, participants: int) -> bool:
        """``analyze`` refers the LR statistic of a study of ``participants`` to its
        parametric bootstrap (the plan's ``p_value`` rule), not to chi2."""
        return self.p_value == "bootstrap" or (self.p_value == "auto"
                                                and participants < self.bootstrap_below)

    @property
    def comparisons(self) -> tuple[str, ...]:
        """The conditions tested against the reference, in order."""
        return self.conditions[1:]

    @property
    def symbol_effect_name(self) -> str | None:
        """The plan's name of the symbol's random intercept (``digit`` or ``symbol``: the one
        it names besides participant), None when it has none."""
        return next((e for e in self.random_effects if e in SYMBOL_EFFECTS), None)

    @property
    def symbol_effect(self) -> bool:
        """The fitted model has a random intercept of the symbol (fit_glmm drops a factor
        with a single level, so a one-symbol protocol has none)."""
        return self.symbol_effect_name is not None and len(self.symbols) > 1

    @property
    def digits(self) -> tuple[Symbol, ...]:
        """:attr:`symbols` under the name it had when every protocol showed digits."""
        return self.symbols

    @property
    def digit_effect(self) -> bool:
        """:attr:`symbol_effect` under the name it had when every protocol showed digits."""
        return self.symbol_effect

    @property
    def symbol_sd_name(self) -> str:
        """The name of the symbol intercept's SD in reports: ``digit_sd`` for the digit set
        (as before stimulus sets), ``symbol_sd`` for any other."""
        return f"{self.symbol_column}_sd"

    def cell_trials(self, repetitions: int) -> np.ndarray:
        """Trials per participant in each (symbol, condition) cell, levels pooled (D, C)."""
        return np.full((len(self.symbols), len(self.conditions)),
                       float(repetitions * len(self.levels)))

    def fixed_design(self) -> np.ndarray:
        """Treatment coding, one row per condition: ``Intercept`` and an indicator of each
        non-reference condition (:func:`crs_study.analysis.primary.design`)."""
        C = len(self.conditions)
        return np.column_stack([np.ones(C), np.eye(C)[:, 1:]])

    def to_dict(self) -> dict[str, Any]:
        """The design as JSON: ``symbols`` and ``symbol_column`` for any set; a digit design
        keeps its ``digits`` key too (as written before stimulus sets)."""
        out = {"protocol": self.protocol, "plan": self.plan,
               "conditions": list(self.conditions), "reference": self.reference,
               "digits": list(self.symbols), "levels": list(self.levels),
               "repetitions": self.repetitions, "random_effects": list(self.random_effects),
               "structure": self.structure, "singular_fit": self.singular_fit,
               "reduction": list(self.reduction), "p_value": self.p_value,
               "bootstrap_below": self.bootstrap_below, "method": self.method,
               "n_quadrature": self.n_quadrature, "alpha": self.alpha,
               "symbols": list(self.symbols), "symbol_column": self.symbol_column,
               "noun": self.noun}
        if self.symbol_column != "digit":
            del out["digits"]
        return out


_RANGE = re.compile(r"^\s*(\d+)\s*(?::\s*(\d+)\s*(?::\s*(\d+)\s*)?)?$")


#: The most participants (per simulated study) and repetitions power takes: far beyond any
#: study of this design, and a larger value is a typo that would run for days.
MAX_VALUES = {"--participants": 1000, "--repetitions": 100}


def parse_range(text: str | int | list | tuple, option: str, minimum: int) -> tuple[int, ...]:
    """``"4:40:4"`` (start:stop:step, stop included), ``"3:10"`` (step 1), ``"12"`` or
    ``"4,8,16"`` (items of either form) as sorted distinct whole numbers from ``minimum`` to
    :data:`MAX_VALUES` of ``option``; a list of integers is taken as it is. Errors name
    ``option``."""
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
            if len(range(start, stop + 1, step)) > 200:  # counted before it is made
                raise PowerError(f"{option}: at most 200 values, got "
                                 f"{len(range(start, stop + 1, step))} in {item.strip()!r}")
            values += list(range(start, stop + 1, step))
    else:
        raise PowerError(f"{option}: expected a range such as 4:40:4, got {text!r}")
    low = min(values)
    if low < minimum:
        what = {"--participants": "at least 2 participants (the participant variance needs "
                                  "two)"}.get(option, f"values of at least {minimum}")
        raise PowerError(f"{option}: expected {what}, got {low}")
    most = MAX_VALUES.get(option)
    if most is not None and max(values) > most:
        raise PowerError(f"{option}: expected at most {most}, got {max(values)}")
    if len(set(values)) > 200:
        raise PowerError(f"{option}: at most 200 values, got {len(set(values))}")
    return tuple(sorted(set(values)))
