"""Outer optimisation of the GLMM objective, the observed information and the GLM fallback."""

from __future__ import annotations

import warnings as _warnings

import numpy as np
import pandas as pd
from scipy import optimize, stats

from crs_study.analysis.glmm_newton import THETA_CAP
from crs_study.analysis.glmm_optimise import Optimum, at_cap, boundary_failures, maximise
from crs_study.analysis.glmm_result import BoundaryFace, FitState, GlmmResult
from crs_study.analysis.glmm_start import moment_start
from crs_study.analysis.glmm_terms import INTERCEPT, covariance, sd_and_correlation

_CONVERGED_GRADIENT = 2e-3  # lme4's check.conv.grad tolerance (on the deviance scale)
_END_TOLERANCE = 5e-5       # Brent's tolerance on a profile end (log-odds or SD)
#: A profile interval's end is sought at most this far from the estimate (log-odds or SD
#: units): 15 on the log-odds scale is an odds ratio of 3.3 million, beyond any difference
#: between two displays; the profile of separated or nearly separated data (a condition at 0
#: or 100 % for every participant) stays flat far out, each point a slow fit, and an end
#: out there says only that the data do not bound it: reported as open (null), as when the
#: profile never reaches the cutoff.
PROFILE_SPAN = 15.0


def _minimise(problem, start: np.ndarray, fixed_values: dict[int, float]
              ) -> tuple[np.ndarray, Optimum, int]:
    """``(theta, optimum, evaluations)`` of :func:`~.glmm_optimise.maximise` with
    ``fixed_values`` held (kept for callers of the earlier name)."""
    opt = maximise(problem, start, fixed_values)
    return opt.theta, opt, opt.evaluations


