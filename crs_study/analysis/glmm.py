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
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats
from scipy.special import gammaln

from crs_study.analysis.glmm_core import (
    MAX_QUADRATURE,
    BinomialData,
    CrossedTerms,
    NoRandom,
    SingleFactor,
)
from crs_study.analysis.glmm_fit import fit_glm, optimise, profile_interval, profile_sd_interval
from crs_study.analysis.glmm_result import P_FLOOR, GlmmResult, LrtResult, format_pvalue
from crs_study.analysis.glmm_separation import (
    Separation,
    one_sided_limit,
    separated_rows,
    separation_direction,
)
from crs_study.analysis.glmm_terms import RandomTerm, parse_random, structure_label
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
    lme4's) with scipy (TNC, then L-BFGS-B if needed), unconstrained, from ``beta = 0`` and
    every factor the identity; a covariance near the boundary (an SD near 0, a correlated
    term near losing rank) is put on it only when the variance-scale slope there says the
    likelihood falls inward, otherwise the fit restarts from interior points
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
    terms = (_random_terms(data, random, random_design) if random is not None else
             [RandomTerm(g) for g in ([groups] if isinstance(groups, str) else list(groups))])
    group_list = [t.group for t in terms]
    _check_arguments(data, response, trials, group_list, method, n_quadrature)
    data = _drop_unused_levels(data, fixed, notes)
    X, names = _design(data, fixed)
    X, names = _drop_aliased(X, names, notes)
    y, m, user_constant = _response(data, response, trials)
    codes, kept = _group_codes(data, terms, notes)
    Z, kept = _term_designs(data, kept, random_design, notes)
    single_intercept = len(kept) == 1 and kept[0].is_intercept
    if method == "agq" and kept and not single_intercept:
        raise AnalysisError(f"adaptive quadrature needs a single random intercept (as lme4's "
                            f"nAGQ > 1); got {structure_label(kept)}: use method='laplace'")
    direction = separation_direction(X, y, m, _row_codes)
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
            problem = _Problem(NoRandom(_pool(X, y, m, [], [])), names, (), None,
                               user_constant)
            return fit_glm(X, y, m, names, user_constant, len(data), response, fixed_text,
                           groups_done, notes, problem)
        binomial = (_pool(X, y, m, codes, Z) if aggregate else
                    _unpooled(X, y, m, codes, Z))
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


def _random_terms(data: pd.DataFrame, random, random_design) -> list[RandomTerm]:
    """The terms of ``random`` (lme4 text, or RandomTerm objects), their columns checked."""
    if isinstance(random, str):
        return [RandomTerm(group, tuple(_patsy_columns(data, design)), correlated, design)
                for design, group, correlated in parse_random(random)]
    terms = list(random)
    for term in terms:
        if not isinstance(term, RandomTerm):
            raise AnalysisError(f"random= takes lme4 text or RandomTerm objects, got "
                                f"{type(term).__name__}")
        if term.design is None and not term.is_intercept:
            if random_design is None:
                raise AnalysisError(f"random term {term.label()} names design columns "
                                    f"{list(term.columns)!r}: give them as random_design=")
            missing = [c for c in term.columns if c not in random_design.columns]
            if missing:
                raise AnalysisError(f"random term {term.label()}: column(s) {missing!r} are "
                                    f"not in random_design {list(random_design.columns)!r}")
    return terms


def _patsy_columns(data: pd.DataFrame, design: str) -> list[str]:
    return list(_patsy_design(data, design).columns)


def _patsy_design(data: pd.DataFrame, formula: str,
                  what: str = "random-effects formula") -> pd.DataFrame:
    import patsy

    try:
        return patsy.dmatrix(formula, data, NA_action="raise", return_type="dataframe")
    except patsy.PatsyError as exc:
        message = str(exc).splitlines()[0]
        raise AnalysisError(f"{what} {formula!r}: {message}") from None


