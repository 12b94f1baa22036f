"""The primary test: a mixed-effects logistic regression of correctness on condition.

``correct ~ condition + (1 | participant) [+ (1 | symbol)]`` (lme4 notation), fitted by
maximum likelihood with :func:`crs_study.analysis.glmm.fit_glmm` (Laplace, or adaptive
Gauss-Hermite quadrature for a single random intercept). Conditions use treatment coding
against the plan's reference condition, so each coefficient is the log odds ratio of a
condition against the reference, at the typical participant (and symbol). The symbol's
intercept groups trials by the trial table's symbol column (``digit`` in a digit dataset, so
the model reads ``(1 | digit)`` there, as before stimulus sets; ``symbol`` in any other); a
plan asks for it as ``symbol`` or, as plans written for digits do, ``digit``.

Each comparison reports the odds ratio ``exp(b)`` with its profile-likelihood interval as
``ci95`` (as lme4's ``confint(method = "profile")``: the values of ``b`` where twice the drop
of the likelihood, maximised over every other parameter, reaches ``chi2_1(level)``; it
follows the skewness of the likelihood that a Wald interval ignores), the Wald interval
``exp(b -/+ z se)`` as ``ci95_wald``, the Wald p-value ``2 Phi(-|b/se|)`` and the
likelihood-ratio p-value of dropping that coefficient (chi2 with 1 df); ``p_value`` is the
likelihood-ratio one, which is the more accurate for logistic models (Agresti 2013,
Categorical Data Analysis, 3rd ed., sec. 1.3.3). Each random intercept's standard deviation
gets its profile-likelihood interval too (``model.random_effects``), 0 as its lower end when
the profile at 0 is within the cutoff.
With more than two conditions an omnibus likelihood-ratio test of condition (k - 1 df) is
reported too. When the model cannot be fitted for numerical reasons (:class:`GlmmFitError`),
Fisher's exact test on the pooled 2 x 2 table is reported instead, with a warning saying so;
a wrong request (an unknown method, ``n_quadrature`` out of range) raises
:class:`~crs_study.errors.AnalysisError` instead of hiding behind that fallback.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd
from scipy import stats

from crs_study._display import Display
from crs_study.analysis import glmm
from crs_study.analysis.accuracy import floor_p
from crs_study.analysis.glmm import GlmmFitError
from crs_study.analysis.glmm_result import format_pvalue
from crs_study.analysis.glmm_terms import structure_label
from crs_study.analysis.jsonable import json_text
from crs_study.analysis.primary_fit import (  # the fits, re-exported: primary's API
    LrComparison,
    PrimaryFits,
    design,
    fit_model,
    fit_primary,
)
from crs_study.analysis.structure import REDUCTION_STEPS


@dataclass(frozen=True)
class Comparison:
    """One condition against the reference: ``estimate`` is an odds ratio (condition/reference).

    ``ci95`` is the interval at the plan's level (95 % unless alpha differs), of the kind
    ``ci_method`` names (profile likelihood for the GLMM); ``ci95_wald`` the Wald interval
    when the GLMM gave one; ``p_value`` the method's p; ``p_wald`` and ``p_lr`` both when the
    GLMM gave them (else None). ``separated``: the condition's ML odds ratio is infinite
    (every trial of one condition right, or wrong); then ``estimate``, ``log_odds``,
    ``std_error``, ``p_wald`` and ``ci95_wald`` are None, ``ci95`` holds the one-sided
    unpenalised profile limit (the other end None: infinite), ``p_value`` is the
    likelihood-ratio p at the supremum, and ``penalised`` the penalised fit's odds ratio, Wald
    interval and p, labelled so and never the primary figure. ``test`` names the test
    (``"glmm"`` or ``"fisher"``, as ``method`` describes it in words) and
    ``logistic_regression`` says the GLMM had no random effect to estimate (the model is then
    a logistic regression): fields, so a reader never parses them out of ``method``.
    """

    condition: str
    reference: str
    method: str
    estimate: float | None   # None: the ML estimate does not exist (separation)
    ci95: tuple[float | None, float | None]  # None: the profile gives no finite end
    p_value: float
    p_wald: float | None = None
    p_lr: float | None = None
    log_odds: float | None = None
    std_error: float | None = None
    ci_method: str = ""
    ci95_wald: tuple[float, float] | None = None
    separated: bool = False
    penalised: dict | None = None
    test: Literal["glmm", "fisher"] = "glmm"
    logistic_regression: bool = False
    p_method: str = "chi2"       # which p is p_value: "chi2" (LR), "bootstrap", "wald"
    bootstrap: dict | None = None   # BootstrapLR.to_dict() when the plan's p is the bootstrap

    def to_dict(self) -> dict:
        return {"condition": self.condition, "reference": self.reference,
                "method": self.method, "estimate": self.estimate, "ci95": list(self.ci95),
                "ci_method": self.ci_method,
                "ci95_wald": None if self.ci95_wald is None else list(self.ci95_wald),
                "p_value": self.p_value, "p_wald": self.p_wald, "p_lr": self.p_lr,
                "log_odds": self.log_odds, "std_error": self.std_error,
                "separated": self.separated, "penalised": self.penalised, "primary": True,
                "test": self.test, "logistic_regression": self.logistic_regression,
                "p_method": self.p_method, "bootstrap": self.bootstrap}


@dataclass(frozen=True)
class PrimaryResult:
    """Comparisons against the reference, the omnibus test, the model summary, warnings."""

    comparisons: tuple[Comparison, ...]
    omnibus: dict | None
    model: dict | None
    warnings: tuple[str, ...] = field(default=())
    fits: PrimaryFits | None = field(default=None, repr=False, compare=False)

    def summary(self) -> str:
        """lme4's ``summary(glmer(...))`` of the model used, the random structure the plan
        asked for and every reduction step, and the likelihood-ratio test(s)."""
        if self.fits is None:
            return "\n".join(["No mixed model was fitted.",
                              *[f"{c.condition} vs {c.reference}: {c.method}, odds ratio "
                                f"{c.estimate:.4g}, p = {c.p_value:.3g}"
                                for c in self.comparisons], *self.warnings])
        fits = self.fits
        lines = [fits.full.summary(), "", f"Random structure: the plan asks for "
                 f"{fits.spec.structure!r} ({structure_label(fits.planned)}), rule for a "
                 f"singular fit: {fits.spec.singular_fit}"
                 + (f" ({', then '.join(fits.spec.reduction)})"
                    if fits.spec.singular_fit == "reduce" else "")]
        for k, step in enumerate(fits.steps, 1):
            lines.append(f"  {k}. {step.formula}: "
                         + (step.action if step.action else "used"))
        lines += ["", "Likelihood-ratio test(s) of condition (random part as fitted):"]
        for test in fits.tests:
            if test.test is None:
                lines.append(f"  {test.condition} vs {test.reference}: not available "
                             f"({test.error})")
                continue
            lines.append(f"  {test.condition} vs {test.reference}: chi2 = "
                         f"{test.test.statistic:.4g}, df = {test.test.df}, p = "
                         f"{format_pvalue(test.test.pvalue)}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        parts = [f"{c.condition} vs {c.reference}: OR "
                 + ("n/a" if c.estimate is None else f"{c.estimate:.3g}")
                 + f", p = {format_pvalue(c.p_value)}" for c in self.comparisons]
        model = ("no mixed model" if self.fits is None else
                 f"correct ~ condition + {self.fits.full.random_formula}")
        return f"<PrimaryResult {model}; {'; '.join(parts) or 'no comparison'}; .summary()>"

    def _repr_html_(self) -> str:
        """The comparisons as a small table in a notebook (:mod:`crs_study._display`)."""
        model = ("no mixed model" if self.fits is None else
                 f"correct ~ condition + {self.fits.full.random_formula}")
        return Display("PrimaryResult", (("model", model), *(
            (f"{c.condition} vs {c.reference}", f"{c.method}: " + (
                "n/a" if c.estimate is None else f"{c.estimate:.3g}")
             + f", p = {format_pvalue(c.p_value)}") for c in self.comparisons)),
            self.warnings, ".summary(), .to_frame()").html()

    def to_frame(self) -> pd.DataFrame:
        """One row per comparison (the fields of :class:`Comparison`)."""
        return pd.DataFrame([c.to_dict() for c in self.comparisons])

    def to_dict(self) -> dict:
        """``comparisons`` (the primary ones of ``results.json``), ``omnibus`` and ``model``
        (``results.json``'s ``primary``)."""
        return {"comparisons": [c.to_dict() for c in self.comparisons],
                "omnibus": self.omnibus, "model": self.model}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def primary_test(trials: pd.DataFrame, conditions: list[str], reference: str,
                 random_effects: tuple[str, ...] = ("participant",), method: str = "laplace",
                 n_quadrature: int = 25, alpha: float = 0.05, *, structure: str = "maximal",
                 singular_fit: str = "keep",
                 reduction: tuple[str, ...] = REDUCTION_STEPS, p_value: str = "chi2",
                 bootstrap_below: int = 20, bootstrap_replicates: int = 1000,
                 bootstrap_stop_after: int = 0, seed: int = 20260101,
                 map_tasks=None) -> PrimaryResult:
    """Fit the GLMM on the answered ``trials`` and compare each condition with ``reference``.

    ``conditions`` are those present in the data, ``reference`` among them. The fits and LR
    tests are :func:`fit_primary`'s (the plan's random part and its rule for a singular fit:
    ``structure``, ``singular_fit``, ``reduction``); this adds the profile intervals, the
    omnibus test and the model summary, with the structure planned, fitted and why.

    ``p_value`` is the plan's rule for the primary p: ``chi2`` (the LR statistic against
    chi2), ``bootstrap`` (its parametric bootstrap, ``bootstrap_replicates`` replicates,
    seeded from ``seed``, stopping early once ``bootstrap_stop_after`` replicates reached the
    observed statistic when that is > 0; :mod:`crs_study.analysis.bootstrap`) or ``auto``:
    the bootstrap with fewer than ``bootstrap_below`` participants, where the chi2 reference
    is liberal.
    ``map_tasks(function, tasks)`` runs the bootstrap's units of work (default: here).
    """
    warnings: list[str] = []
    if len(conditions) < 2 or reference not in conditions:
        warnings.append(f"primary test not run: it needs the reference and at least one other "
                        f"condition with trials, found {conditions!r}")
        return PrimaryResult((), None, None, tuple(warnings))
    try:
        fits = fit_primary(trials, conditions, reference, random_effects, method, n_quadrature,
                           structure=structure, singular_fit=singular_fit, reduction=reduction)
    except GlmmFitError as exc:  # numerical only: a wrong method or n_quadrature raises
        warnings.append(f"the mixed model could not be fitted ({exc}); reported Fisher's exact "
                        "test on the pooled 2 x 2 table of each condition against the reference "
                        "instead, which ignores the repeated measures")
        data = trials.loc[trials["correct"].notna() & trials["condition"].isin(conditions)]
        return PrimaryResult(fisher_comparisons(data, conditions, reference, alpha), None,
                             None, tuple(warnings))
    full = fits.full
    warnings += list(fits.warnings)
    warnings += _structure_warnings(fits)
    warnings += [f"GLMM: {w}" for w in full.warnings]
    seen = set(full.warnings)
    for group in full.boundary:
        warnings.append(f"GLMM: with every {group.removesuffix('_id')} variance at 0 the odds "
                        "ratios and Wald intervals are those of the logistic regression without "
                        "that random term (the same model at variance 0); the profile "
                        "intervals let those variances move inward at other odds ratios")
    level = 1.0 - alpha
    odds = full.odds_ratios(level)
    wald = full.pvalues
    label = _method_label(full)
    columns = [t.column for t in fits.tests if t.column in full.params.index]
    profile = _profile_odds(full, columns, level, warnings)
    comparisons = []
    for test in fits.tests:
        condition, column = test.condition, test.column
        if column not in full.params.index:
            warnings.append(f"GLMM dropped the coefficient of {condition!r} (no trials or "
                            "aliased): no comparison for it")
            continue
        if test.test is None:
            warnings.append(f"GLMM likelihood-ratio test of {condition!r} not available: the "
                            f"model without it could not be fitted ({test.error}); p_value is "
                            "the Wald p")
            comparisons.append(_comparison(test, label, odds, profile, wald[column], None))
            continue
        for note in test.test.warnings:   # the fits' own notes are reported once, above
            core = note.split(": ", 1)[1] if note.startswith(("full model: ",
                                                              "reduced model: ")) else note
            if core not in seen:
                seen.add(core)
                warnings.append(f"GLMM likelihood-ratio test of {condition!r}: {note}")
        comparisons.append(_comparison(test, label, odds, profile, wald[column],
                                       test.test.pvalue))
    participants = int(full.n_groups.get("participant_id", 1))
    rule = p_value if p_value != "auto" else (
        "bootstrap" if participants < bootstrap_below else "chi2")
    if rule == "bootstrap":
        comparisons = _bootstrapped(fits, comparisons, bootstrap_replicates, seed, map_tasks,
                                    warnings, bootstrap_stop_after)
    omnibus = None
    if len(comparisons) > 1:
        omnibus = _omnibus(trials, conditions, reference, fits, n_quadrature, warnings)
    model = full.to_dict(level)
    model["random_effects"] = _random_effect_intervals(full, level, warnings)
    model["structure"] = fits.structure()
    model["p_value_rule"] = {"rule": p_value, "bootstrap_below": bootstrap_below,
                             "replicates": bootstrap_replicates,
                             "stop_after": bootstrap_stop_after, "participants": participants,
                             "used": rule}
    return PrimaryResult(tuple(comparisons), omnibus, model, tuple(warnings), fits)


def _bootstrapped(fits: PrimaryFits, comparisons: list[Comparison], replicates: int,
                  seed: int, map_tasks, warnings: list[str],
                  stop_after: int = 0) -> list[Comparison]:
    """Each comparison's p made the parametric bootstrap's (the LR p kept as ``p_lr``)."""
    out = []
    by_condition = {t.condition: t for t in fits.tests}
    for k, comparison in enumerate(comparisons):
        test = by_condition.get(comparison.condition)
        result, reason = (None, "not a GLMM comparison") if test is None or \
            comparison.test != "glmm" else fits.bootstrap(
                test, replicates, int(np.random.SeedSequence([seed, 7, k]).generate_state(1)[0]),
                map_tasks, stop_after)
        if result is None:
            warnings.append(f"GLMM: the plan's p is the parametric bootstrap, but for "
                            f"{comparison.condition!r} the chi2 LR p is reported: {reason}")
            out.append(comparison)
            continue
        if result.failed:
            warnings.append(f"GLMM bootstrap of {comparison.condition!r}: {result.failed} of "
                            f"{result.used + result.failed} replicates drawn could not be "
                            f"fitted and are left out (p from {result.used})")
        out.append(dataclasses.replace(
            comparison, p_value=floor_p(result.pvalue), p_method="bootstrap",
            bootstrap=result.to_dict(),
            method=comparison.method.replace(
                "odds ratio, LR test", f"odds ratio, LR test by "
                                       f"{result.describe()}")))
    return out


def _structure_warnings(fits: PrimaryFits) -> list[str]:
    """A caution the random part calls for: a model of intercepts alone is anti-conservative
    when the condition effect varies. (The reduction steps are the model's story, told in
    ``model.structure`` and the report, not warnings.)"""
    out = []
    if fits.spec.structure == "intercepts":
        out.append("GLMM random structure: the plan asks for random intercepts only; when "
                   "participants (or symbols) differ in the effect of condition, this model's "
                   "p-value is too small (anti-conservative; Barr et al. 2013): a within-"
                   "participant design is tested with structure = \"maximal\"")
    return out


def _omnibus(trials, conditions, reference, fits: PrimaryFits, n_quadrature: int,
             warnings: list[str]) -> dict | None:
    """Likelihood-ratio test of condition as a whole (k - 1 df)."""
    full = fits.full
    data = trials.loc[trials["correct"].notna() & trials["condition"].isin(conditions)]
    data = data.reset_index(drop=True)
    counts = "n_trials" if "n_trials" in data.columns else None
    try:
        full_design = design(data, conditions, reference)
        intercept = full_design[["Intercept"]].copy()
        intercept.attrs["formula"] = "1"
        null = fit_model(data, intercept, list(full.terms), full_design,
                    fits.method, n_quadrature, counts)
    except GlmmFitError as exc:
        warnings.append(f"GLMM omnibus likelihood-ratio test not available: the model "
                        f"without condition could not be fitted ({exc})")
        return None
    test = glmm.lrt(full, null)
    return {"method": "likelihood-ratio test of condition", "statistic": float(test.statistic),
            "df": int(test.df), "p_value": floor_p(test.pvalue)}


def _profile_odds(full, columns: list[str], level: float,
                  warnings: list[str]) -> pd.DataFrame | None:
    """Profile-likelihood intervals of the odds ratios, or None (Wald then) with a warning."""
    try:
        limits = glmm.profile_conf_int(full, level, columns)
    except GlmmFitError as exc:
        warnings.append(f"GLMM: the profile-likelihood intervals could not be computed "
                        f"({exc}); the odds ratios' ci95 are Wald intervals")
        return None
    with np.errstate(over="ignore"):  # a limit beyond ~709 log-odds is no limit: inf, then null
        odds = np.exp(limits)
    for column in columns:
        ends = odds.loc[column]
        if not (np.isfinite(ends).all() and (ends > 0.0).all()):  # exp(-inf) = 0: open too
            warnings.append(f"GLMM: the profile likelihood of {column!r} stays within the "
                            "cutoff to one side (separation or too few trials): that end of its "
                            "odds-ratio ci95 is null")
    return odds


def _random_effect_intervals(full, level: float, warnings: list[str]) -> dict:
    """Per random effect (the group, or ``group:column`` for a term of several): variance,
    sd and the profile-likelihood interval of the sd where the sd is a parameter of the fit
    (a correlated term's SDs are not: no interval, said so in ``ci_method``)."""
    if not len(full.variance_components):
        return {}
    try:
        table = glmm.profile_sd_conf_int(full, level)
    except GlmmFitError as exc:
        warnings.append(f"GLMM: no profile interval for the random-effect standard deviations "
                        f"({exc})")
        table = None
    out = {}
    for group, variance in full.variance_components.items():
        name = group.replace("_id", "", 1) if group.startswith("participant_id") else group
        profiled = table is not None and group in table.index
        entry = {"variance": float(variance), "sd": float(np.sqrt(variance)),
                 "sd_ci95": None,
                 "ci_method": "profile likelihood (lme4 confint 'profile')" if profiled else
                 "none: a correlated term's SD is not a parameter of the fit (its Cholesky "
                 "factor is)"}
        if profiled:
            low, high = (float(v) for v in table.loc[group, ["ci_low", "ci_high"]])
            entry["sd_ci95"] = [low, high if np.isfinite(high) else None]
            if not np.isfinite(high):
                warnings.append(f"GLMM: the {name} standard deviation has no finite upper "
                                "profile limit (the likelihood stays flat: too few levels); "
                                "its sd_ci95 upper end is null")
        out[name] = entry
    return out


def _comparison(test: LrComparison, label: str, odds: pd.DataFrame,
                profile: pd.DataFrame | None, p_wald: float, p_lr: float | None) -> Comparison:
    """One GLMM comparison; ``p_value`` is the likelihood-ratio p, else the Wald p.

    A separated condition (ML odds ratio infinite): no estimate, the one-sided unpenalised
    profile limit as ``ci95``, the penalised figures apart under ``penalised``.
    """
    full, column = test.full, test.column
    wald_ci = (float(odds.loc[column, "ci_low"]), float(odds.loc[column, "ci_high"]))
    if profile is None:
        ci, how = wald_ci, "Wald (exp(b -/+ z se)); the profile failed"
    else:
        ci = tuple(value if np.isfinite(value) and value > 0.0 else None for value in
                   (float(profile.loc[column, "ci_low"]), float(profile.loc[column, "ci_high"])))
        how = ("profile likelihood (lme4 confint 'profile')"
               + (", of the penalised likelihood" if full.penalty else ""))
    if test.separated:
        return Comparison(
            condition=test.condition, reference=test.reference, method=label, estimate=None,
            # no LR test: no p (the penalised Wald p is never the primary figure)
            ci95=ci, p_value=float("nan") if p_lr is None else floor_p(p_lr), p_wald=None,
            p_lr=None if p_lr is None else floor_p(p_lr), log_odds=None, std_error=None,
            ci_method=("one-sided profile-likelihood limit of the unpenalised likelihood "
                       "against its supremum (the ML odds ratio is infinite: separation); "
                       "the other end is infinite"), ci95_wald=None, separated=True,
            penalised={"odds_ratio": float(odds.loc[column, "odds_ratio"]),
                       "ci95_wald": list(wald_ci), "p_wald": floor_p(p_wald),
                       "log_odds": float(full.params[column]),
                       "std_error": float(full.bse[column]), "prior": full.penalty,
                       "note": "posterior mode under the prior: not a maximum-likelihood "
                               "estimate, never the primary figure"},
            logistic_regression=full.method == "glm")
    return Comparison(
        condition=test.condition, reference=test.reference, method=label,
        estimate=float(odds.loc[column, "odds_ratio"]), ci95=ci,
        p_value=floor_p(p_wald if p_lr is None else p_lr), p_wald=floor_p(p_wald),
        p_lr=None if p_lr is None else floor_p(p_lr), log_odds=float(full.params[column]),
        std_error=float(full.bse[column]), ci_method=how, ci95_wald=wald_ci,
        logistic_regression=full.method == "glm", p_method="wald" if p_lr is None else "chi2")


def _method_label(model) -> str:
    how = {"laplace": "Laplace", "agq": f"AGQ {model.n_quadrature} points",
           "glm": "no random effect estimable: logistic regression"}.get(model.method,
                                                                        model.method)
    effects = "" if model.random_formula == "none" else f" + {model.random_formula}"
    penalty = (", separation: ML odds ratio infinite, LR test at the supremum"
               if model.separation is not None else "")
    return f"GLMM correct ~ condition{effects} ({how}{penalty}); odds ratio, LR test"


def fisher_comparisons(data: pd.DataFrame, conditions: list[str], reference: str,
                        alpha: float) -> tuple[Comparison, ...]:
    """Pooled 2 x 2 tables: Fisher's exact p (``scipy.stats.fisher_exact``); the odds ratio
    and its Woolf interval by ``statsmodels`` ``Table2x2``, after 0.5 is added to every cell
    when one is 0 (Haldane-Anscombe). The correction is applied here: statsmodels 0.15's own
    ``shift_zeros`` adds 0.5 to the empty cells only, not to all four as its documentation
    says."""
    from statsmodels.stats.contingency_tables import Table2x2

    out = []
    ref = data.loc[data["condition"] == reference, "correct"]
    for condition in conditions:
        if condition == reference:
            continue
        other = data.loc[data["condition"] == condition, "correct"]
        table = np.array([[other.sum(), len(other) - other.sum()],
                          [ref.sum(), len(ref) - ref.sum()]], dtype=float).round()
        p = stats.fisher_exact(table.astype(int)).pvalue
        two_by_two = Table2x2(table + 0.5 if (table == 0).any() else table,
                              shift_zeros=False)
        low, high = two_by_two.oddsratio_confint(alpha=alpha, method="normal")
        out.append(Comparison(condition, reference, "Fisher's exact test, pooled 2 x 2 table "
                              "(odds ratio with Woolf interval)",
                              float(two_by_two.oddsratio), (float(low), float(high)),
                              floor_p(p), log_odds=float(two_by_two.log_oddsratio),
                              std_error=float(two_by_two.log_oddsratio_se),
                              ci_method="Woolf (Wald on the log odds ratio)", test="fisher"))
    return tuple(out)