def optimise(problem, nobs: int, response: str, fixed: str, groups: tuple[str, ...],
             method: str, n_quadrature: int, n_groups: dict[str, int], penalty: str | None,
             notes: list[str]) -> GlmmResult:
    """Maximise the (penalised) marginal log-likelihood and assemble the result.

    From the data's empirical logits and moments (:func:`~.glmm_start.moment_start`; a
    single intercept from ``beta = 0`` and SD 1), by
    :func:`~.glmm_optimise.maximise`: theta unconstrained, a boundary (an SD at 0, a
    correlated term of reduced rank) taken only when its variance-scale slope says the
    likelihood falls inward. ``converged`` is true when the gradient over the parameters not
    on the boundary is within lme4's tolerance (``2 max |dl/dtheta| < 2e-3``, or the Newton
    step ``H^-1 g`` below 1e-4 as lme4 scales it) *and* every boundary passed that check;
    each boundary or singular-fit sentence is a measured statement. ``problem.terms`` holds
    the fitted terms (:class:`~.glmm_terms.RandomTerm`).
    """
    n_fixed = problem.n_fixed
    layout = getattr(problem.model, "layout", None)
    if layout is not None:
        lik = problem.model.likelihood
        start = moment_start(lik.X, lik.Y[0], lik.m, lik.terms, layout)
    else:
        start = np.r_[np.zeros(n_fixed), np.ones(problem.model.n_variance)]
    opt = maximise(problem, start)
    theta, at_zero = opt.theta, opt.at_zero
    failed = boundary_failures(opt)
    terms = tuple(problem.terms)
    faces = []
    # in the model's order, whichever order the optimiser met them (as batched fits list them)
    for face in sorted(opt.faces, key=lambda f: f.block.indices[0]):
        described = describe_face(face, terms, theta, n_fixed)
        sentence = described.text
        if any(face is f for f in failed):
            notes.append(f"{sentence} although the likelihood rises as it moves inward (d "
                         f"loglik / d variance = {face.slope:.3g} there) and no interior start "
                         f"found a higher maximum; estimates may be unreliable")
            continue
        faces.append(described)
        tail = ("a likelihood-ratio test of this variance follows a 50:50 mixture of chi2(0) "
                "and chi2(1)" if not face.block.matrix else "the fit is singular")
        notes.append(f"{sentence} (boundary, a singular fit): the likelihood falls as it moves "
                     f"inward (d loglik / d variance = {face.slope:.3g} there, every other "
                     f"parameter re-maximised); {tail}")
    value, gradient = problem.objective(theta)
    free = [i for i in range(len(theta)) if i not in at_zero]
    information = -_hessian(problem, theta, free)
    max_grad = float(np.max(np.abs(gradient[free]))) if free else 0.0
    converged = bool(np.isfinite(value) and 2.0 * max_grad < _CONVERGED_GRADIENT)
    if not converged and np.isfinite(value):
        try:  # lme4 scales the gradient by the Hessian before judging it
            step = np.linalg.solve(information, gradient[free])
            converged = bool(np.max(np.abs(step)) < 1e-4)
        except np.linalg.LinAlgError:
            pass
    if not converged:
        notes.append(f"the optimiser did not converge (max |gradient| {max_grad:.3g}, "
                     f"{opt.message}); estimates may be unreliable")
    capped = at_cap(theta, n_fixed) if layout is not None else ()
    if len(capped):
        notes.append(f"{len(capped)} loading(s) of the random effects' Cholesky factor reached "
                     f"the cap of {THETA_CAP:g} (an SD of {THETA_CAP:g} or more on the logit "
                     "scale) with the likelihood still rising: the data do not bound that "
                     "variance (a condition near 0 or 100 % correct for some groups); the fit "
                     "is treated as not converged")
    converged = converged and not failed and not len(capped)
    cov = _fixed_covariance(information, n_fixed, notes)
    names = problem.names
    loglike = float(problem.model.loglik(theta, grad=False)) + problem.user_constant
    variances = _variances(terms, theta[n_fixed:])
    index = _labels(names)      # one index for the three: each conversion of a list costs
    return GlmmResult(
        params=pd.Series(theta[:n_fixed], index=index, name="estimate"),
        bse=pd.Series(np.sqrt(np.diag(cov)), index=index, name="std_error"),
        cov_params=pd.DataFrame(cov, index=index, columns=index),
        variance_components=variances,
        loglike=loglike, nobs=nobs, n_groups=n_groups, method=method,
        n_quadrature=n_quadrature, converged=converged,
        n_function_evaluations=opt.evaluations, n_iterations=opt.iterations,
        max_abs_gradient=max_grad, response=response, fixed=fixed, groups=groups,
        penalty=penalty, warnings=tuple(notes),
        _model=FitState(problem, theta, tuple(at_zero), _full_curvature(information, free,
                                                                       len(theta))),
        terms=terms, theta=tuple(float(t) for t in theta[n_fixed:]),
        faces=tuple(faces))


#: pandas' dtype for an index of text labels, as ``pd.Index(list_of_str)`` infers it.
_TEXT_LABELS = pd.Index(["label"]).dtype


def _labels(names: list[str]) -> pd.Index:
    """``pd.Index(names)`` for text labels, without inferring the dtype again (a third of the
    time of a fit's result on 1,200 trials was pandas building its three objects)."""
    return pd.Index(names, dtype=_TEXT_LABELS) if names else pd.Index(names)   # as inferred


def _full_curvature(information: np.ndarray, free: list[int], size: int) -> np.ndarray:
    """The negative Hessian over the free parameters as a full matrix (identity for the held
    ones), the start of a nearby fit's Newton iteration."""
    out = np.eye(size)
    out[np.ix_(free, free)] = information
    return out


def _variances(terms, theta: np.ndarray) -> pd.Series:
    """Every random effect's variance: indexed by the group for a random intercept alone (as
    before slopes existed), ``group:column`` for each column of a larger term."""
    index, values = [], []
    start = 0
    for term in terms:
        if term.is_intercept:            # T is its one entry: the variance is its square
            index.append(term.group)
            values.append(float(theta[start]) ** 2)
            start += 1
            continue
        sigma = covariance(term, theta[start:start + term.n_theta])
        start += term.n_theta
        for j, column in enumerate(term.columns):
            index.append(f"{term.group}:{column}")
            values.append(float(sigma[j, j]))
    return pd.Series(np.array(values), index=_labels(index), name="variance")


