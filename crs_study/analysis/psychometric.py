"""Psychometric functions: accuracy against a varied stimulus level, per condition.

``psi(x) = gamma + (1 - gamma - lambda) F(x; alpha, beta)`` (Wichmann & Hill 2001, Percept.
Psychophys. 63:1293, Eq. 1) with the guess rate ``gamma = 1 / number of symbols`` fixed and
the lapse rate ``lambda`` free in ``[0, lapse_max]``; ``F`` is the logistic ``1 / (1 +
exp(-beta (x - alpha)))`` (``beta`` may be negative: accuracy falling with the level, as for
stroke speed) or the Weibull ``1 - exp(-(x / alpha)^beta)`` (``x > 0``, rising). Parameters
maximise the binomial likelihood of the counts per level (``scipy.optimize.minimize``,
bounded truncated Newton ``"TNC"``, three starts from a grid). A lapse rate at its upper bound
``lapse_max`` is warned about: the data ask for more lapses than the plan allows, which
biases the slope and the threshold. The threshold is the level where ``F = threshold``
(0.5: half-way between guessing and ``1 - lambda``); its interval is a seeded percentile
bootstrap that redraws the count at each level from its observed proportion (resampling the
trials there).

A flat psychometric function has no threshold: when a binomial logistic regression of the
counts on the level (statsmodels GLM) finds no slope (likelihood-ratio p >= alpha, chi2(1)),
the threshold is reported as missing (NaN here, ``None`` in ``to_dict``), no interval is
bootstrapped, and a warning says so, instead of an alpha extrapolated far beyond the levels.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize, special, stats

from crs_study._display import Display, Displayed
from crs_study.analysis.accuracy import wilson_interval
from crs_study.analysis.jsonable import json_text
from crs_study.analysis.plan import known_level_columns
from crs_study.dataset.schema import symbol_column

#: A lapse rate within this fraction of ``lapse_max`` counts as at the bound (TNC stops a
#: hair inside it).
LAPSE_BOUND_TOLERANCE = 1e-3


@dataclass(frozen=True)
class PsychometricFit:
    """One condition's fit: parameters, threshold with interval, and the data it used
    (``data``: ``level, n_trials, n_correct, accuracy, ci_low, ci_high``)."""

    condition: str
    function: str
    alpha: float
    beta: float
    lapse: float
    guess: float
    threshold: float
    threshold_ci95: tuple[float, float] | None
    loglike: float
    data: pd.DataFrame
    n_bootstrap: int = 0
    note: str = ""
    lapse_max: float = float("nan")

    def degenerate(self) -> tuple[str, ...]:
        """Why the fit cannot be read at face value (empty when it can): the lapse rate at
        its upper bound ``lapse_max`` (the data ask for more errors at the easiest levels
        than it allows, so slope and threshold are biased: Wichmann & Hill 2001, "The
        psychometric function I", Percept Psychophys 63:1293), or a slope so steep that the
        function rises from 25 % to 75 % of its range between two adjacent levels tested
        (the data then only bound the slope from below: any steeper fits as well)."""
        flags = []
        if self.lapse_max > 0 and self.lapse >= self.lapse_max * (1.0 - LAPSE_BOUND_TOLERANCE):
            flags.append(f"lapse rate {self.lapse:.3g} at its bound {self.lapse_max:g}")
        levels = np.unique(self.data["level"].to_numpy(float))
        if len(levels) > 1 and self.beta != 0:
            with np.errstate(all="ignore"):
                rise = abs(threshold_level(self.function, self.alpha, self.beta, 0.75)
                           - threshold_level(self.function, self.alpha, self.beta, 0.25))
            if rise < np.min(np.diff(levels)):
                flags.append(f"slope {self.beta:.3g} not identified (the whole rise lies "
                             "between two levels tested)")
        return tuple(flags)

    def predict(self, levels: np.ndarray) -> np.ndarray:
        return psi(np.asarray(levels, float), self.function, self.alpha, self.beta,
                   self.guess, self.lapse)

    def to_dict(self) -> dict:
        return {"condition": self.condition, "function": self.function, "alpha": self.alpha,
                "beta": self.beta, "lapse": self.lapse, "guess": self.guess,
                "threshold": None if np.isnan(self.threshold) else self.threshold,
                "threshold_ci95": None if self.threshold_ci95 is None
                else list(self.threshold_ci95),
                "loglike": self.loglike, "n_bootstrap": self.n_bootstrap, "note": self.note,
                "levels": self.data["level"].tolist(),
                "n_trials": self.data["n_trials"].tolist(),
                "n_correct": self.data["n_correct"].tolist()}


@dataclass(frozen=True, repr=False)
class PsychometricResult(Displayed):
    level_column: str | None
    fits: dict[str, PsychometricFit]
    skipped: bool
    note: str = ""
    warnings: tuple[str, ...] = field(default=())

    def _display(self) -> Display:
        if self.skipped:
            return Display("PsychometricResult (skipped)", (("why", self.note),), self.warnings)
        rows = []
        for condition, fit in self.fits.items():
            ci = "" if fit.threshold_ci95 is None else \
                f" [{fit.threshold_ci95[0]:.3g}, {fit.threshold_ci95[1]:.3g}]"
            text = (f"threshold {fit.threshold:.3g}{ci}" if np.isfinite(fit.threshold)
                    else "no threshold (flat)")
            flags = fit.degenerate()
            rows.append((condition, text + (f"; DEGENERATE: {'; '.join(flags)}" if flags
                                            else "")))
        return Display(f"PsychometricResult ({self.fits[next(iter(self.fits))].function} "
                       f"of {self.level_column})", tuple(rows), self.warnings,
                       ".to_frame(), .fits")

    def to_frame(self) -> pd.DataFrame:
        """One row per condition's fit (the fields of :class:`PsychometricFit`)."""
        return pd.DataFrame([f.to_dict() for f in self.fits.values()])

    def to_dict(self) -> dict:
        """``results.json``'s ``psychometric``: the level column, whether the fits were
        skipped and why, and each condition's fit."""
        return {"level_column": self.level_column, "skipped": self.skipped, "note": self.note,
                "fits": {c: f.to_dict() for c, f in self.fits.items()}}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def sigmoid(x: np.ndarray, function: str, alpha: float, beta: float) -> np.ndarray:
    if function == "logistic":
        return special.expit(beta * (x - alpha))
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.expm1(-np.power(np.clip(x, 0.0, None) / alpha, beta))


def psi(x: np.ndarray, function: str, alpha: float, beta: float, guess: float,
        lapse: float) -> np.ndarray:
    """``gamma + (1 - gamma - lambda) F(x)``."""
    return guess + (1.0 - guess - lapse) * sigmoid(x, function, alpha, beta)


def threshold_level(function: str, alpha: float, beta: float, at: float = 0.5) -> float:
    """Level where ``F = at``: logistic ``alpha + logit(at) / beta``; Weibull
    ``alpha (-ln(1 - at))^(1/beta)``."""
    if function == "logistic":
        return float(alpha + special.logit(at) / beta)
    return float(alpha * (-np.log1p(-at)) ** (1.0 / beta))


def find_level_column(trials: pd.DataFrame, wanted: str = "auto") -> str | None:
    """The level column: ``wanted``, or the first of the known level columns that varies
    (:func:`~crs_study.analysis.plan.known_level_columns`)."""
    candidates = known_level_columns(symbol_column(trials.columns)) if wanted == "auto" \
        else (wanted,)
    for column in candidates:
        if column in trials and pd.api.types.is_numeric_dtype(trials[column]) \
                and trials[column].nunique() > 1:
            return column
    return None


def _sigmoid_and_derivatives(x: np.ndarray, function: str, alpha: float, beta: float):
    """``F`` and its derivatives with respect to ``alpha`` and ``beta``."""
    if function == "logistic":
        f = special.expit(beta * (x - alpha))
        slope = f * (1.0 - f)
        return f, -beta * slope, (x - alpha) * slope
    ratio = np.clip(x, 1e-300, None) / alpha
    u = np.power(ratio, beta)
    decay = np.exp(-u)
    return -np.expm1(-u), decay * (-beta * u / alpha), decay * u * np.log(ratio)


def fit_counts(levels: np.ndarray, n: np.ndarray, k: np.ndarray, function: str, guess: float,
               lapse_max: float, start: tuple[float, float, float] | None = None
               ) -> tuple[float, float, float, float]:
    """Maximum-likelihood ``(alpha, beta, lapse, loglike)`` for counts ``k`` of ``n``.

    Without ``start``, a coarse grid over ``(alpha, beta)`` at three lapse rates (0, half
    and all of ``lapse_max``) gives three starts, the best grid point at each; from each,
    ``scipy.optimize.minimize(method="TNC")`` (truncated Newton within the bounds, analytic
    gradient) climbs, and the highest likelihood wins. One start from the grid left the
    likelihood short by more than 0.001 (up to 0.52) in 5-8 % of simulated fits, whichever
    method climbed (L-BFGS-B 8/150, TNC 5/150); three starts, 0/150 (see the tests).
    """
    levels, n, k = (np.asarray(v, dtype=float) for v in (levels, n, k))
    low, high = float(levels.min()), float(levels.max())
    span = max(high - low, 1e-9)

    def nll(theta: np.ndarray) -> tuple[float, np.ndarray]:
        a, b, lam = theta
        f, df_da, df_db = _sigmoid_and_derivatives(levels, function, a, b)
        p = np.clip(guess + (1.0 - guess - lam) * f, 1e-12, 1 - 1e-12)
        value = -float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))
        dp = -(k / p - (n - k) / (1.0 - p))
        scale = 1.0 - guess - lam
        grad = np.array([np.sum(dp * scale * df_da), np.sum(dp * scale * df_db),
                         np.sum(dp * -f)])
        return value, grad

    if function == "logistic":
        bounds = [(low - span, high + span), (-100.0 / span, 100.0 / span), (0.0, lapse_max)]
        alphas = np.linspace(low, high, 25)
        betas = np.concatenate([-np.geomspace(0.5, 60, 12), np.geomspace(0.5, 60, 12)]) / span
    else:
        bounds = [(max(low, 1e-6) / 10, high * 10), (0.1, 50.0), (0.0, lapse_max)]
        alphas = np.geomspace(max(low, 1e-6), high, 25)
        betas = np.geomspace(0.3, 30, 20)
    if start is not None:
        starts = [start]
    else:
        grid_a, grid_b = np.meshgrid(alphas, betas, indexing="ij")
        f = sigmoid(levels[None, None, :], function, grid_a[..., None], grid_b[..., None])
        starts = []
        for lapse0 in (0.0, 0.5 * lapse_max, lapse_max):
            p = np.clip(guess + (1 - guess - lapse0) * f, 1e-12, 1 - 1e-12)
            ll = np.sum(k * np.log(p) + (n - k) * np.log1p(-p), axis=-1)
            i, j = np.unravel_index(np.argmax(ll), ll.shape)
            starts.append((grid_a[i, j], grid_b[i, j], lapse0))
    best = None
    for x0 in starts:
        x0 = np.clip(np.asarray(x0, float), [b[0] for b in bounds], [b[1] for b in bounds])
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            result = optimize.minimize(nll, x0, jac=True, method="TNC", bounds=bounds)
        if best is None or result.fun < best.fun:
            best = result
    a, b, lam = best.x
    return float(a), float(b), float(lam), -float(best.fun)


