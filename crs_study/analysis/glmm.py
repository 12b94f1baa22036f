"""Binomial-logit mixed models by maximum likelihood, validated against R's lme4.

``fit_glmm(data, "correct", "condition", "participant")`` is lme4's
``glmer(correct ~ condition + (1 | participant), family = binomial)``: fixed effects from a
patsy formula with treatment contrasts, one random intercept (Laplace or adaptive Gauss-Hermite
quadrature) or several crossed ones (Laplace), responses as 0/1 rows or successes out of
``trials`` per row (lme4's ``cbind(successes, failures)`` form).

Rows sharing the grouping levels and the design row are pooled into one binomial row before
fitting: the likelihood kernel is the same, the binomial constants of the data as given are
added back, so 16,000 trials of a two-condition design cost as much as 80 rows.

Where maximum likelihood fails the fit still returns, with a sentence in ``warnings``:

* **separation** (a condition at 100 % or 0 %, or any direction in which the data are
  separated; found by the linear program of Konis 2007, as R's ``detectseparation``): the
  maximum-likelihood estimate is infinite. The result carries ``separation``
  (:mod:`crs_study.analysis.glmm_separation`): the separated coefficients, the supremum of the
  unpenalised likelihood (which :func:`lrt` uses) and what :func:`profile_conf_int` needs for
  the one-sided unpenalised profile limit. The printed coefficients are penalised, for
  orientation only: independent normal priors, N(0, 10^2) on the intercept and N(0, 2.5^2) on
  every other coefficient (the scales of Gelman, Jakulin, Pittau & Su 2008, Ann. Appl. Stat.
  2:1360, in the normal form that blme's ``bglmer`` offers as a fixed-effect prior); posterior
  modes, standard errors from the penalised information;
* **a variance at zero**: reported as exactly 0 only when the likelihood falls as the variance
  moves inward (:mod:`crs_study.analysis.glmm_optimise`); the fixed effects are those of the
  model without that term; a likelihood-ratio test of that variance is a 50:50 mixture of
  chi2(0) and chi2(1) (Self & Liang 1987, JASA 82:605);
* **a grouping factor with one level** (a single participant): no variance is estimable, the
  term is dropped; with none left the model is a logistic regression by statsmodels' GLM;
* **a level with no rows** (a missing condition) or aliased design columns: dropped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from crs_study.analysis.glmm_core import (
    MAX_QUADRATURE,
    CrossedTerms,
    NoRandom,
    SingleFactor,
)
from crs_study.analysis.glmm_data import (
    check_arguments,
    drop_aliased,
    drop_unused_levels,
    fixed_design,
    group_codes,
    pool,
    random_terms,
    response_arrays,
    row_codes,
    term_designs,
    unpooled,
)
from crs_study.analysis.glmm_fit import fit_glm, optimise, profile_interval, profile_sd_interval
from crs_study.analysis.glmm_result import P_FLOOR, GlmmResult, LrtResult, format_pvalue
from crs_study.analysis.glmm_separation import (
    Separation,
    one_sided_limit,
    separated_rows,
    separation_direction,
)
from crs_study.analysis.glmm_terms import RandomTerm, structure_label
from crs_study.errors import AnalysisError

__all__ = ["fit_glmm", "lrt", "profile_conf_int", "profile_sd_conf_int", "GlmmResult",
           "LrtResult", "format_pvalue", "GlmmFitError", "MAX_QUADRATURE",
           "PRIOR_SD_INTERCEPT", "PRIOR_SD_COEFFICIENT"]

#: Prior standard deviations used against separation (Gelman et al. 2008 scales, normal form).
PRIOR_SD_INTERCEPT = 10.0
PRIOR_SD_COEFFICIENT = 2.5

#: Failures of the arithmetic, not of the request: what a caller may answer with a simpler
#: method. Anything else ``fit_glmm`` raises (an unknown method, a missing column, an
#: out-of-range ``n_quadrature``) is a plain :class:`AnalysisError` about how it was called.
_NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError,
                     OverflowError, ValueError)


class GlmmFitError(AnalysisError):
    """The likelihood could not be evaluated or maximised (a numerical failure)."""


@dataclass(frozen=True)
class _Problem:
    """A prepared fit: the objective and how to read its parameter vector."""

    model: object
    names: list[str]
    terms: tuple  # the fitted random terms (RandomTerm)
    prior_sd: np.ndarray | None  # per fixed coefficient, None when unpenalised
    user_constant: float

    @property
    def n_fixed(self) -> int:
        return len(self.names)

    def objective(self, theta: np.ndarray, grad: bool = True):
        """Penalised log-likelihood kernel (and gradient)."""
        out = self.model.loglik(theta, grad)
        if self.prior_sd is None:
            return out
        beta = theta[: self.n_fixed]
        pen = -0.5 * float(np.sum((beta / self.prior_sd) ** 2))
        if not grad:
            return out + pen
        value, g = out
        g = g.copy()
        g[: self.n_fixed] -= beta / self.prior_sd**2
        return value + pen, g

    @property
    def batched(self) -> bool:
        """Whether :meth:`gradients` evaluates many points at once (crossed terms)."""
        return hasattr(self.model, "gradients")

    def gradients(self, thetas: np.ndarray) -> np.ndarray:
        """The objective's gradient at each of ``thetas`` (K, size): batched where the
        model can (:attr:`batched`), one evaluation after another otherwise."""
        if not self.batched:
            return np.array([self.objective(t)[1] for t in thetas])
        g = self.model.gradients(thetas)
        if self.prior_sd is not None:
            g[:, : self.n_fixed] -= thetas[:, : self.n_fixed] / self.prior_sd**2
        return g


def fit_glmm(data: pd.DataFrame, response: str, fixed: str | pd.DataFrame = "1",
             groups: str | Sequence[str] = (), *, random: str | Sequence[RandomTerm] | None = None,
             random_design: pd.DataFrame | None = None, trials: str | None = None,
             method: str = "laplace", n_quadrature: int = 25,
             aggregate: bool = True) -> GlmmResult:
    """Fit ``response ~ fixed + random``, binomial with logit link, by maximum likelihood.

    Parameters
    ----------
    data : DataFrame with one row per trial (``response`` 0/1) or per binomial count.
    response : column of 0/1 outcomes, or of successes when ``trials`` is given.
    fixed : right-hand side of a patsy formula (e.g. ``"C(condition, Treatment('off'))"``),
        or a design matrix (DataFrame, one column per coefficient, rows as ``data``; its
        ``attrs["formula"]`` names it in the summary).
    groups : grouping factor(s) of random intercepts; several are crossed (lme4's ``(1 |
        g1) + (1 | g2)``). Give either ``groups`` or ``random``.
    random : the random part in lme4's notation, ``"(1 + condition | participant) + (1 |
        digit)"`` (``||``: uncorrelated), each term's left side a patsy formula evaluated on
        ``data``; or :class:`~crs_study.analysis.glmm_terms.RandomTerm` objects whose
        ``columns`` name columns of ``random_design`` (or whose ``design`` is such a formula).
    random_design : the design columns the terms of ``random`` name (rows as ``data``).
    trials : column of the number of trials per row (lme4's ``cbind(y, trials - y)``).
    method : ``"laplace"`` or ``"agq"`` (adaptive Gauss-Hermite; one random intercept only).
    n_quadrature : quadrature points for ``"agq"`` (lme4's ``nAGQ``).
    aggregate : pool identical rows before fitting (same estimates; off only for timing).

    Notes
    -----
    Maximises the Laplace or AGQ marginal log-likelihood jointly over ``(beta, theta)``
    (lme4's second optimisation stage; theta the entries of each term's Cholesky factor, as
    lme4's) by Newton's method (scipy's TNC, then L-BFGS-B, where it stops short),
    unconstrained, from the data's empirical logits and moments
    (:func:`~.glmm_start.moment_start`; lme4 starts at ``beta = 0`` and every factor the
    identity, one intercept from ``beta = 0``, SD 1); a covariance near the boundary (an SD
    near 0, a correlated term near losing rank) is put on it only when the variance-scale
    slope there says the likelihood falls inward, otherwise the fit restarts from interior points
    (:func:`~.glmm_optimise.maximise`). Standard errors: the inverse of the observed
    information of that objective, fixed-effects block (lme4's ``calc.vcov.hess``), the
    Hessian by central differences of the exact gradient.
    """
    notes: list[str] = []
    if not isinstance(data, pd.DataFrame):
        raise AnalysisError(f"fit_glmm expects a pandas DataFrame, got {type(data).__name__}")
    if random is not None and (groups if isinstance(groups, str) else list(groups)):
        raise AnalysisError("give the random effects either as groups= (random intercepts) or "
                            "as random= (any terms), not both")
    terms = (random_terms(data, random, random_design) if random is not None else
             [RandomTerm(g) for g in ([groups] if isinstance(groups, str) else list(groups))])
    group_list = [t.group for t in terms]
    check_arguments(data, response, trials, group_list, method, n_quadrature)
    data = drop_unused_levels(data, fixed, notes)
    X, names = fixed_design(data, fixed)
    X, names = drop_aliased(X, names, notes)
    y, m, user_constant = response_arrays(data, response, trials)
    codes, kept = group_codes(data, terms, notes)
    Z, kept = term_designs(data, kept, random_design, notes)
    single_intercept = len(kept) == 1 and kept[0].is_intercept
    if method == "agq" and kept and not single_intercept:
        raise AnalysisError(f"adaptive quadrature needs a single random intercept (as lme4's "
                            f"nAGQ > 1); got {structure_label(kept)}: use method='laplace'")
    binomial = (pool(X, y, m, codes, Z) if aggregate else
                unpooled(X, y, m, codes, Z))
    # the pooled rows hold the same distinct design rows with the same sums: the same program
    direction = separation_direction(binomial.X, binomial.successes, binomial.trials,
                                     row_codes)
    separated = [] if direction is None else [
        n for n, d in zip(names, direction, strict=True) if d != 0]
    prior_sd = None
    penalty = None
    if separated:
        prior_sd = np.where(np.array(names) == "Intercept", PRIOR_SD_INTERCEPT,
                            PRIOR_SD_COEFFICIENT)
        penalty = (f"normal priors N(0, {PRIOR_SD_INTERCEPT:g}^2) on the intercept and "
                   f"N(0, {PRIOR_SD_COEFFICIENT:g}^2) on the other coefficients")
        notes.append(f"complete or quasi-complete separation: the maximum-likelihood estimate of "
                     f"{separated!r} is infinite (a condition at 100 % or 0 % correct?); the "
                     f"estimates are penalised by {penalty} (posterior mode), the "
                     f"likelihood-ratio test and the one-sided profile limits use the "
                     f"unpenalised likelihood and its supremum")
    fixed_text = fixed if isinstance(fixed, str) else fixed.attrs.get("formula",
                                                                       "<design matrix>")
    groups_done = tuple(t.group for t in terms)
    try:
        if not kept and prior_sd is None:
            problem = _Problem(NoRandom(pool(X, y, m, [], [])), names, (), None,
                               user_constant)
            return fit_glm(X, y, m, names, user_constant, len(data), response, fixed_text,
                           groups_done, notes, problem)
        if not kept:
            model = NoRandom(binomial)
        elif single_intercept:
            model = SingleFactor(binomial, n_quadrature if method == "agq" else 1)
        else:
            model = CrossedTerms(binomial, kept)
        problem = _Problem(model, names, tuple(kept), prior_sd, user_constant)
        result = optimise(problem, len(data), response, fixed_text, groups_done,
                          "glm" if not kept else method,
                          n_quadrature if method == "agq" and kept else (1 if kept else 0),
                          {t.group: int(c.max()) + 1 for t, c in zip(kept, codes, strict=True)},
                          penalty, notes)
        if direction is None:
            return result
        sup = _supremum(data, response, trials, terms, random_design, method, n_quadrature,
                        X, names, direction)
        unpenalised = _Problem(model, names, tuple(kept), None, user_constant)
        return dataclasses.replace(result, separation=Separation(
            tuple(separated), tuple(int(np.sign(d)) for d in direction if d != 0), sup,
            unpenalised))
    except _NUMERICAL_ERRORS as exc:
        raise GlmmFitError(f"numerical failure while maximising the likelihood "
                           f"({type(exc).__name__}: {exc})") from exc


def _supremum(data, response, trials, terms, random_design, method, n_quadrature, X, names,
              direction) -> float:
    """The supremum of the unpenalised log-likelihood of separated data: the maximum over the
    rows that the separation does not push to 0 or 1 (those contribute 0 in the limit, and
    their binomial constants are 0). See :mod:`crs_study.analysis.glmm_separation`."""
    keep = ~separated_rows(X, direction)
    if not keep.any():
        return 0.0
    rest = data.loc[keep]
    design = pd.DataFrame(X[keep], columns=names, index=rest.index)
    fit = fit_glmm(rest, response, design, random=terms, random_design=random_design,
                   trials=trials, method=method, n_quadrature=n_quadrature)
    return fit.separation.sup_loglike if fit.separation else fit.loglike


# ----------------------------------------------------------------------------- inference
def lrt(full: GlmmResult, reduced: GlmmResult) -> LrtResult:
    """Likelihood-ratio test of ``reduced`` nested in ``full`` (same data, same response).

    ``statistic = 2 (l_full - l_reduced)`` against chi2 with the difference in parameters as
    degrees of freedom; when the reduced model lacks one variance component the null sits on
    the boundary and the reference is the mixture ``0.5 chi2(df - 1) + 0.5 chi2(df)`` (Self &
    Liang 1987; Stram & Lee 1994, Biometrics 50:1171).
    """
    notes: list[str] = []
    if full.nobs != reduced.nobs or full.response != reduced.response:
        raise AnalysisError(f"lrt needs two fits of the same data: full has {full.nobs} rows of "
                            f"{full.response!r}, reduced {reduced.nobs} rows of "
                            f"{reduced.response!r}")
    df = full.n_params - reduced.n_params
    if df < 1:
        raise AnalysisError(f"lrt: the full model must have more parameters than the reduced "
                            f"one, got {full.n_params} and {reduced.n_params}")
    if {full.method, reduced.method} == {"laplace", "agq"}:
        raise AnalysisError("lrt: compare fits made with the same method (laplace or agq), got "
                            f"{full.method!r} and {reduced.method!r}")
    if not set(reduced.params.index) <= set(full.params.index) or not set(
            reduced.variance_components.index) <= set(full.variance_components.index):
        notes.append("the reduced model's terms are not a subset of the full model's; check "
                     "that the models are nested")
    if full.separation or reduced.separation:
        notes.append("separation: a separated model enters the test with the supremum of its "
                     "unpenalised log-likelihood (the separated coefficients at infinity), not "
                     "with its penalised fit")
    notes += [f"full model: {w}" for w in full.warnings]
    notes += [f"reduced model: {w}" for w in reduced.warnings]
    loglike_full, loglike_reduced = (r.separation.sup_loglike if r.separation else r.loglike
                                     for r in (full, reduced))
    statistic = 2.0 * (loglike_full - loglike_reduced)
    if statistic < -1e-6:
        notes.append(f"the reduced model fits better than the full one (statistic "
                     f"{statistic:.3g}): an optimisation failed; statistic set to 0")
    # Differences below optimiser precision are 0: chi2(0) puts its mass exactly there.
    statistic = statistic if statistic > 1e-6 else 0.0
    n_var = len(full.variance_components) - len(reduced.variance_components)
    if n_var == 1:
        low = stats.chi2.sf(statistic, df - 1) if df > 1 else float(statistic == 0.0)
        pvalue = 0.5 * low + 0.5 * stats.chi2.sf(statistic, df)
        distribution = f"0.5 chi2({df - 1}) + 0.5 chi2({df})"
    else:
        pvalue = stats.chi2.sf(statistic, df)
        distribution = f"chi2({df})"
        if n_var > 1:
            notes.append("several variances tested at once: the chi2 reference is conservative")
    return LrtResult(statistic=float(statistic), df=int(df),
                     pvalue=float(max(pvalue, P_FLOOR)), distribution=distribution,
                     loglike_full=loglike_full, loglike_reduced=loglike_reduced,
                     warnings=tuple(notes))


def profile_conf_int(result: GlmmResult, level: float = 0.95,
                     terms: Sequence[str] | None = None) -> pd.DataFrame:
    """Profile-likelihood intervals of fixed effects (lme4's ``confint(method = "profile")``).

    Columns ``ci_low``, ``ci_high`` (log-odds); an end is infinite when the profile does not
    drop by ``chi2_1(level) / 2`` within 2^12 standard errors. A coefficient whose ML estimate
    is infinite (separation) gets the one-sided limit of the *unpenalised* profile against the
    supremum, the other end infinite (:func:`~.glmm_separation.one_sided_limit`); the other
    coefficients of a separated fit are profiled on its penalised likelihood.
    """
    _check_profilable(result)
    names = list(result.params.index) if terms is None else list(terms)
    unknown = [t for t in names if t not in result.params.index]
    if unknown:
        raise AnalysisError(f"unknown term {unknown[0]!r}; terms: {list(result.params.index)!r}")
    try:
        rows = {t: _profile_term(result, t, level) for t in names}
    except _NUMERICAL_ERRORS as exc:
        raise GlmmFitError(f"numerical failure while profiling the likelihood "
                           f"({type(exc).__name__}: {exc})") from exc
    return pd.DataFrame.from_dict(rows, orient="index", columns=["ci_low", "ci_high"])


def _profile_term(result: GlmmResult, term: str, level: float) -> tuple[float, float]:
    index = list(result.params.index).index(term)
    separation = result.separation
    if separation is not None and term in separation.coefficients:
        return one_sided_limit(separation, list(result.params.index), result._model.theta, term,
                               level)
    return profile_interval(result, index, level)


def profile_sd_conf_int(result: GlmmResult, level: float = 0.95) -> pd.DataFrame:
    """Profile-likelihood intervals of the random effects' standard deviations.

    lme4's ``confint(method = "profile")`` rows ``.sig01, ...``: one row per standard
    deviation that is a parameter of the fit (a random intercept alone, or a column of an
    uncorrelated term), indexed as ``variance_components`` (the group, or ``group:column``),
    with columns ``sd`` (the estimate), ``ci_low``, ``ci_high``. The lower end is 0 when the
    profile at 0 lies within the cutoff (the boundary, see ``glmm_fit.profile_sd_interval``).
    A correlated term's SDs are functions of its Cholesky factor, not parameters of the fit:
    they get no row. Empty when the model has no random effect.
    """
    _check_profilable(result)
    try:
        rows = {name: (float(np.sqrt(result.variance_components[name])),
                       *profile_sd_interval(result, index, level))
                for name, index in _sd_parameters(result)}
    except _NUMERICAL_ERRORS as exc:
        raise GlmmFitError(f"numerical failure while profiling the likelihood "
                           f"({type(exc).__name__}: {exc})") from exc
    return pd.DataFrame.from_dict(rows, orient="index", columns=["sd", "ci_low", "ci_high"])


def _sd_parameters(result: GlmmResult) -> list[tuple[str, int]]:
    """``(variance_components name, parameter index)`` of every standard deviation that is
    a parameter of the fit."""
    n_fixed = len(result.params)
    if not result.terms:
        return [(g, n_fixed + k) for k, g in enumerate(result.variance_components.index)]
    out, start = [], n_fixed
    for term in result.terms:
        if not term.correlated or term.size == 1:
            for j, column in enumerate(term.columns):
                out.append((term.group if term.is_intercept else f"{term.group}:{column}",
                            start + j))
        start += term.n_theta
    return out


def _check_profilable(result: GlmmResult) -> None:
    if result._model is None:
        raise AnalysisError("profile intervals need a likelihood fitted by fit_glmm; this "
                            "result carries none")