def describe_face(face, terms, theta: np.ndarray, n_fixed: int) -> BoundaryFace:
    """A boundary as a measured fact: which variance is 0, which correlation is +-1, with the
    slope of the likelihood there."""
    term = terms[face.block.term]
    group = term.shown_group()
    start = _term_start(terms, face.block.term, n_fixed)

    def variance(column: str, where: str = "") -> BoundaryFace:
        what = "random intercept" if column == INTERCEPT else f"random slope of {column!r}"
        return BoundaryFace(term.label(), group, "variance", (column,), face.slope,
                            f"the variance of the {what} for {group!r} is estimated at 0"
                            f"{where}", in_slope_term=face.block.matrix)

    if not face.block.matrix:
        return variance(term.columns[face.block.indices[0] - start])
    r, d = term.size, face.deficiency
    single = [j for j in range(r) if np.allclose(np.abs(face.null[j]), 1.0, atol=1e-3)]
    if d == 1 and single:
        return variance(term.columns[single[0]], f" (in {term.label()})")
    if d == r:
        return BoundaryFace(term.label(), group, "rank", term.columns, face.slope,
                            f"every variance of {term.label()} is estimated at 0",
                            in_slope_term=True)
    sigma = covariance(term, theta[start:start + term.n_theta])
    sd, corr = sd_and_correlation(sigma)
    if r == 2 and d == 1:
        bound = 1.0 if corr[0, 1] > 0 else -1.0
        # G = slope n n' on the face; d loglik / d rho = 2 G_12 sd_1 sd_2 at the bound
        corr_slope = float(2.0 * face.slope * face.null[0, 0] * face.null[1, 0] * sd[0] * sd[1])
        return BoundaryFace(term.label(), group, "correlation", term.columns, face.slope,
                            f"the correlation of the random effects in {term.label()} is "
                            f"estimated at {bound:+.0f} (d loglik / d correlation = "
                            f"{corr_slope:.3g} there)", corr_slope, in_slope_term=True)
    return BoundaryFace(term.label(), group, "rank", term.columns, face.slope,
                        f"the covariance matrix of {term.label()} is estimated singular "
                        f"(rank {r - d} of {r}: correlations at +-1)", in_slope_term=True)


def _term_start(terms, k: int, n_fixed: int) -> int:
    return n_fixed + sum(t.n_theta for t in terms[:k])


def _hessian(problem, theta: np.ndarray, free: list[int]) -> np.ndarray:
    """Hessian of the objective over the ``free`` parameters, by central differences.

    Differences of the analytic gradient where the model has one (the ``2k`` points in one
    batched evaluation where the model can); of values otherwise.
    """
    k = len(free)
    H = np.zeros((k, k))
    if not k:
        return H
    steps = np.array([1e-4 * max(1.0, abs(theta[i])) for i in free])
    if problem.model.analytic_gradient:
        points = np.tile(theta, (2 * k, 1))          # up, down for each parameter in turn
        points[2 * np.arange(k), free] += steps
        points[2 * np.arange(k) + 1, free] -= steps
        if problem.batched:         # every point from the optimum's modes, in one pass
            problem.objective(theta)
        g = problem.gradients(points)[:, free]
        H = (g[0::2] - g[1::2]) / (2 * steps[:, None])
        problem.objective(theta)  # restore the warm start at the optimum
        return 0.5 * (H + H.T)
    steps = [1e-3 * max(1.0, abs(theta[i])) for i in free]

    def f(shift: dict[int, float]) -> float:
        t = theta.copy()
        for i, d in shift.items():
            t[i] += d
        return problem.objective(t, grad=False)

    centre = f({})
    for a in range(k):
        i, hi = free[a], steps[a]
        H[a, a] = (f({i: hi}) - 2 * centre + f({i: -hi})) / hi**2
        for b in range(a):
            j, hj = free[b], steps[b]
            H[a, b] = H[b, a] = (f({i: hi, j: hj}) - f({i: hi, j: -hj}) - f({i: -hi, j: hj})
                                 + f({i: -hi, j: -hj})) / (4 * hi * hj)
    return H


