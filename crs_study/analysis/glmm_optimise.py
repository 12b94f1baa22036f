"""Maximising the GLMM objective: local fits, the boundary check and restarts.

The objective ``l(beta, sigma)`` (Laplace or AGQ marginal log-likelihood, see
:mod:`crs_study.analysis.glmm_core`) is *even* in every random-effect standard deviation
``sigma_k``: only ``sigma_k^2`` enters the model. Two consequences decide the design:

1. On the SD scale the derivative ``dl/dsigma_k`` is exactly 0 at ``sigma_k = 0`` whatever
   the data say, so the boundary always satisfies the first-order conditions there. A
   bounded optimiser on ``sigma >= 0`` (the earlier TNC) whose line search clips a sigma onto
   the bound never leaves it: 23 of 59 lme4 comparisons stopped short that way (issue 12).
   Here every sigma is optimised *unconstrained* (any real; the estimate is ``|sigma|``), so
   no step is ever clipped onto 0.
2. Whether 0 is the estimate is then decided by a check the SD-scale gradient cannot fool:
   the one-sided derivative of the profile on the *variance* scale ``v = sigma^2`` at
   ``v = 0``. With every other parameter re-maximised (the fit with ``sigma_k`` held at 0)
   the envelope theorem gives ``d l_prof / dv (0+) = dl/dv = (1/2) d^2 l / d sigma_k^2`` at
   ``sigma_k = 0``; it is computed as ``g_k(h) / (2 h)`` from the exact gradient at ``sigma_k
   = h = 1e-3`` (the derivative on the variance scale at ``v = 1e-6``), or from values where
   the model's gradient is itself a difference. The boundary is the estimate only when that
   slope is <= 0 for every sigma held at 0 (the Karush-Kuhn-Tucker condition of the problem
   on the variance scale, ``v >= 0``), and the boundary fit is at least as high as the best
   interior one. Otherwise the variance is moved inward: the fit restarts from interior
   points (``RESTART_SIGMAS``) and the best optimum found is kept, as lme4's ``allFit``
   compares optimisers (STYLE.md point 19).

The same :func:`maximise` fits the full model, the reduced one and every point of every
profile, so a profile frees every variance (none is held at the estimate's boundary).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

#: A sigma below this after a local fit is compared with the boundary fit (sigma = 0).
NEAR_ZERO = 0.05
#: Largest variance-scale slope at v = 0 (loglik per unit variance) still read as <= 0.
SLOPE_TOLERANCE = 1e-6
#: Interior starting values of a sigma whose boundary is not a maximum.
RESTART_SIGMAS = (0.3, 1.0, 2.5)
_SLOPE_STEP = 1e-3
_MAX_ROUNDS = 4
# Truncated Newton (scipy's C TNC), unconstrained: as accurate as L-BFGS-B here and free of
# the per-iteration BLAS calls that make scipy's L-BFGS-B ~10x slower on a busy
# multi-threaded OpenBLAS; L-BFGS-B is the second try when TNC stops short.
_METHODS = (("TNC", {"maxfun": 3000, "ftol": 1e-14, "gtol": 1e-9, "xtol": 1e-10}),
            ("L-BFGS-B", {"maxiter": 3000, "ftol": 1e-15, "gtol": 1e-7}))
#: Profile points need the maximum to ~1e-8 in log-likelihood, not the estimates to 1e-10: a
#: profile end is where the drop meets the cutoff, and an error e in the drop moves the end
#: by about e / slope (slope ~ 1 on the signed-root scale), far below the 1e-4 Brent tolerance.
_PROFILE_METHODS = (("TNC", {"maxfun": 3000, "ftol": 1e-11, "gtol": 1e-6, "xtol": 1e-8}),
                    ("L-BFGS-B", {"maxiter": 3000, "ftol": 1e-13, "gtol": 1e-6}))
_LOCAL_GRADIENT = 2e-5   # max |gradient| of the log-likelihood accepted after the first method


@dataclass
class Optimum:
    """A maximum of the objective over the parameters not held.

    ``theta`` has every sigma as ``|sigma|``; ``at_zero`` the sigma indices estimated at the
    boundary (exactly 0 in ``theta``) with their variance-scale slopes ``d l / dv`` at 0+
    (all <= ``SLOPE_TOLERANCE`` when the boundary check passed).
    """

    theta: np.ndarray
    value: float
    at_zero: dict[int, float] = field(default_factory=dict)
    evaluations: int = 0
    iterations: int = 0
    restarts: int = 0
    message: str = ""


class _Counted:
    """Wraps an objective for the minimiser: ``-value``, ``-gradient``, counts calls."""

    def __init__(self, problem, held: dict[int, float], size: int):
        self.problem = problem
        self.held = held
        self.mask = np.ones(size, bool)
        self.mask[list(held)] = False
        self.calls = 0

    def full(self, free: np.ndarray) -> np.ndarray:
        theta = np.empty(len(self.mask))
        theta[~self.mask] = [self.held[i] for i in np.flatnonzero(~self.mask)]
        theta[self.mask] = free
        return theta

    def __call__(self, free: np.ndarray):
        self.calls += 1
        value, g = self.problem.objective(self.full(free))
        if not np.isfinite(value):
            return np.inf, np.zeros(len(free))
        return -value, -g[self.mask]


def local_fit(problem, start: np.ndarray, held: dict[int, float],
              methods=_METHODS) -> Optimum:
    """One unconstrained local maximisation (sigmas may go negative; returned as ``|sigma|``).

    TNC first; L-BFGS-B from TNC's end when the gradient there is not yet small.
    """
    counted = _Counted(problem, held, len(start))
    x = start[counted.mask]
    iterations, message = 0, "no free parameter"
    if len(x):
        for method, options in methods:
            res = optimize.minimize(counted, x, jac=True, method=method, options=options)
            x, iterations, message = res.x, iterations + int(res.nit), str(res.message)
            _, g = counted(x)
            if np.max(np.abs(g)) < _LOCAL_GRADIENT:
                break
    theta = counted.full(x)
    theta[problem.n_fixed:] = np.abs(theta[problem.n_fixed:])
    value = problem.objective(theta, grad=False)
    return Optimum(theta, float(value), {}, counted.calls + 1, iterations, 0, message)


def variance_slope(problem, theta: np.ndarray, index: int) -> float:
    """``d l / dv`` at ``v = sigma_index^2 = 0+``, the other parameters as in ``theta``.

    ``(1/2) d^2 l / d sigma^2`` at 0, from the exact gradient at ``sigma = h``: ``g(h) / 2h``
    is the variance-scale derivative at ``v = h^2`` (``dl/dv = (dl/dsigma) / (2 sigma)``).
    Where the model's gradient is itself a difference, from values: ``(l(v = d) - l(0)) / d``.
    """
    h = _SLOPE_STEP
    shifted = theta.copy()
    shifted[index] = h
    if getattr(problem.model, "analytic_gradient", True):
        slope = float(problem.objective(shifted)[1][index]) / (2.0 * h)
    else:
        d = 1e-4
        shifted[index] = np.sqrt(d)
        base = theta.copy()
        base[index] = 0.0
        slope = (problem.objective(shifted, grad=False)
                 - problem.objective(base, grad=False)) / d
    problem.objective(theta, grad=False)   # leave the warm start at theta
    return slope


def maximise(problem, start: np.ndarray, held: dict[int, float] | None = None,
             profile: bool = False) -> Optimum:
    """The maximum of the objective over the parameters not ``held``, boundary checked.

    A local fit; then, for the sigmas that ended near 0, the fit with them held at 0 and the
    variance-scale slope of each there. All slopes <= 0 and the boundary fit no lower: the
    boundary is the estimate. Some slope > 0: restarts from ``RESTART_SIGMAS`` for those
    sigmas, the best optimum kept, and the check repeated on it (at most ``_MAX_ROUNDS``).
    ``profile``: the looser tolerances of a profile point (``_PROFILE_METHODS``).
    """
    held = dict(held or {})
    methods = _PROFILE_METHODS if profile else _METHODS
    sigmas = [i for i in range(problem.n_fixed, len(start)) if i not in held]
    best = local_fit(problem, np.asarray(start, float), held, methods)
    evaluations, iterations, restarts = best.evaluations, best.iterations, 0
    for _ in range(_MAX_ROUNDS):
        near = [i for i in sigmas if best.theta[i] < NEAR_ZERO]
        if not near:
            break
        boundary_start = best.theta.copy()
        boundary_start[near] = 0.0
        boundary = local_fit(problem, boundary_start, {**held, **dict.fromkeys(near, 0.0)},
                             methods)
        evaluations += boundary.evaluations
        iterations += boundary.iterations
        slopes = {i: variance_slope(problem, boundary.theta, i) for i in near}
        inward = [i for i, s in slopes.items() if s > SLOPE_TOLERANCE]
        tolerance = 1e-9 * (1.0 + abs(best.value))
        if not inward:
            if boundary.value >= best.value - tolerance:
                boundary.at_zero = slopes
                best = boundary
            break
        if best.value > boundary.value + tolerance:
            break        # a small interior SD, higher than the boundary: a true estimate
        # Moving inward raises l, yet the local fit did not get away from 0 (a flat start):
        # restart from interior points, keep the best, check again.
        improved = False
        for sigma in RESTART_SIGMAS:
            restart = boundary.theta.copy()
            restart[inward] = sigma
            candidate = local_fit(problem, restart, held, methods)
            evaluations += candidate.evaluations
            iterations += candidate.iterations
            restarts += 1
            if candidate.value > best.value + 1e-10 * (1.0 + abs(best.value)):
                best, improved = candidate, True
        if not improved:
            best = boundary      # report the boundary with the slope that says it is not
            best.at_zero = slopes      # a maximum: the fit is then flagged unconverged
            break
    problem.objective(best.theta, grad=False)   # the warm start at the optimum
    best.evaluations, best.iterations, best.restarts = evaluations, iterations, restarts
    return best


def boundary_failures(opt: Optimum) -> dict[int, float]:
    """The boundary sigmas whose variance-scale slope says moving inward raises l."""
    return {i: s for i, s in opt.at_zero.items() if s > SLOPE_TOLERANCE}