# ----------------------------------------------------------------------------- preparation
def _check_arguments(data, response, trials, group_list, method, n_quadrature) -> None:
    if not isinstance(data, pd.DataFrame):
        raise AnalysisError(f"fit_glmm expects a pandas DataFrame, got {type(data).__name__}")
    for role, col in [("response", response), ("trials", trials)] + [
            ("group", g) for g in group_list]:
        if col is not None and col not in data.columns:
            raise AnalysisError(f"{role} column {col!r} is not in the data; columns: "
                                f"{list(data.columns)!r}")
    if method not in ("laplace", "agq"):
        raise AnalysisError(f"method must be 'laplace' or 'agq', got {method!r}")
    if (isinstance(n_quadrature, bool) or not isinstance(n_quadrature, int | np.integer)
            or not 1 <= n_quadrature <= MAX_QUADRATURE):
        raise AnalysisError(f"n_quadrature must be an integer in 1..{MAX_QUADRATURE}, "
                            f"got {n_quadrature!r}")
    if len(data) == 0:
        raise AnalysisError("no rows to fit: the data frame is empty")


def _drop_unused_levels(data: pd.DataFrame, fixed, notes: list[str]) -> pd.DataFrame:
    """Remove categories without rows from categorical columns named in the formula."""
    if not isinstance(fixed, str):
        return data
    tokens = set(re.findall(r"[A-Za-z_][A-Za-z0-9_.]*", fixed))
    out = data
    for col in data.columns:
        if col in tokens and isinstance(data[col].dtype, pd.CategoricalDtype):
            present = set(data[col].dropna().unique())
            unused = [c for c in data[col].cat.categories if c not in present]
            if unused:
                out = out.copy() if out is data else out
                out[col] = out[col].cat.remove_unused_categories()
                notes.append(f"level(s) {unused!r} of {col!r} have no trials; dropped from the "
                             f"model")
    return out


def _design(data: pd.DataFrame, fixed) -> tuple[np.ndarray, list[str]]:
    if isinstance(fixed, pd.DataFrame):
        if not fixed.index.equals(data.index):
            raise AnalysisError(f"the design matrix's rows must be the data's (same index): "
                                f"{len(fixed)} rows against {len(data)}, or another order")
        X = fixed.to_numpy(dtype=float)
        names = [str(c) for c in fixed.columns]
    elif isinstance(fixed, str):
        if "~" in fixed:
            raise AnalysisError(f"fixed is the right-hand side of a formula (e.g. 'condition'), "
                                f"got {fixed!r}; give the response as response=")
        design = _patsy_design(data, fixed, "fixed-effects formula")
        X = design.to_numpy(dtype=float)
        names = list(design.columns)
    else:
        raise AnalysisError(f"fixed must be a formula string or a DataFrame, got "
                            f"{type(fixed).__name__}")
    if not np.all(np.isfinite(X)):
        raise AnalysisError("the fixed-effects design has missing or infinite values")
    return X, names