def _fixed_covariance(information: np.ndarray, n_fixed: int, notes: list[str]) -> np.ndarray:
    """``inverse(information)[beta, beta]`` (lme4 calc.vcov.hess), with honest fallbacks."""
    whole = _positive_definite_inverse(information)
    if whole is not None:
        return whole[:n_fixed, :n_fixed]
    block = _positive_definite_inverse(information[:n_fixed, :n_fixed])
    if block is not None:
        notes.append("the information matrix of all parameters is not positive definite; "
                     "standard errors treat the variance(s) as known")
        return block
    notes.append("the information matrix of the fixed effects is singular; standard errors "
                 "are not available (NaN)")
    return np.full((n_fixed, n_fixed), np.nan)


def _positive_definite_inverse(matrix: np.ndarray) -> np.ndarray | None:
    """The inverse of a positive-definite ``matrix``, or None when it is not one, or is so
    near singular that its computed inverse has a diagonal entry <= 0 or not finite."""
    try:
        np.linalg.cholesky(matrix)
        inverse = np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return None
    diagonal = np.diag(inverse)
    if not np.all(np.isfinite(inverse)) or np.any(diagonal <= 0):
        return None
    return inverse


def fit_glm(X, y, m, names, user_constant, nobs, response, fixed, groups, notes,
            problem=None) -> GlmmResult:
    """Fixed-effects logistic regression by statsmodels' GLM (no random effect estimable).

    ``problem``, the same likelihood as our objective, lets the result be profiled.
    """
    import statsmodels.api as sm

    with _warnings.catch_warnings(record=True) as caught:
        _warnings.simplefilter("always")
        fit = sm.GLM(np.column_stack([y, m - y]), X, family=sm.families.Binomial()).fit()
    notes.extend(f"statsmodels GLM: {w.message}" for w in caught)
    eta = X @ fit.params
    loglike = float(np.sum(y * eta - m * np.logaddexp(0.0, eta))) + user_constant
    cov = np.asarray(fit.cov_params())
    index = _labels(names)
    return GlmmResult(
        params=pd.Series(fit.params, index=index, name="estimate"),
        bse=pd.Series(np.sqrt(np.diag(cov)), index=index, name="std_error"),
        cov_params=pd.DataFrame(cov, index=index, columns=index),
        variance_components=pd.Series([], index=[], name="variance", dtype=float),
        loglike=loglike, nobs=nobs, n_groups={}, method="glm", n_quadrature=0,
        converged=bool(fit.converged), n_function_evaluations=int(fit.fit_history["iteration"]),
        n_iterations=int(fit.fit_history["iteration"]), max_abs_gradient=float(np.max(np.abs(
            X.T @ (y - m / (1 + np.exp(-eta)))))), response=response, fixed=fixed,
        groups=groups, penalty=None, warnings=tuple(notes),
        _model=None if problem is None else FitState(problem, np.asarray(fit.params, float)))


def profile_interval(result: GlmmResult, index: int, level: float) -> tuple[float, float]:
    """Profile-likelihood interval of fixed effect ``index``: ``2 (l_max - l_prof(b)) = chi2``.

    Each profile point re-maximises over every other parameter, every variance included (a
    variance estimated at 0 is free to move inward at other values of ``b``: holding it at 0
    gave intervals narrower than lme4's with few trials per cell), by the same boundary-checked
    :func:`~.glmm_optimise.maximise` as the fit (Venzon & Moolgavkar 1988 in the plain
    bracketing form); the ends are found with Brent's method.
    """
    problem, theta_hat = result._model.problem, result._model.theta
    se = float(result.bse.iloc[index]) if np.isfinite(result.bse.iloc[index]) else 1.0
    drop = _profile_drop(problem, theta_hat, index, level, result._model.curvature)
    low = _profile_end(drop, theta_hat[index], -2.0 * se)
    high = _profile_end(drop, theta_hat[index], 2.0 * se)
    problem.objective(theta_hat)  # restore the warm start at the optimum
    return low, high