def level_effect_pvalue(levels: np.ndarray, n: np.ndarray, k: np.ndarray) -> float:
    """Likelihood-ratio p-value (chi2(1)) of the slope of ``logit p = b0 + b1 level``.

    Binomial GLM by statsmodels; 0 % or 100 % everywhere (no information) gives 1.0.
    """
    import statsmodels.api as sm

    n, k = np.asarray(n, float), np.asarray(k, float)
    if k.sum() in (0.0, n.sum()):
        return 1.0
    endog = np.column_stack([k, n - k])
    exog = sm.add_constant(np.asarray(levels, float))
    with np.errstate(over="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # separation (0 % below a level, 100 % above): llf -> 0
        full = sm.GLM(endog, exog, family=sm.families.Binomial()).fit()
    statistic = max(2.0 * (float(full.llf) - float(full.llnull)), 0.0)  # llnull: intercept only
    return float(stats.chi2.sf(statistic, 1))


def analyse_psychometric(trials: pd.DataFrame, conditions: list[str], guess: float,
                         level_column: str = "auto", function: str = "logistic",
                         lapse_max: float = 0.1, threshold: float = 0.5,
                         n_bootstrap: int = 200, seed: int = 0, alpha: float = 0.05
                         ) -> PsychometricResult:
    """Fit each condition's psychometric function (see module docstring); skip with a note
    when no level varies."""
    column = find_level_column(trials, level_column)
    if column is None:
        wanted = list(known_level_columns(symbol_column(trials.columns))) \
            if level_column == "auto" else [level_column]
        return PsychometricResult(None, {}, True, f"no stimulus level varies in the data "
                                  f"(looked for {wanted}): psychometric functions skipped")
    if function == "weibull" and (trials[column].dropna() <= 0).any():
        return PsychometricResult(column, {}, True, f"the Weibull function needs levels > 0 and "
                                  f"{column!r} has levels <= 0: psychometric functions skipped; "
                                  "use function = \"logistic\"")
    fits, warnings = {}, []
    for index, condition in enumerate(conditions):
        data = trials.loc[(trials["condition"] == condition) & trials["correct"].notna()
                          & trials[column].notna()]
        table = data.groupby(column)["correct"].agg(["size", "sum"]).reset_index()
        table.columns = ["level", "n_trials", "n_correct"]
        table["n_correct"] = table["n_correct"].round().astype(int)
        if len(table) < 3:
            warnings.append(f"psychometric function of {condition!r}: {len(table)} level(s) "
                            f"of {column!r}, a fit needs 3 or more; skipped")
            continue
        table["accuracy"] = table["n_correct"] / table["n_trials"]
        table["ci_low"], table["ci_high"] = wilson_interval(table["n_correct"].to_numpy(),
                                                            table["n_trials"].to_numpy(),
                                                            alpha)
        levels = table["level"].to_numpy(float)
        n, k = table["n_trials"].to_numpy(), table["n_correct"].to_numpy()
        a, b, lam, ll = fit_counts(levels, n, k, function, guess, lapse_max)
        if lapse_max > 0 and lam >= lapse_max * (1.0 - LAPSE_BOUND_TOLERANCE):
            warnings.append(f"psychometric function of {condition!r}: the lapse rate sits at "
                            f"its upper bound {lapse_max:g} (psychometric.lapse_max): the "
                            "data ask for more errors at the easiest levels than the bound "
                            "allows, so the slope and threshold are biased; check the easiest "
                            "levels or raise the bound")
        point = threshold_level(function, a, b, threshold)
        ci, note = None, ""
        p_level = level_effect_pvalue(levels, n, k)
        if p_level >= alpha:
            note = (f"accuracy does not change with {column!r} (likelihood-ratio test of the "
                    f"slope, p = {p_level:.3g}): the function is flat and has no threshold; "
                    "none is reported")
            warnings.append(f"psychometric function of {condition!r}: {note}")
            fits[condition] = PsychometricFit(condition, function, a, b, lam, guess, np.nan,
                                              None, ll, table, 0, note, lapse_max)
            continue
        if n_bootstrap:
            rng = np.random.default_rng([seed, 8, index])
            draws = rng.binomial(n, k / n, size=(n_bootstrap, len(n)))
            boot = np.array([threshold_level(function, *fit_counts(
                levels, n, kk, function, guess, lapse_max, start=(a, b, lam))[:2], threshold)
                for kk in draws])
            outside = np.mean((boot < levels.min()) | (boot > levels.max()))
            ci = tuple(float(v) for v in np.quantile(boot, [alpha / 2, 1 - alpha / 2]))
            if outside > alpha:
                note = (f"{outside:.0%} of bootstrap thresholds fall outside the levels "
                        "tested: the interval is an extrapolation")
                warnings.append(f"psychometric threshold of {condition!r}: {note}")
        if not levels.min() <= point <= levels.max():
            note = (note + "; " if note else "") + "the threshold lies outside the levels tested"
        fits[condition] = PsychometricFit(condition, function, a, b, lam, guess, point, ci, ll,
                                          table, n_bootstrap, note, lapse_max)
    if not fits:
        return PsychometricResult(column, {}, True, f"{column!r} varies but no condition has "
                                  "3 or more levels: psychometric functions skipped",
                                  tuple(warnings))
    return PsychometricResult(column, fits, False, "", tuple(warnings))
