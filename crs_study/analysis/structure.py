"""The primary model's random structure, as the analysis plan states it before the data.

A reviewer of a within-participant design asks first whether the model lets each participant
(and each symbol) have an effect of condition of their own: when people differ in how much a
display helps them, a model with random intercepts alone treats every trial as independent
evidence about the effect and its p-value is far too small (Barr, Levy, Scheepers & Tily 2013,
"Random effects structure for confirmatory hypothesis testing: Keep it maximal", J. Mem. Lang.
68:255). The plan therefore states (:class:`RandomSpec`):

* the **grouping factors** (``participant``, and ``symbol``/``digit`` for the symbol shown);
* the **structure**: ``maximal`` (default) gives each factor a random slope of condition when
  condition varies within it in the data (:func:`planned_terms`), correlated with its
  intercept, lme4's ``(1 + condition | participant) + (1 + condition | symbol)``;
  ``intercepts`` is the model without slopes, ``(1 | participant) + (1 | symbol)``, which is
  anti-conservative when the effect varies between participants; or an lme4 random part
  written out, e.g. ``"(1 + condition | participant) + (1 | symbol)"``;
* the **rule for a failing, non-converging or singular fit**: the ``reduction`` steps applied
  in order, one refit each, until the fit is regular: drop the correlations (every term made
  uncorrelated, lme4's ``||``), then drop the random slope with the smallest estimated
  variance, and the next (Matuschek, Kliegl, Vasishth, Baayen & Bates 2017, "Balancing Type I
  error and power in linear mixed models", J. Mem. Lang. 94:305; Bates, Kliegl, Vasishth &
  Baayen 2015, "Parsimonious mixed models", arXiv:1506.04967). A fit that fails or does not
  converge is always reduced. A singular fit (a variance at 0, a correlation at +-1) is a
  maximum on the boundary of the parameter space, measured as such
  (:mod:`crs_study.analysis.glmm_optimise`): ``singular_fit = "keep"`` (the default) uses it
  as it is, ``"reduce"`` reduces it too. The default is chosen by the Type I error it gives:
  on 1000 simulated null studies of the shipped protocol (participant intercept SD 0.6, slope
  SD 0.6 or 1.0, symbol intercept SD 0.3, no symbol slope) the LR test of the kept maximal
  fit rejected at alpha 0.05 in 5.4-5.9 % at 6 participants, 6.1-6.3 % at 12 and 4.1-4.5 % at
  24; after reducing singular fits, 6.6-6.8 %, 6.3-6.8 % and 4.0-4.1 %; random intercepts
  alone, 22-39 %. A random intercept whose variance is estimated at 0 is a regular boundary
  estimate (the model then equals the one without it) and never a reason to reduce.

The steps taken are reported (:class:`ModelStep`): which model was fitted, why it was
reduced, and what was dropped. Nothing is dropped silently.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import pandas as pd

from crs_study.analysis.glmm_terms import INTERCEPT, RandomTerm, parse_random, structure_label
from crs_study.errors import AnalysisError

STRUCTURES = ("maximal", "intercepts")
SINGULAR_FIT_RULES = ("reduce", "keep")
REDUCTION_STEPS = ("correlations", "slopes")
#: The grouping factors a plan may name (``symbol`` and ``digit`` are the same: the symbol
#: shown, whatever the trials call its column).
GROUPING_FACTORS = ("participant", "symbol", "digit")
#: What the left side of a written-out term may hold: the intercept and condition.
_TERM_PARTS = {"1", "0", "condition"}


@dataclass(frozen=True)
class RandomSpec:
    """The plan's random part: ``effects`` (grouping factors, plan names), ``structure``
    (``maximal``, ``intercepts`` or lme4 text), ``singular_fit`` and ``reduction``."""

    effects: tuple[str, ...] = ("participant",)
    structure: str = "maximal"
    singular_fit: str = "keep"
    reduction: tuple[str, ...] = REDUCTION_STEPS

    def __post_init__(self) -> None:
        if self.singular_fit not in SINGULAR_FIT_RULES:
            raise AnalysisError(f"singular_fit: expected one of {list(SINGULAR_FIT_RULES)}, "
                                f"got {self.singular_fit!r}")
        unknown = [s for s in self.reduction if s not in REDUCTION_STEPS]
        if unknown or len(set(self.reduction)) != len(self.reduction):
            raise AnalysisError(f"reduction: expected distinct steps among "
                                f"{list(REDUCTION_STEPS)}, got {list(self.reduction)!r}")
        if self.structure not in STRUCTURES:
            written_terms(self.structure)       # raises on anything it cannot read
            groups = [g for _, g, _ in parse_random(self.structure)]
            if set(groups) != set(self.effects):
                raise AnalysisError(f"structure {self.structure!r} groups by {groups!r}, the "
                                    f"plan's random effects are {list(self.effects)!r}: "
                                    f"name the same factors")

    @property
    def written(self) -> bool:
        """The structure is an lme4 random part written out."""
        return self.structure not in STRUCTURES

    def to_dict(self) -> dict:
        return {"effects": list(self.effects), "structure": self.structure,
                "singular_fit": self.singular_fit, "reduction": list(self.reduction)}


def written_terms(text: str) -> list[tuple[str, bool, bool]]:
    """An lme4 random part restricted to what the primary model can hold: per term ``(group,
    intercept, slope of condition)`` and whether it is correlated."""
    out = []
    for lhs, group, correlated in parse_random(text):
        if group not in GROUPING_FACTORS:
            raise AnalysisError(f"structure {text!r}: grouping factor {group!r}; expected one "
                                f"of {list(GROUPING_FACTORS)}")
        parts = [p.strip() for p in lhs.replace("-", "+ -").split("+") if p.strip()]
        bad = [p for p in parts if p not in _TERM_PARTS and p != "-1"]
        if bad:
            raise AnalysisError(f"structure {text!r}: {bad[0]!r} in the term of {group!r}; a "
                                f"term holds 1 (the intercept) and condition (its slope)")
        intercept = "0" not in parts and "-1" not in parts
        slope = "condition" in parts
        if not intercept and not slope:
            raise AnalysisError(f"structure {text!r}: the term of {group!r} holds nothing")
        out.append((group, intercept, slope, correlated))
    return out


@dataclass(frozen=True)
class ModelStep:
    """One fit of the reduction sequence: its random part, what came of it and what was done
    next (``action`` empty for the model finally used; ``error`` when it could not be
    fitted)."""

    formula: str
    loglike: float | None
    converged: bool
    singular: tuple[str, ...]
    action: str = ""
    error: str | None = None

    def to_dict(self) -> dict:
        return {"random": self.formula, "loglike": self.loglike, "converged": self.converged,
                "singular": list(self.singular), "action": self.action, "error": self.error}


def varies_within(data: pd.DataFrame, group: str, factor: str = "condition") -> bool:
    """``factor`` varies within ``group``: at least two of its levels have trials in two or
    more levels of ``factor`` (so a slope by ``group`` has something to estimate)."""
    per_level = data.groupby(group, observed=True)[factor].nunique()
    return int((per_level >= 2).sum()) >= 2


def planned_terms(spec: RandomSpec, data: pd.DataFrame, contrasts: Sequence[str],
                  columns: Mapping[str, str]) -> tuple[list[RandomTerm], list[str]]:
    """The terms the plan asks for on these data, and a note for each slope the design does
    not allow. ``contrasts``: the condition columns of the design (treatment coded);
    ``columns``: each plan name of a grouping factor -> its data column."""
    notes = []
    terms = []
    if spec.written:
        for group, intercept, slope, correlated in written_terms(spec.structure):
            cols = ((INTERCEPT,) if intercept else ()) + (tuple(contrasts) if slope else ())
            terms.append(RandomTerm(columns[group], cols, correlated))
        return terms, notes
    for name in spec.effects:
        column = columns[name]
        slope = spec.structure == "maximal" and bool(contrasts)
        if slope and not varies_within(data, column):
            notes.append(f"condition does not vary within {name} in these data: no random "
                         f"slope of condition by {name} (the maximal model has none)")
            slope = False
        terms.append(RandomTerm(column, (INTERCEPT,) + (tuple(contrasts) if slope else ())))
    return terms, notes


def reduction_reasons(fit, singular: bool = True) -> list[str]:
    """Why a fit calls for the reduction rule: it did not converge, or (``singular``: the
    plan reduces singular fits) a correlated term lost rank or a slope's variance is 0 (a
    random intercept at 0 alone is a regular boundary, never a reason)."""
    reasons = []
    if not fit.converged:
        reasons.append("the fit did not converge")
    if singular:
        reasons += [face.text for face in fit.faces if face.involves_slope]
    return reasons


def reduce_terms(spec: RandomSpec, terms: Sequence[RandomTerm], fit,
                 done: set[str]) -> tuple[list[RandomTerm], str] | None:
    """The next model of the rule and what it drops, or None when no step is left.

    ``done`` holds the steps already taken (``correlations`` is taken once, ``slopes``
    repeats). ``fit`` (the last fit, or None when it failed) gives the slopes' variances.
    """
    for step in spec.reduction:
        if step == "correlations" and "correlations" not in done:
            if any(t.correlated and t.size > 1 for t in terms):
                done.add("correlations")
                new = [t.uncorrelated() if t.size > 1 else t for t in terms]
                return new, f"dropped the correlations: {structure_label(new)}"
        if step == "slopes":
            candidates = [(k, c) for k, t in enumerate(terms) for c in t.slopes]
            if not candidates:
                continue
            variances = _slope_variances(fit, terms)
            k, column = min(candidates, key=lambda kc: (variances.get(kc, 0.0), kc))
            term = terms[k]
            new = list(terms)
            new[k] = term.without(column)
            variance = variances.get((k, column))
            told = "" if variance is None else f", variance {variance:.3g}, the smallest"
            return new, (f"dropped the random slope of {column!r} by "
                         f"{term.shown_group()} ({told.lstrip(', ') or 'the first slope'}): "
                         f"{structure_label(new)}")
    return None


def _slope_variances(fit, terms: Sequence[RandomTerm]) -> dict[tuple[int, str], float]:
    """The estimated variance of each slope, by (term index, column), from ``fit``."""
    if fit is None:
        return {}
    out = {}
    variances = fit.variance_components
    for k, term in enumerate(terms):
        for column in term.slopes:
            key = f"{term.group}:{column}"
            if key in variances.index:
                out[(k, column)] = float(variances[key])
    return out