def profile_sd_interval(result: GlmmResult, index: int, level: float) -> tuple[float, float]:
    """Profile-likelihood interval of the standard deviation at parameter ``index``.

    As lme4's ``confint(method = "profile")`` for ``.sig0k``: the ends are where ``2 (l_max -
    l_prof(sigma)) = chi2_1(level)``, every other parameter (other variances included)
    re-maximised. The standard deviation cannot be negative: when the profile at ``sigma =
    0`` is still within the cutoff the lower end is 0 (always so when the estimate itself is
    0); the upper end is infinite when the profile never drops that far (a flat likelihood,
    e.g. two groups).
    """
    problem, theta_hat = result._model.problem, result._model.theta
    drop = _profile_drop(problem, theta_hat, index, level, result._model.curvature)
    sigma = float(theta_hat[index])
    low = 0.0 if drop(0.0) <= 0.0 else float(optimize.brentq(drop, 0.0, sigma,
                                                              xtol=_END_TOLERANCE))
    high = _profile_end(drop, sigma, max(0.5 * sigma, 0.25))
    problem.objective(theta_hat)
    return low, high


def _profile_drop(problem, theta_hat: np.ndarray, index: int, level: float,
                  curvature: np.ndarray | None = None):
    """``b -> sqrt(2 (l_max - l_prof(b))) - sqrt(chi2_1(level))``: negative inside the
    interval. On this signed-root scale (lme4's ``zeta``) the profile is nearly linear, so
    Brent's method needs few points."""
    target = np.sqrt(stats.chi2.ppf(level, 1))
    top = problem.objective(theta_hat, grad=False)

    centre = float(theta_hat[index])
    optima = {centre: theta_hat.copy()}   # warm starts: profiled optima by held value
    known = {centre: -target}   # Brent asks again for the bracket's ends

    def drop(value: float) -> float:
        if float(value) in known:
            return known[float(value)]
        # start from the nearest optimum on the same side of the estimate, never from the
        # other end's search (on a likelihood with several peaks that start could land lower
        # and overstate the drop, placing the end too close)
        side = sorted((v for v in optima if (v - centre) * (value - centre) >= 0),
                      key=lambda v: abs(v - value))
        start = optima[side[0]].copy()
        if len(side) > 1:   # the other parameters extrapolated along the profile trace
            a, b = side[0], side[1]
            start = start + (value - a) / (a - b) * (optima[a] - optima[b])
            start[problem.n_fixed:] = np.abs(start[problem.n_fixed:])
        start[index] = value
        opt = maximise(problem, start, {index: value}, profile=True, curvature=curvature)
        optima[float(value)] = opt.theta
        known[float(value)] = float(np.sqrt(2.0 * max(top - opt.value, 0.0))) - target
        return known[float(value)]

    return drop


def _profile_end(drop, estimate: float, step: float) -> float:
    """The root of ``drop`` beyond ``estimate`` in the direction of ``step`` (doubled to
    bracket it, never beyond ``PROFILE_SPAN``); infinite when the profile does not reach the
    cutoff within that span. A first step of 0 (a standard error of 0) starts at a
    thousandth of the span."""
    if not np.isfinite(step) or abs(step) < 1e-3 * PROFILE_SPAN:
        step = float(np.copysign(1e-3 * PROFILE_SPAN, step if np.isfinite(step) else 1.0))
    while True:   # at most 11 doublings from a thousandth to the whole span
        step = float(np.copysign(min(abs(step), PROFILE_SPAN), step))
        if drop(estimate + step) > 0:
            a, b = sorted((estimate, estimate + step))
            return float(optimize.brentq(drop, a, b, xtol=_END_TOLERANCE))
        if abs(step) >= PROFILE_SPAN:
            return float(np.copysign(np.inf, step))
        step *= 2.0