def _drop_aliased(X: np.ndarray, names: list[str], notes: list[str]):
    """Drop design columns that are zero or linear combinations of others (lme4 does too)."""
    from scipy.linalg import qr

    if X.shape[1] == 0:
        raise AnalysisError("the fixed-effects design has no columns")
    _, R, piv = qr(X, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    rank = int(np.sum(diag > max(X.shape) * np.finfo(float).eps * diag[0])) if diag[0] else 0
    if rank == X.shape[1]:
        return X, names
    keep = np.sort(piv[:rank])
    dropped = [names[i] for i in sorted(piv[rank:])]
    notes.append(f"fixed-effect column(s) {dropped!r} are empty or aliased with others "
                 f"(a condition without trials?); dropped")
    return X[:, keep], [names[i] for i in keep]


def _response(data: pd.DataFrame, response: str, trials: str | None):
    """Successes, trials and the binomial constant ``sum log C(trials, successes)``."""
    y = pd.to_numeric(data[response], errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(y)
    if bad.any():
        first = data[response].to_numpy()[bad][0]
        raise AnalysisError(f"response {response!r} has {int(bad.sum())} missing or non-numeric "
                            f"value(s), e.g. {first!r}")
    if trials is None:
        if not np.all((y == 0) | (y == 1)):
            raise AnalysisError(f"response {response!r} must be 0/1 per trial (or give trials=), "
                                f"got {y[(y != 0) & (y != 1)][0]!r}")
        return y, np.ones_like(y), 0.0
    m = pd.to_numeric(data[trials], errors="coerce").to_numpy(dtype=float)
    if not np.all(np.isfinite(m)) or np.any(m < 0) or np.any(m != np.round(m)):
        raise AnalysisError(f"trials {trials!r} must be non-negative integers")
    if np.any(y < 0) or np.any(y > m) or np.any(y != np.round(y)):
        raise AnalysisError(f"response {response!r} must be integers between 0 and {trials!r}")
    constant = float(np.sum(gammaln(m + 1) - gammaln(y + 1) - gammaln(m - y + 1)))
    return y, m, constant


def _group_codes(data: pd.DataFrame, terms: list[RandomTerm], notes: list[str]):
    """The level codes of each term's grouping factor; a factor of one level is dropped."""
    codes, kept = [], []
    for term in terms:
        g = term.group
        if data[g].isna().any():
            raise AnalysisError(f"group column {g!r} has {int(data[g].isna().sum())} missing "
                                f"value(s)")
        c, levels = pd.factorize(data[g], sort=True)
        if len(levels) < 2:
            shown = term.shown_group()  # as the report names it: participant
            what = "random intercept" if term.is_intercept else f"random term {term.label()}"
            notes.append(f"grouping factor {shown!r} has a single level ({levels[0]!r}): its "
                         f"variance is not estimable; the {what} was dropped")
            continue
        codes.append(c.astype(np.intp))
        kept.append(term)
    if terms and not kept:
        notes.append("no random effect left: fitted a fixed-effects logistic regression")
    return codes, kept


def _term_designs(data: pd.DataFrame, terms: list[RandomTerm], random_design,
                  notes: list[str]) -> tuple[tuple[np.ndarray, ...], list[RandomTerm]]:
    """Each term's design ``Z`` (n, r); a column with no nonzero entry (a condition without
    trials) is dropped from its term, with a note."""
    Z, kept = [], []
    for term in terms:
        if term.is_intercept and term.design is None:
            Z.append(np.ones((len(data), 1)))
            kept.append(term)
            continue
        frame = (_patsy_design(data, term.design) if term.design is not None
                 else random_design.loc[data.index, list(term.columns)])
        z = frame.to_numpy(dtype=float)
        if not np.all(np.isfinite(z)):
            raise AnalysisError(f"random term {term.label()}: its design has missing or "
                                f"infinite values")
        empty = [c for c, col in zip(term.columns, z.T, strict=True) if not np.any(col)]
        for column in empty:
            notes.append(f"random term {term.label()}: column {column!r} is zero on every "
                         f"row; dropped from the term")
            term = term.without(column)
        z = z[:, [i for i, c in enumerate(frame.columns) if c not in empty]]
        Z.append(z)
        kept.append(term)
    return tuple(Z), kept


def _row_codes(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of each row's distinct value (rows of a 2-D array) and one row per distinct value.

    Column-wise hashed factorisation (``pandas.factorize``, sorted codes) combined in mixed
    radix: much faster than ``np.unique(axis=0)``, which sorts rows as opaque byte strings,
    or ``np.unique`` per column; the distinct rows come in sorted key order, as ``np.unique``
    gives them, so the pooled rows do not depend on the order of the data.
    """
    key = np.zeros(len(columns), dtype=np.int64)
    for col in columns.T:
        inverse, uniques = pd.factorize(col, sort=True)
        key = key * len(uniques) + inverse
    inverse, uniques = pd.factorize(key, sort=True)
    first = np.empty(len(uniques), dtype=np.intp)
    first[inverse[::-1]] = np.arange(len(key) - 1, -1, -1)
    return inverse.astype(np.intp), columns[first]


def _pool(X, y, m, codes, Z) -> BinomialData:
    """Sum successes and trials over rows with equal group levels, design row and random
    designs."""
    k = len(codes)
    widths = [z.shape[1] for z in Z]
    inverse, unique = _row_codes(np.column_stack([*(c.astype(float) for c in codes), X,
                                                  *Z]))
    p = X.shape[1]
    ends = k + p + np.cumsum(widths, dtype=int)
    pooled_Z = tuple(unique[:, e - w:e] for e, w in zip(ends, widths, strict=True))
    return BinomialData(unique[:, k:k + p], np.bincount(inverse, y), np.bincount(inverse, m),
                        tuple(unique[:, i].astype(np.intp) for i in range(k)),
                        tuple(int(c.max()) + 1 for c in codes), pooled_Z or None)


def _unpooled(X, y, m, codes, Z) -> BinomialData:
    return BinomialData(X, y, m, tuple(codes), tuple(int(c.max()) + 1 for c in codes),
                        tuple(Z) or None)


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
