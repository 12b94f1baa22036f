"""Result objects of the GLMM: :class:`GlmmResult` (one fit) and :class:`LrtResult` (a test).

Columns of :meth:`GlmmResult.to_frame` (one row per fixed-effect coefficient, log-odds scale):

============  =============================================================================
estimate      maximum-likelihood coefficient (penalised when ``penalty`` is set)
std_error     Wald standard error, sqrt of the diagonal of ``cov_params``
z             ``estimate / std_error``
p_value       two-sided Wald p, ``2 * (1 - Phi(|z|))``, floored at the smallest positive float
ci_low        lower end of the Wald interval ``estimate -/+ z_{1-a/2} std_error``
ci_high       upper end
odds_ratio    ``exp(estimate)``; ``or_ci_low`` / ``or_ci_high`` the exponentiated interval
============  =============================================================================
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats

from crs_study.analysis.glmm_terms import (
    INTERCEPT,
    covariance,
    sd_and_correlation,
    structure_label,
)

#: Smallest p-value reported as a number; p-values below it are clamped to it (never 0).
P_FLOOR = float(np.finfo(float).tiny)
#: Below this, a p-value is printed as "< 1e-16": double precision cannot resolve 1 - p.
P_TEXT_FLOOR = 1e-16


@dataclass(frozen=True)
class BoundaryFace:
    """A boundary the estimate sits on, measured: in ``term`` (its label), ``kind``
    ``"variance"`` (the variance of ``columns[0]`` at 0), ``"correlation"`` (the correlation of
    the two ``columns`` at +-1) or ``"rank"`` (a covariance matrix of lower rank); ``slope``
    the derivative of the log-likelihood per unit variance added in the most favourable
    missing direction (<= 0: the boundary is the maximum), ``correlation_slope`` the profile's
    ``d loglik / d correlation`` at the correlation's bound (for ``"correlation"``)."""

    term: str
    group: str
    kind: str
    columns: tuple[str, ...]
    slope: float
    text: str
    correlation_slope: float | None = None
    in_slope_term: bool = False

    @property
    def involves_slope(self) -> bool:
        """It concerns a random slope: a slope's variance, or any boundary of a term that has
        slopes (only a random intercept alone at variance 0 does not)."""
        return self.in_slope_term or any(c != INTERCEPT for c in self.columns)

    def to_dict(self) -> dict:
        return {"term": self.term, "group": self.group, "kind": self.kind,
                "columns": list(self.columns), "slope": self.slope,
                "correlation_slope": self.correlation_slope, "text": self.text}


def format_pvalue(p: float) -> str:
    """A p-value as text: ``"< 1e-16"`` below machine precision, else 3 significant digits."""
    if not math.isfinite(p):
        return "n/a"
    if p < P_TEXT_FLOOR:
        return "< 1e-16"
    return f"{p:.3g}"


def wald_pvalues(z: np.ndarray) -> np.ndarray:
    """Two-sided normal p-values ``2 * Phi(-|z|)``, floored at :data:`P_FLOOR` (never 0)."""
    p = 2.0 * stats.norm.sf(np.abs(np.asarray(z, dtype=float)))
    return np.where(np.isnan(p), np.nan, np.maximum(p, P_FLOOR))


@dataclass(frozen=True)
class FitState:
    """What profiles and refits need of a fit: the objective (``problem``), the estimate
    ``theta``, the parameters held on a boundary (``at_zero``) and the negative Hessian of
    the objective there (``curvature``, full size, identity rows for the held parameters;
    None when none was taken), a Newton start for nearby fits."""

    problem: object
    theta: np.ndarray
    at_zero: tuple = ()
    curvature: np.ndarray | None = None


