"""Maximum-likelihood fits of many studies at once, at the maximum ``fit_glmm`` finds.

:func:`fit_batch` maximises :class:`~crs_study.power_analysis.laplace.BatchLaplace` for every
study of a batch by Newton's method: the exact gradient, the Hessian by forward differences of it, a
step-halving line search, every study on its own and frozen once its gradient is below
``GRADIENT_TOL`` (far inside lme4's convergence check, ``2 max |g| < 2e-3``, and inside the
``2e-5`` that :mod:`crs_study.analysis.glmm_optimise` accepts). Sigmas are unconstrained, as
there: the objective is even in each, the estimate is ``|sigma|``.

The boundary is then decided exactly as :func:`crs_study.analysis.glmm_optimise.maximise`
decides it, with its constants: a sigma below ``NEAR_ZERO`` after the local fit is held at
0, the rest refitted, and the variance-scale slope ``g(h) / 2h`` at ``h = 1e-3`` read; no
slope above ``SLOPE_TOLERANCE`` and a boundary fit no lower: the boundary is the estimate; an
inward slope and an interior optimum higher than the boundary: the interior one; an inward
slope and no higher interior optimum is where ``maximise`` restarts from interior points: such
a study is marked ``needs_reference`` and refitted by ``fit_glmm`` itself, as is every study
whose Newton iteration stalls (:mod:`crs_study.power_analysis.study`).

Starting values: the generating parameters (a power simulation knows them), each sigma at
least ``MIN_START_SIGMA`` (at sigma = 0 the gradient of an even function is 0 whatever the
data: a start there never leaves it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crs_study.analysis.glmm_optimise import NEAR_ZERO, SLOPE_TOLERANCE
from crs_study.power_analysis.laplace import BatchLaplace

#: A study's fit is done when no free coordinate of the gradient exceeds this.
GRADIENT_TOL = 1e-6
MAX_ITERATIONS = 40
MIN_START_SIGMA = 0.25
#: The Hessian is taken afresh by differences every this many iterations (BFGS between):
#: near a boundary (l ~ a sigma^2 + b sigma^4) the secant updates alone converge slowly.
REFRESH_EVERY = 4
#: Longest step in any coordinate (log-odds or SD units) in one iteration.
MAX_STEP = 1.0
_SLOPE_STEP = 1e-3  # glmm_optimise._SLOPE_STEP: the slope is read at sigma = 1e-3


@dataclass
class BatchFit:
    """The maxima of a batch: ``theta`` (S, n) with sigmas as ``|sigma|``, ``value`` (S,) the
    log-likelihood kernel, ``at_zero`` (S, n) the sigmas estimated at the boundary,
    ``needs_reference`` (S,) the studies to refit with ``fit_glmm``, ``iterations`` (S,),
    ``curvature`` (S, n, n) the last negative-Hessian approximation of the interior fit (a
    start for a nested model's)."""

    theta: np.ndarray
    value: np.ndarray
    at_zero: np.ndarray
    needs_reference: np.ndarray
    iterations: np.ndarray
    curvature: np.ndarray


def _newton(objective: BatchLaplace, theta0: np.ndarray, held: np.ndarray,
            N0: np.ndarray | None = None):
    """Maxima over the free coordinates (``~held``) of every study.

    The first step is Newton's with the Hessian by forward differences of the exact
    gradient; later steps update that matrix by BFGS (the secant pairs of the accepted
    steps, skipped where the curvature condition fails), so an iteration costs one
    evaluation of value and gradient when its full step is taken; ``N0`` (S, n, n), a
    negative Hessian known to be near (a related model's), replaces the first differences.
    Returns ``(theta, value, converged, iterations, N)`` with ``N`` each study's last
    matrix; ``objective.warm`` holds the conditional modes at ``theta``.
    """
    theta = theta0.copy()
    S, n = theta.shape
    free = ~held
    value, g = objective.evaluate(theta)
    g = np.where(free, g, 0.0)
    converged = np.zeros(S, dtype=bool)
    iterations = np.zeros(S, dtype=int)
    N = None if N0 is None else N0.copy()
    N_last = np.zeros((S, n, n))
    active = np.arange(S)
    sub = objective.subset(active)
    for iteration in range(MAX_ITERATIONS):
        th, v, ga = theta[active], value[active], g[active]
        done = np.max(np.abs(ga), axis=1) < GRADIENT_TOL
        bad = ~np.isfinite(v) | ~np.isfinite(ga).all(axis=1)
        converged[active[done & ~bad]] = True
        keep = ~done & ~bad
        if not keep.all():
            objective.warm.put(active[~keep], sub.warm.take(~keep))
            if N is not None:
                N_last[active[~keep]] = N[~keep]
            active, th, v, ga = active[keep], th[keep], v[keep], ga[keep]
            sub = sub.subset(np.flatnonzero(keep))
            N = None if N is None else N[keep]
        if not len(active):
            break
        iterations[active] += 1
        if N is None or (iteration and iteration % REFRESH_EVERY == 0):
            N = _negative_hessian(sub, th, ga, free[active])
        elif iteration == 0:                # N0 given: differences only where it is unusable
            unusable = np.linalg.eigvalsh(N)[:, 0] <= 0
            if unusable.any():
                rows = np.flatnonzero(unusable)
                N[rows] = _negative_hessian(sub.subset(rows), th[rows], ga[rows],
                                            free[active][rows])
        step = _solve(N, ga, free[active])
        th_new, v_new, g_new, ok = _line_search(sub, th, v, step)
        g_new = np.where(free[active], g_new, 0.0)
        N = _bfgs(N, th_new - th, ga - g_new, ok)
        theta[active] = np.where(ok[:, None], th_new, th)
        value[active] = np.where(ok, v_new, v)
        g[active] = np.where(ok[:, None], g_new, ga)
        if not ok.all():                       # no ascent along the step: stalled
            objective.warm.put(active[~ok], sub.warm.take(~ok))
            N_last[active[~ok]] = N[~ok]
            active, N = active[ok], N[ok]
            sub = sub.subset(np.flatnonzero(ok))
    else:
        objective.warm.put(active, sub.warm)
        if N is not None:
            N_last[active] = N
    theta[:, objective.design.n_fixed:] = np.abs(theta[:, objective.design.n_fixed:])
    return theta, value, converged, iterations, N_last


def _negative_hessian(sub: BatchLaplace, theta, g, free) -> np.ndarray:
    """``-d2 l / dtheta2`` over the free coordinates by forward differences of the exact
    gradient (identity rows and columns for the held ones)."""
    S, n = theta.shape
    warm = sub.warm.copy()
    H = np.zeros((S, n, n))
    for j in range(n):
        if not free[:, j].any():
            continue
        h = 1e-5 * np.maximum(1.0, np.abs(theta[:, j]))
        shifted = theta.copy()
        shifted[:, j] += h
        sub.warm = warm.copy()
        _, gj = sub.evaluate(shifted)
        H[:, :, j] = (gj - g) / h[:, None]
    sub.warm = warm
    N = -0.5 * (H + np.swapaxes(H, 1, 2))
    mask = free[:, :, None] & free[:, None, :]
    N = np.where(mask, N, 0.0)
    idx = np.arange(n)
    N[:, idx, idx] = np.where(free, N[:, idx, idx], 1.0)
    return N


def _solve(N: np.ndarray, g: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The ascent step ``N^-1 g``, ``N`` made positive definite where it is not (eigenvalues
    reflected and floored: the usual modified Newton step), shortened to ``MAX_STEP`` in its
    longest coordinate (a flat direction would otherwise send it far off, where every
    evaluation costs many inner iterations for nothing)."""
    lam, V = np.linalg.eigh(N)
    top = np.max(np.abs(lam), axis=1, keepdims=True)
    lam = np.maximum(np.abs(lam), 1e-8 * np.maximum(top, 1.0))
    step = np.where(free, np.einsum("sij,sj->si", V, np.einsum("sji,sj->si", V, g) / lam), 0.0)
    longest = np.max(np.abs(step), axis=1, keepdims=True)
    return step * np.minimum(1.0, MAX_STEP / np.maximum(longest, 1e-300))


def _bfgs(N: np.ndarray, s: np.ndarray, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """BFGS update of the negative Hessian ``N`` with step ``s`` and gradient change ``y =
    g_old - g_new`` (Nocedal & Wright 2006, eq. 6.19), where ``y's > 0``."""
    ys = np.einsum("si,si->s", y, s)
    Ns = np.einsum("sij,sj->si", N, s)
    sNs = np.einsum("si,si->s", s, Ns)
    good = ok & (ys > 1e-12 * np.sqrt(np.einsum("si,si->s", y, y) * np.einsum(
        "si,si->s", s, s))) & (sNs > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        update = (y[:, :, None] * y[:, None, :] / ys[:, None, None]
                  - Ns[:, :, None] * Ns[:, None, :] / sNs[:, None, None])
    return np.where(good[:, None, None], N + update, N)


def _line_search(sub: BatchLaplace, theta, value, step):
    """The full step where the objective does not fall there (value and gradient in one
    evaluation), else the step halved until it does (values only, then the gradient at the
    point taken). ``ok`` False where 30 halvings found no such point."""
    S = len(theta)
    warm = sub.warm.copy()
    trial = theta + step
    v, g = sub.evaluate(trial)
    ok = _not_lower(v, value)
    candidate = np.where(ok[:, None], trial, theta)
    new_value = np.where(ok, v, value)
    new_g = np.where(ok[:, None], g, 0.0)
    best = sub.warm
    best.put(np.flatnonzero(~ok), warm.take(~ok))
    pending = np.flatnonzero(~ok)
    t = np.ones(S)
    halved = np.zeros(S, dtype=bool)
    for _ in range(30):
        if not len(pending):
            break
        t[pending] *= 0.5
        trial = theta[pending] + t[pending, None] * step[pending]
        part = sub.subset(pending)
        part.warm = warm.take(pending)
        v, _ = part.evaluate(trial, grad=False)
        good = _not_lower(v, value[pending])
        accepted = pending[good]
        ok[accepted] = halved[accepted] = True
        candidate[accepted] = trial[good]
        new_value[accepted] = v[good]
        best.put(accepted, part.warm.take(good))
        pending = pending[~good]
    if halved.any():
        rows = np.flatnonzero(halved)
        part = sub.subset(rows)
        part.warm = best.take(rows)
        new_value[rows], new_g[rows] = part.evaluate(candidate[rows])
        best.put(rows, part.warm)
    sub.warm = best
    return candidate, new_value, new_g, ok


def _not_lower(v: np.ndarray, value: np.ndarray) -> np.ndarray:
    return np.isfinite(v) & (v >= value - 1e-12 * (1.0 + np.abs(value)))


def fit_batch(objective: BatchLaplace, start: np.ndarray,
              curvature: np.ndarray | None = None) -> BatchFit:
    """Maximise every study's likelihood from ``start`` (S, n), boundary checked;
    ``curvature`` (S, n, n), a negative Hessian near the start (the full model's at its
    maximum, for the reduced model), saves the first differences."""
    S, n = start.shape
    k = objective.design.n_fixed
    start = start.copy()
    start[:, k:] = np.maximum(np.abs(start[:, k:]), MIN_START_SIGMA)
    held = np.zeros((S, n), dtype=bool)
    theta, value, converged, iterations, N = _newton(objective, start, held, curvature)
    needs = ~converged
    at_zero = np.zeros((S, n), dtype=bool)
    near = np.zeros((S, n), dtype=bool)
    near[:, k:] = theta[:, k:] < NEAR_ZERO
    check = np.flatnonzero(near.any(axis=1) & converged)
    if len(check):
        sub = objective.subset(check)
        b_theta, b_value, b_ok, b_iter, _ = _newton(sub, np.where(near[check], 0.0,
                                                                  theta[check]), near[check])
        iterations[check] += b_iter
        slopes = _slopes(sub, b_theta, near[check])
        inward = ((slopes > SLOPE_TOLERANCE) & near[check]).any(axis=1)
        best = value[check]
        tolerance = 1e-9 * (1.0 + np.abs(best))
        take_boundary = b_ok & ~inward & (b_value >= best - tolerance)
        keep_interior = ~take_boundary & (best > b_value + tolerance)
        rows = check[take_boundary]
        theta[rows] = b_theta[take_boundary]
        value[rows] = b_value[take_boundary]
        at_zero[rows] = near[check][take_boundary]
        needs[check[~take_boundary & ~keep_interior]] = True
    return BatchFit(theta, value, at_zero, needs, iterations, N)


def _slopes(sub: BatchLaplace, theta: np.ndarray, near: np.ndarray) -> np.ndarray:
    """``d l / dv`` at ``v = sigma^2 = 0+`` for each ``near`` sigma: ``g(h) / 2h`` from the
    exact gradient at ``sigma = h``, the other parameters at the boundary fit (as
    ``glmm_optimise.variance_slope``); NaN elsewhere."""
    slopes = np.full(theta.shape, np.nan)
    for j in np.flatnonzero(near.any(axis=0)):
        rows = np.flatnonzero(near[:, j])
        shifted = theta[rows].copy()
        shifted[:, j] = _SLOPE_STEP
        _, g = sub.subset(rows).evaluate(shifted)
        slopes[rows, j] = g[:, j] / (2.0 * _SLOPE_STEP)
    return slopes
