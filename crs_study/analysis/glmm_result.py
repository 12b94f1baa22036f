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

#: Smallest p-value reported as a number; p-values below it are clamped to it (never 0).
P_FLOOR = float(np.finfo(float).tiny)
#: Below this, a p-value is printed as "< 1e-16": double precision cannot resolve 1 - p.
P_TEXT_FLOOR = 1e-16


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

    @property
    def n_params(self) -> int:
        """Estimated parameters: fixed effects plus variance components."""
        return len(self.params) + len(self.variance_components)

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
        """Grouping factors whose variance was estimated at 0 (on the boundary)."""
        return tuple(g for g, v in self.variance_components.items() if v == 0.0)

    def conf_int(self, level: float = 0.95) -> pd.DataFrame:
        """Wald intervals ``estimate -/+ z_{(1+level)/2} * std_error`` (log-odds)."""
        z = stats.norm.ppf(0.5 + level / 2.0)
        return pd.DataFrame({"ci_low": self.params - z * self.bse,
                             "ci_high": self.params + z * self.bse})

    def odds_ratios(self, level: float = 0.95) -> pd.DataFrame:
        """Odds ratios ``exp(estimate)`` with the exponentiated Wald interval."""
        ci = self.conf_int(level)
        return pd.DataFrame({"odds_ratio": np.exp(self.params),
                             "ci_low": np.exp(ci["ci_low"]), "ci_high": np.exp(ci["ci_high"])})

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
            "warnings": list(self.warnings)}

    def summary(self) -> str:
        """A text summary in the layout of lme4's ``summary(glmer(...))``."""
        how = {"laplace": "Laplace approximation",
               "agq": f"adaptive Gauss-Hermite quadrature, {self.n_quadrature} points",
               "glm": "fixed-effects logistic regression (no random effect estimable)"}
        lines = [f"Binomial-logit mixed model, maximum likelihood ({how[self.method]})",
                 f"Formula: {self.response} ~ {self.fixed}"
                 + "".join(f" + (1 | {g})" for g in self.variance_components.index),
                 f"{'AIC':>10s} {'BIC':>10s} {'logLik':>10s} {'deviance':>10s}",
                 f"{self.aic:10.1f} {self.bic:10.1f} {self.loglike:10.2f} {self.deviance:10.1f}",
                 "", "Random effects:"]
        for g, v in self.variance_components.items():
            lines.append(f"  {g:20s} (Intercept)  variance {v:.4g}  std.dev. {math.sqrt(v):.4g}"
                         f"  ({self.n_groups.get(g, 0)} groups)")
        if not len(self.variance_components):
            lines.append("  none")
        lines += [f"Number of obs: {self.nobs}", "", "Fixed effects:",
                  f"{'':24s} {'Estimate':>9s} {'Std.Err':>9s} {'z':>8s} {'Pr(>|z|)':>10s}"
                  f" {'OR':>9s} {'95% CI of OR':>21s}"]
        frame = self.to_frame()
        for name, row in frame.iterrows():
            lines.append(f"{str(name):24s} {row.estimate:9.4f} {row.std_error:9.4f} {row.z:8.3f}"
                         f" {format_pvalue(row.p_value):>10s} {row.odds_ratio:9.4g}"
                         f"   [{row.or_ci_low:.4g}, {row.or_ci_high:.4g}]")
        lines.append(f"converged: {self.converged}, function evaluations: "
                     f"{self.n_function_evaluations}, max |gradient|: {self.max_abs_gradient:.2g}")
        if self.penalty:
            lines.append(f"penalty: {self.penalty}")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


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
