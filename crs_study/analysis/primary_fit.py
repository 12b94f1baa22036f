"""The primary test's fits: the full model and, per condition, the model without it.

``correct ~ condition + random part`` (lme4 notation), the random part the plan's
(:mod:`crs_study.analysis.structure`: by default the maximal model, a random slope of
condition by participant and by symbol), fitted by maximum likelihood with
:func:`crs_study.analysis.glmm.fit_glmm`, reduced step by step by the plan's rule when the
fit fails (or is singular and the plan says so), and each condition's likelihood-ratio test
against the model without it. No profiles, no files, no report: the unit of work a power
simulation repeats; :mod:`crs_study.analysis.primary` adds the intervals, the bootstrap p
and the summary that ``analyze`` reports.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from crs_study.analysis import glmm
from crs_study.analysis.accuracy import floor_p, symbol_column_of
from crs_study.analysis.bootstrap import StudyRows, bootstrap_lr
from crs_study.analysis.glmm import GlmmFitError
from crs_study.analysis.glmm_terms import structure_label
from crs_study.analysis.structure import (
    REDUCTION_STEPS,
    ModelStep,
    RandomSpec,
    planned_terms,
    reduce_terms,
    reduction_reasons,
)
from crs_study.errors import AnalysisError

#: Random intercept (as a plan names it) -> its grouping column; the symbol's intercept
#: (``SYMBOL_EFFECTS``) groups by the trials' symbol column, whatever it is called.
GROUP_COLUMNS = {"participant": "participant_id"}
SYMBOL_EFFECTS = ("symbol", "digit")



@dataclass(frozen=True)
class LrComparison:
    """The likelihood-ratio test of one condition against the reference (no profiles).

    ``log_odds`` / ``odds_ratio``: the ML estimate, None when it is infinite (``separated``)
    or the coefficient was dropped; ``test`` is None when the reduced model could not be
    fitted (``error`` says why) or the coefficient was dropped.
    """

    condition: str
    reference: str
    column: str
    full: object = field(repr=False)
    reduced: object = field(default=None, repr=False)
    test: object = None
    error: str | None = None

    @property
    def separated(self) -> bool:
        sep = self.full.separation
        return sep is not None and self.column in sep.coefficients

    @property
    def log_odds(self) -> float | None:
        if self.column not in self.full.params.index or self.separated:
            return None
        return float(self.full.params[self.column])

    @property
    def odds_ratio(self) -> float | None:
        return None if self.log_odds is None else float(np.exp(self.log_odds))

    @property
    def p_value(self) -> float | None:
        return None if self.test is None else floor_p(self.test.pvalue)

    def to_dict(self) -> dict:
        test = self.test
        return {"condition": self.condition, "reference": self.reference,
                "log_odds": self.log_odds, "odds_ratio": self.odds_ratio,
                "separated": self.separated, "p_value": self.p_value,
                "statistic": None if test is None else test.statistic,
                "df": None if test is None else test.df,
                "distribution": None if test is None else test.distribution,
                "loglike_full": None if test is None else test.loglike_full,
                "loglike_reduced": None if test is None else test.loglike_reduced,
                "converged": bool(self.full.converged and (
                    self.reduced is None or self.reduced.converged)),
                "error": self.error}


@dataclass(frozen=True)
class PrimaryFits:
    """The full model and one likelihood-ratio test per non-reference condition.

    ``spec`` is the plan's random part, ``planned`` the terms it asked for on these data,
    ``steps`` every model the reduction rule fitted (:class:`~.structure.ModelStep`), the one
    used last.
    """

    full: object = field(repr=False)
    tests: tuple[LrComparison, ...]
    method: str
    warnings: tuple[str, ...] = ()
    spec: RandomSpec = field(default_factory=RandomSpec)
    planned: tuple = ()
    steps: tuple[ModelStep, ...] = ()
    data: pd.DataFrame | None = field(default=None, repr=False)     # the rows fitted
    design: pd.DataFrame | None = field(default=None, repr=False)   # their full design

    def bootstrap(self, test: LrComparison, replicates: int, seed: int,
                  map_tasks=None, stop_after: int = 0):
        """The parametric bootstrap of ``test`` (:mod:`crs_study.analysis.bootstrap`), or
        None with the reason when it does not apply (no LR test, separation, a reduced
        model whose random part differs from the full one's)."""
        full = self.full
        if test.test is None or test.reduced is None:
            return None, "no likelihood-ratio test to calibrate"
        if not full.terms:
            return None, ("no random effect could be estimated (a logistic regression): its "
                          "LR test needs no calibration for repeated measures")
        if test.separated or full.separation is not None or test.reduced.separation:
            return None, "separation: the LR test at the supremum keeps the chi2 reference"
        if tuple(test.reduced.terms) != tuple(full.terms):
            return None, "the model without the condition lost a random term"
        counts = "n_trials" if "n_trials" in self.data.columns else None
        rows = StudyRows.of(self.data, self.design, full.terms, "correct", counts)
        result = bootstrap_lr(rows, test.column, test.test.statistic,
                              np.r_[test.reduced.params.to_numpy(), test.reduced.theta],
                              np.r_[full.params.to_numpy(), full.theta], replicates, seed,
                              map_tasks, (full._model.curvature,
                                          test.reduced._model.curvature), stop_after)
        return result, None

    def to_frame(self) -> pd.DataFrame:
        return pd.DataFrame([t.to_dict() for t in self.tests])

    def structure(self) -> dict:
        """What the plan asked for, what was fitted and why (``results.json``'s
        ``primary.model.structure``)."""
        return {**self.spec.to_dict(), "planned": structure_label(self.planned),
                "fitted": self.full.random_formula,
                "reduced": len(self.steps) > 1,
                "steps": [step.to_dict() for step in self.steps]}


def fit_primary(trials: pd.DataFrame, conditions: list[str], reference: str,
                random_effects: tuple[str, ...] = ("participant",), method: str = "laplace",
                n_quadrature: int = 25, *, structure: str = "maximal",
                singular_fit: str = "keep",
                reduction: tuple[str, ...] = REDUCTION_STEPS) -> PrimaryFits:
    """Fit the full model and, per condition, the model without it: the primary LR tests.

    No profiles, no files, no report: the unit of work of a power simulation (the same fits
    and tests :func:`primary_test` reports). ``trials`` has ``correct`` (0/1 per row, or the
    number correct when an ``n_trials`` column gives the trials of each row: the aggregated
    form, same likelihood), ``condition``, ``participant_id`` and the symbol shown
    (``digit`` or ``symbol``); rows with ``correct`` missing are left out. ``conditions`` must
    hold ``reference`` and another condition.

    The random part is the plan's (:mod:`crs_study.analysis.structure`): ``random_effects``
    the grouping factors, ``structure`` (``maximal``: a random slope of condition by each
    factor it varies within; ``intercepts``; or lme4 text), and for a singular or failing
    fit ``singular_fit`` and ``reduction``, applied step by step and recorded in ``steps``.
    The model without a condition keeps the random part finally used (Barr et al. 2013: the
    slopes stay in the null model of the test). A failure of every model the rule allows
    raises :class:`GlmmFitError`; of a reduced fit, that test's ``error``. A separated
    condition (ML odds ratio infinite) is tested at the supremum of the likelihood
    (:mod:`crs_study.analysis.glmm_separation`).
    """
    if len(conditions) < 2 or reference not in conditions:
        raise AnalysisError(f"the primary test needs the reference {reference!r} and another "
                            f"condition, got {conditions!r}")
    spec = RandomSpec(tuple(random_effects), structure, singular_fit, tuple(reduction))
    symbol = symbol_column_of(trials)
    columns = ["correct", "condition", "participant_id", symbol]
    columns += ["n_trials"] if "n_trials" in trials.columns else []
    data = trials.loc[trials["correct"].notna(), columns].reset_index(drop=True)
    data = data.loc[data["condition"].isin(conditions)].reset_index(drop=True)
    counts = "n_trials" if "n_trials" in data.columns else None
    full_design = design(data, conditions, reference)
    group_columns = {name: symbol if name in SYMBOL_EFFECTS else GROUP_COLUMNS[name]
                     for name in (*GROUP_COLUMNS, *SYMBOL_EFFECTS)}
    planned, notes = planned_terms(spec, data, list(full_design.columns[1:]), group_columns)
    if method == "agq" and not (len(planned) == 1 and planned[0].is_intercept):
        notes.append(f"adaptive quadrature needs a single random intercept; the plan's model "
                     f"{structure_label(planned)} is fitted with the Laplace approximation instead")
        method = "laplace"
    full, terms, steps = _fit_by_rule(spec, data, full_design, planned, method, n_quadrature,
                                      counts)
    tests = []
    for column in full_design.columns[1:]:
        condition = column[len("condition["):-1]
        if column not in full.params.index:
            tests.append(LrComparison(condition, reference, column, full,
                                      error="coefficient dropped (no trials or aliased)"))
            continue
        try:
            without = full_design.drop(columns=column)
            without.attrs["formula"] = ("1" if without.shape[1] == 1 else
                                        f"condition (without {column})")
            reduced = fit_model(data, without, terms, full_design, method, n_quadrature, counts)
        except GlmmFitError as exc:
            tests.append(LrComparison(condition, reference, column, full, error=str(exc)))
            continue
        tests.append(LrComparison(condition, reference, column, full, reduced,
                                  glmm.lrt(full, reduced)))
    return PrimaryFits(full, tuple(tests), method, tuple(notes), spec, tuple(planned),
                       tuple(steps), data, full_design)


def _fit_by_rule(spec: RandomSpec, data, full_design, terms, method, n_quadrature, counts):
    """The plan's model, reduced by its rule while the fit fails, does not converge or (with
    ``singular_fit = "reduce"``) is singular: ``(fit, terms, steps)``. A random intercept at
    variance 0 alone is a regular boundary, never a reason."""
    done: set[str] = set()
    steps = []
    while True:
        label = structure_label(terms)
        try:
            fit, error = fit_model(data, full_design, terms, full_design, method, n_quadrature,
                              counts), None
        except GlmmFitError as exc:
            fit, error = None, str(exc)
        reasons = ([f"the fit failed ({error})"] if fit is None
                   else reduction_reasons(fit, spec.singular_fit == "reduce"))
        following = reduce_terms(spec, terms, fit, done) if reasons else None
        if following is None:
            if fit is None:
                raise GlmmFitError(error)
            steps.append(ModelStep(label, fit.loglike, bool(fit.converged), fit.singular))
            return fit, terms, steps
        terms, action = following
        steps.append(ModelStep(label, None if fit is None else fit.loglike,
                               bool(fit is not None and fit.converged),
                               () if fit is None else fit.singular,
                               f"{'; '.join(reasons)}: {action}", error))


def design(trials: pd.DataFrame, conditions: list[str], reference: str) -> pd.DataFrame:
    """Treatment-coded design: ``Intercept`` and one ``condition[c]`` column per other one."""
    columns = {"Intercept": np.ones(len(trials))}
    for condition in conditions:
        if condition != reference:
            columns[f"condition[{condition}]"] = (trials["condition"] == condition).to_numpy(
                dtype=float)
    frame = pd.DataFrame(columns, index=trials.index)
    frame.attrs["formula"] = "condition"
    return frame


def fit_model(data: pd.DataFrame, design_matrix: pd.DataFrame, terms,
              random_design: pd.DataFrame, method: str, n_quadrature: int,
              trials: str | None = None):
    """``correct ~ design_matrix + terms`` on ``data`` (``trials``: its counts column)."""
    return glmm.fit_glmm(data, "correct", design_matrix, random=terms,
                         random_design=random_design, trials=trials, method=method,
                         n_quadrature=n_quadrature)