@dataclass(frozen=True)
class GlmmResult:
    """A binomial-logit mixed model fitted by maximum likelihood (lme4's ``glmer`` numbers).

    ``loglike`` is the marginal log-likelihood with the binomial constants of the data as
    given (0/1 rows or successes/trials rows), approximated by Laplace or AGQ; ``aic = -2 ll +
    2 k`` and ``bic = -2 ll + k log(nobs)`` with ``k`` the fixed effects plus the variances and
    ``nobs`` the rows of the data (as lme4). ``cov_params`` is the fixed-effects block of the
    inverse observed information of the whole objective (lme4's ``vcov(use.hessian = TRUE)``).
    """

    params: pd.Series
    bse: pd.Series
    cov_params: pd.DataFrame
    variance_components: pd.Series  # random-intercept variance per grouping factor
    loglike: float
    nobs: int
    n_groups: Mapping[str, int]
    method: str  # "laplace", "agq" or "glm" (no random effect could be estimated)
    n_quadrature: int
    converged: bool
    n_function_evaluations: int
    n_iterations: int
    max_abs_gradient: float
    response: str
    fixed: str
    groups: tuple[str, ...]
    penalty: str | None = None  # the prior used against separation, if any
    warnings: tuple[str, ...] = ()
    _model: object = field(default=None, repr=False, compare=False)
    #: :class:`~crs_study.analysis.glmm_separation.Separation` when an ML estimate is infinite
    separation: object = None
    #: the random terms fitted (:class:`~crs_study.analysis.glmm_terms.RandomTerm`)
    terms: tuple = ()
    #: lme4's theta: each term's Cholesky factor entries, column by column
    theta: tuple[float, ...] = ()
    #: the boundaries the estimate sits on, as measured facts (:class:`BoundaryFace`)
    faces: tuple = ()

    @property
    def n_params(self) -> int:
        """Estimated parameters: fixed effects plus the covariance parameters (theta)."""
        return len(self.params) + (len(self.theta) if self.terms else
                                   len(self.variance_components))

    @property
    def singular(self) -> tuple[str, ...]:
        """Each boundary of the estimate in words (a variance at 0, a correlation at +-1)."""
        return tuple(face.text for face in self.faces)

    @property
    def is_singular(self) -> bool:
        """A variance at 0 or a correlation at +-1 (lme4's ``isSingular``)."""
        return bool(self.faces)

    @property
    def random_formula(self) -> str:
        """The random part in lme4's notation."""
        if self.terms:
            return structure_label(self.terms)
        return " + ".join(f"(1 | {g.removesuffix('_id')})"
                          for g in self.variance_components.index) or "none"

    def covariances(self) -> dict[str, pd.DataFrame]:
        """Each term's covariance matrix ``Sigma_k`` (labelled rows and columns), by term."""
        out = {}
        start = 0
        for term in self.terms:
            theta = np.asarray(self.theta[start:start + term.n_theta])
            start += term.n_theta
            names = [_effect_name(c) for c in term.columns]
            out[term.label()] = pd.DataFrame(covariance(term, theta), index=names,
                                             columns=names)
        return out

    def random_effects(self) -> pd.DataFrame:
        """lme4's "Random effects" table: one row per (group, effect), ``variance``, ``sd``
        and the correlations with the term's earlier effects (``corr`` a list, empty for the
        first effect or an uncorrelated term)."""
        rows = []
        for term, sigma in zip(self.terms, self.covariances().values(), strict=True):
            sd, corr = sd_and_correlation(sigma.to_numpy())
            for j, name in enumerate(sigma.index):
                rows.append({"group": term.shown_group(), "term": term.label(), "effect": name,
                             "variance": float(sigma.iloc[j, j]), "sd": float(sd[j]),
                             "corr": [float(c) for c in corr[j, :j]]
                             if term.correlated else []})
        if not self.terms:
            for g, v in self.variance_components.items():
                rows.append({"group": g.removesuffix("_id"),
                             "term": f"(1 | {g.removesuffix('_id')})",
                             "effect": "(Intercept)", "variance": float(v),
                             "sd": math.sqrt(v), "corr": []})
        return pd.DataFrame(rows, columns=["group", "term", "effect", "variance", "sd", "corr"])

    @property
    def zvalues(self) -> pd.Series:
        return self.params / self.bse

    @property
    def pvalues(self) -> pd.Series:
        return pd.Series(wald_pvalues(self.zvalues.to_numpy()), index=self.params.index)

    @property
    def deviance(self) -> float:
        """``-2 loglike`` (the "deviance" column of lme4's summary)."""
        return -2.0 * self.loglike

    @property
    def aic(self) -> float:
        return self.deviance + 2.0 * self.n_params

    @property
    def bic(self) -> float:
        return self.deviance + self.n_params * math.log(self.nobs)

    @property
    def boundary(self) -> tuple[str, ...]:
        """Grouping factors whose every variance (a random intercept alone, or all of a
        term's intercept and slopes) was estimated at 0: the term drops out of the model."""
        variances: dict[str, list[float]] = {}
        for name, value in self.variance_components.items():
            variances.setdefault(name.split(":", 1)[0], []).append(float(value))
        return tuple(g for g, values in variances.items() if all(v == 0.0 for v in values))

    def conf_int(self, level: float = 0.95) -> pd.DataFrame:
        """Wald intervals ``estimate -/+ z_{(1+level)/2} * std_error`` (log-odds)."""
        z = stats.norm.ppf(0.5 + level / 2.0)
        return pd.DataFrame({"ci_low": self.params - z * self.bse,
                             "ci_high": self.params + z * self.bse})

    def odds_ratios(self, level: float = 0.95) -> pd.DataFrame:
        """Odds ratios ``exp(estimate)`` with the exponentiated Wald interval (an end beyond
        a float's range, from a huge standard error, is infinite)."""
        ci = self.conf_int(level)
        with np.errstate(over="ignore"):
            return pd.DataFrame({"odds_ratio": np.exp(self.params),
                                 "ci_low": np.exp(ci["ci_low"]),
                                 "ci_high": np.exp(ci["ci_high"])})

    def to_frame(self, level: float = 0.95) -> pd.DataFrame:
        """One row per coefficient; the columns are documented in the module docstring."""
        ci, ors = self.conf_int(level), self.odds_ratios(level)
        return pd.DataFrame({
            "estimate": self.params, "std_error": self.bse, "z": self.zvalues,
            "p_value": self.pvalues, "ci_low": ci["ci_low"], "ci_high": ci["ci_high"],
            "odds_ratio": ors["odds_ratio"], "or_ci_low": ors["ci_low"],
            "or_ci_high": ors["ci_high"]})

    def to_dict(self, level: float = 0.95) -> dict:
        """JSON-ready summary (plain floats, lists and strings)."""
        frame = self.to_frame(level)
        return {
            "method": self.method, "n_quadrature": self.n_quadrature,
            "response": self.response, "fixed": self.fixed, "groups": list(self.groups),
            "coefficients": {name: {k: float(v) for k, v in row.items()}
                             for name, row in frame.iterrows()},
            "variance_components": {k: float(v) for k, v in self.variance_components.items()},
            "loglike": self.loglike, "aic": self.aic, "bic": self.bic,
            "deviance": self.deviance, "nobs": self.nobs, "n_groups": dict(self.n_groups),
            "converged": self.converged, "penalty": self.penalty,
            "separation": None if self.separation is None else self.separation.to_dict(),
            "random_formula": self.random_formula, "theta": list(self.theta),
            "random_effects_table": self.random_effects().to_dict(orient="records"),
            "singular": [face.to_dict() for face in self.faces],
            "warnings": list(self.warnings)}

    def summary(self) -> str:
        """A text summary in the layout of lme4's ``summary(glmer(...))``."""
        how = {"laplace": "Laplace Approximation",
               "agq": f"Adaptive Gauss-Hermite Quadrature, nAGQ = {self.n_quadrature}",
               "glm": "fixed-effects logistic regression (no random effect estimable)"}
        lines = [f"Generalized linear mixed model fit by maximum likelihood "
                 f"({how[self.method]}) [glmerMod]", " Family: binomial  ( logit )",
                 f"Formula: {self.response} ~ {self.fixed}"
                 + ("" if self.random_formula == "none" else f" + {self.random_formula}"),
                 "", f"{'AIC':>10s} {'BIC':>10s} {'logLik':>10s} {'deviance':>10s}",
                 f"{self.aic:10.1f} {self.bic:10.1f} {self.loglike:10.2f} {self.deviance:10.1f}",
                 "", "Random effects:"]
        table = self.random_effects()
        if len(table):
            lines.append(f" {'Groups':<13s} {'Name':<22s} {'Variance':>9s} {'Std.Dev.':>9s}"
                         f"  Corr")
            last = None
            for row in table.itertuples():
                group = row.group if row.term != last else ""
                last = row.term
                corr = " ".join(f"{c:6.2f}" for c in row.corr)
                lines.append(f" {group:<13s} {row.effect:<22s} {row.variance:9.4g} "
                             f"{row.sd:9.4g}  {corr}".rstrip())
            groups = ", ".join(f"{g.removesuffix('_id')}, {n}"
                               for g, n in self.n_groups.items())
            lines.append(f"Number of obs: {self.nobs}, groups:  {groups}")
        else:
            lines += ["  none", f"Number of obs: {self.nobs}"]
        lines += ["", "Fixed effects:",
                  f"{'':24s} {'Estimate':>9s} {'Std.Err':>9s} {'z value':>8s} {'Pr(>|z|)':>10s}"]
        for name, row in self.to_frame().iterrows():
            lines.append(f"{str(name):24s} {row.estimate:9.4f} {row.std_error:9.4f} {row.z:8.3f}"
                         f" {format_pvalue(row.p_value):>10s}")
        lines.append("")
        lines.append(f"converged: {self.converged}, function evaluations: "
                     f"{self.n_function_evaluations}, max |gradient|: {self.max_abs_gradient:.2g}")
        lines.append("boundary (singular) fit: " + ("; ".join(self.singular)
                                                     if self.singular else "no"))
        if self.penalty:
            lines.append(f"penalty: {self.penalty}")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _effect_name(column: str) -> str:
    return "(Intercept)" if column == INTERCEPT else column


@dataclass(frozen=True)
class LrtResult:
    """Likelihood-ratio test of a reduced model against the full model nesting it."""

    statistic: float  # 2 (loglike_full - loglike_reduced), >= 0
    df: int
    pvalue: float
    distribution: str  # "chi2(df)" or "0.5 chi2(0) + 0.5 chi2(1)" for one variance on its boundary
    loglike_full: float
    loglike_reduced: float
    warnings: tuple[str, ...] = ()

    def to_frame(self) -> pd.DataFrame:
        return pd.DataFrame([{"statistic": self.statistic, "df": self.df, "p_value": self.pvalue,
                              "distribution": self.distribution,
                              "loglike_full": self.loglike_full,
                              "loglike_reduced": self.loglike_reduced}])
