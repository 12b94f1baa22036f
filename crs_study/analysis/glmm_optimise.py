"""Maximising the GLMM objective: local fits, the boundary check and restarts.

The objective ``l(beta, theta)`` (Laplace or AGQ marginal log-likelihood, see
:mod:`crs_study.analysis.glmm_core`) depends on each term's loading ``T_k`` only through
``Sigma_k = T_k T_k'``: a random intercept's SD ``sigma`` only through ``sigma^2``, a
correlated term's loading only up to the sign of each column. Two consequences decide the
design:

1. On the SD scale the derivative ``dl/dsigma_k`` is exactly 0 at ``sigma_k = 0`` whatever
   the data say (and likewise for a zero column of ``T_k``), so the boundary always
   satisfies the first-order conditions there. A bounded optimiser on ``sigma >= 0`` whose
   line search clips a sigma onto the bound never leaves it (23 of 59 lme4 comparisons of an
   earlier version stopped short that way). Here theta is optimised *unconstrained* (any
   real; the estimate is made lme4's, a non-negative diagonal, afterwards), so no step is
   ever clipped onto the boundary.
2. Whether the boundary is the estimate is then decided by a check the SD-scale gradient
   cannot fool: the one-sided derivative of the profile on the *variance* scale. For a
   standard deviation (a random intercept, a column of an uncorrelated term) that is ``d
   l_prof / dv`` at ``v = sigma^2 = 0+``; with every other parameter re-maximised (the fit
   with ``sigma_k`` held at 0) the envelope theorem gives ``(1/2) d^2 l / d sigma_k^2`` at
   0, computed as ``g_k(h) / (2 h)`` from the exact gradient at ``sigma_k = h = 1e-3``. For
   a correlated term the boundary is ``Sigma_k`` losing rank (a variance at 0, or a
   correlation at +-1): the fit on that face holds the last columns of ``T_k`` at 0 (every
   matrix of rank ``r - d`` is ``L L'`` with ``L`` lower trapezoidal,
   :func:`~crs_study.analysis.glmm_terms.rank_deficient_loading`), and the check is the
   largest eigenvalue of ``N' G N``, ``G = dl/dSigma_k`` and ``N`` the null space of the
   face's ``Sigma_k``: the slope of ``l`` per unit variance added in the most favourable
   missing direction (the Karush-Kuhn-Tucker condition on the cone of covariance matrices,
   Boyd & Vandenberghe 2004, Convex Optimization, sec. 5.9.2), read from ``dl/dT = 2 G T`` at
   ``T`` extended by ``h N``. The boundary is the estimate only when every such slope is <= 0
   and the boundary fit is at least as high as the best interior one. Otherwise the fit
   restarts inward (``RESTART_SIGMAS`` along the rising direction) and the best optimum found
   is kept, as lme4's ``allFit`` compares optimisers.

The same :func:`maximise` fits the full model, the reduced one and every point of every
profile, so a profile frees every variance (none is held at the estimate's boundary).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from crs_study.analysis.glmm_newton import THETA_CAP, newton
from crs_study.analysis.glmm_terms import Block, loading, rank_deficient_loading, theta_of

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
class Face:
    """A boundary an optimum sits on: a block's covariance short of ``deficiency`` dimensions.

    ``held`` are the parameter indices held at 0 on it; ``slope`` the largest variance-scale
    derivative of ``l`` inward (per unit variance, every other parameter as at the optimum;
    <= ``SLOPE_TOLERANCE`` when the boundary is a maximum); ``direction`` (r,) the unit
    vector of the term's effects along which ``l`` rises fastest (``None`` for an SD) and
    ``null`` (r, d) the directions the face's covariance lacks.
    """

    block: Block
    held: tuple[int, ...]
    deficiency: int
    slope: float = float("nan")
    direction: np.ndarray | None = None
    null: np.ndarray | None = None


@dataclass
class Optimum:
    """A maximum of the objective over the parameters not held.

    ``theta`` is lme4's (every loading with a non-negative diagonal); ``faces`` the
    boundaries it sits on (the held parameters exactly 0 in ``theta``), with their slopes.
    """

    theta: np.ndarray
    value: float
    faces: list[Face] = field(default_factory=list)
    evaluations: int = 0
    iterations: int = 0
    restarts: int = 0
    message: str = ""
    settled: bool = True     # False: a local fit stopped short near a face, not yet decided
    curvature: np.ndarray | None = None   # an unsettled end's negative Hessian (Newton's)

    @property
    def at_zero(self) -> dict[int, float]:
        """Each parameter held at 0 on a face, with that face's slope."""
        return {i: face.slope for face in self.faces for i in face.held}


def blocks_of(problem) -> tuple[Block, ...]:
    """The model's boundary blocks: its terms' (:class:`~.glmm_terms.ThetaLayout`), else one
    standard deviation per variance parameter."""
    layout = getattr(problem.model, "layout", None)
    if layout is not None:
        return layout.blocks
    return tuple(Block(k, (problem.n_fixed + k,), False)
                 for k in range(problem.model.n_variance))


def normalise(problem, theta: np.ndarray) -> np.ndarray:
    """``theta`` with each loading's diagonal non-negative (each SD as ``|sigma|``)."""
    layout = getattr(problem.model, "layout", None)
    if layout is not None:
        return layout.normalised(theta)
    out = np.asarray(theta, dtype=float).copy()
    out[problem.n_fixed:] = np.abs(out[problem.n_fixed:])
    return out


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


class _Single:
    """One fit as :func:`~.glmm_newton.newton` takes a batch (S = 1), calls counted."""

    def __init__(self, problem):
        self.problem = problem
        self.warm = np.zeros((1, 0))     # the model keeps its own warm start
        self.calls = 0

    def evaluate(self, theta: np.ndarray, grad: bool = True):
        self.calls += 1
        if not grad:
            return np.array([self.problem.objective(theta[0], grad=False)]), None
        value, g = self.problem.objective(theta[0])
        return np.array([value]), np.asarray(g)[None]

    def subset(self, index) -> _Single:
        return self

    def gradients(self, theta: np.ndarray, rows: np.ndarray) -> np.ndarray:
        self.calls += len(theta)
        return self.problem.gradients(theta)

    def normalised(self, theta: np.ndarray) -> np.ndarray:
        return normalise(self.problem, theta[0])[None]

    @property
    def capped(self) -> np.ndarray:
        """The loading entries (every parameter after the fixed effects)."""
        return np.arange(self.problem.n_fixed + self.problem.model.n_variance) >= \
            self.problem.n_fixed

    def diagonals(self, held: np.ndarray) -> np.ndarray:
        layout = getattr(self.problem.model, "layout", None)
        if layout is not None:
            return layout.diagonals(held)
        return np.broadcast_to(self.capped, held.shape)     # a single intercept's SD


def local_fit(problem, start: np.ndarray, held: dict[int, float],
              methods=_METHODS, curvature: np.ndarray | None = None,
              stop_near_face: bool = False) -> Optimum:
    """One unconstrained local maximisation (theta of any sign; returned normalised).

    Newton's method (:func:`~.glmm_newton.newton`: the exact gradient, a differenced
    Hessian, or ``curvature``, a negative Hessian known to be near, to start) first; where it
    stops short of its gradient tolerance, scipy's TNC from the start, then L-BFGS-B from
    TNC's end when the gradient there is not yet small (:func:`_scipy_fit`). With
    ``stop_near_face`` a Newton end near a boundary is returned unsettled instead: near a
    face Newton's method crawls (``l ~ a s^2 + b s^4``), and the caller decides on the face,
    where the problem is regular, before falling back.
    """
    single = _Single(problem)
    theta0 = np.asarray(start, float).copy()
    mask = np.zeros(len(theta0), dtype=bool)
    for i, value in held.items():
        theta0[i], mask[i] = value, True
    theta, value, converged, iterations, N = newton(
        single, theta0[None], mask[None], None if curvature is None else curvature[None],
        face_sd=NEAR_ZERO if stop_near_face else None)
    if converged[0] and np.isfinite(value[0]):
        value = problem.objective(theta[0], grad=False)
        return Optimum(theta[0], float(value), [], single.calls + 1, int(iterations[0]), 0,
                       "Newton: gradient below tolerance")
    if stop_near_face and np.isfinite(value[0]) and _faces_near(problem, theta[0], held):
        value = problem.objective(theta[0], grad=False)
        return Optimum(theta[0], float(value), [], single.calls + 1, int(iterations[0]), 0,
                       "Newton: stopped near a boundary", settled=False, curvature=N[0])
    fit = _scipy_fit(problem, start, held, methods)
    fit.evaluations += single.calls
    return fit


def _scipy_fit(problem, start: np.ndarray, held: dict[int, float], methods) -> Optimum:
    """scipy's minimisers in turn from ``start`` (the held parameters fixed), every loading
    entry within ``THETA_CAP``."""
    counted = _Counted(problem, held, len(start))
    x = np.clip(np.asarray(start, float), *_box(problem, len(start)))[counted.mask]
    low, high = (bound[counted.mask] for bound in _box(problem, len(start)))
    bounds = optimize.Bounds(low, high)
    iterations, message = 0, "no free parameter"
    if len(x):
        for method, options in methods:
            res = optimize.minimize(counted, x, jac=True, method=method, options=options,
                                    bounds=bounds)
            x, iterations, message = res.x, iterations + int(res.nit), str(res.message)
            _, g = counted(x)
            if np.max(np.abs(g)) < _LOCAL_GRADIENT:
                break
    theta = normalise(problem, counted.full(x))
    value = problem.objective(theta, grad=False)
    return Optimum(theta, float(value), [], counted.calls + 1, iterations, 0, message)


def _box(problem, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The parameters' bounds: the fixed effects free, every loading entry within
    ``THETA_CAP``."""
    high = np.full(size, np.inf)
    high[problem.n_fixed:] = THETA_CAP
    return -high, high


def at_cap(theta: np.ndarray, n_fixed: int) -> np.ndarray:
    """Indices of the loading entries at ``THETA_CAP`` (within a millionth of it)."""
    return n_fixed + np.flatnonzero(np.abs(theta[n_fixed:]) >= THETA_CAP * (1.0 - 1e-6))


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


def rank_slope(problem, theta: np.ndarray, face: Face) -> Face:
    """The face with its slope: the largest eigenvalue of ``N' G N`` (module docstring), from
    the exact gradient of the loading extended by ``h N``; ``direction`` its eigenvector."""
    layout = problem.model.layout
    k = face.block.term
    r, d = layout.terms[k].size, face.deficiency
    loadings = [T[0] for T in layout.loadings(theta[None])]
    T = loadings[k]
    values, vectors = np.linalg.eigh(T @ T.T)
    null = vectors[:, :d]
    h = _SLOPE_STEP
    extended = T.copy()
    extended[:, r - d:] = h * null
    loadings[k] = extended
    _, _, gradients = problem.model.loadings_loglik(theta[:layout.n_fixed], loadings)
    M = null.T @ gradients[k][:, r - d:] / (2.0 * h)
    values, vectors = np.linalg.eigh(0.5 * (M + M.T))
    problem.objective(theta, grad=False)   # leave the warm start at theta
    return Face(face.block, face.held, d, float(values[-1]), null @ vectors[:, -1], null)


def _faces_near(problem, theta: np.ndarray, held: dict[int, float],
                on: list[Face] = ()) -> list[Face]:
    """The blocks whose covariance is within ``NEAR_ZERO`` (SD scale) of losing rank, or,
    for a block already on a face of ``on``, of losing more rank than that face."""
    faces = []
    depth = {face.block: face.deficiency for face in on}
    for block in blocks_of(problem):
        if block not in depth and any(i in held for i in block.indices):
            continue
        if block in depth and not block.matrix:
            continue
        if not block.matrix:
            if abs(theta[block.indices[0]]) < NEAR_ZERO:
                faces.append(Face(block, block.indices, 1))
            continue
        term = problem.model.layout.terms[block.term]
        T = loading(term, theta[list(block.indices)])
        sds = np.sqrt(np.clip(np.linalg.eigvalsh(T @ T.T), 0.0, None))
        d = int(np.sum(sds < NEAR_ZERO))
        if d > depth.get(block, 0):
            r = term.size
            faces.append(Face(block, tuple(i for i, (_, col) in zip(block.indices, term.entries,
                                                                   strict=True)
                                           if col >= r - d), d))
    return faces


def _on_face(problem, theta: np.ndarray, faces: list[Face]) -> np.ndarray:
    """``theta`` moved onto the faces: held SDs 0, correlated loadings of reduced rank."""
    out = theta.copy()
    for face in faces:
        if not face.block.matrix:
            out[face.held[0]] = 0.0
            continue
        term = problem.model.layout.terms[face.block.term]
        idx = list(face.block.indices)
        out[idx] = theta_of(term, rank_deficient_loading(loading(term, theta[idx]),
                                                         face.deficiency))
    return out


def _slopes(problem, theta: np.ndarray, faces: list[Face]) -> list[Face]:
    out = []
    for face in faces:
        if face.block.matrix:
            out.append(rank_slope(problem, theta, face))
        else:
            out.append(Face(face.block, face.held, 1,
                            variance_slope(problem, theta, face.held[0])))
    return out


def _inward(problem, theta: np.ndarray, faces: list[Face], sigma: float) -> np.ndarray:
    """``theta`` moved off the rising faces by ``sigma`` (SD scale) along their directions."""
    out = theta.copy()
    layout = getattr(problem.model, "layout", None)
    for face in faces:
        idx = list(face.block.indices)
        out[idx] = inward_entries(layout, face.block, theta[idx], face.direction, face.null,
                                  sigma)
    return out


def inward_entries(layout, block: Block, values: np.ndarray, direction: np.ndarray | None,
                   null: np.ndarray | None, sigma: float) -> np.ndarray:
    """A block's entries of theta (``values``) moved off its face by ``sigma`` (SD scale):
    an SD set to ``sigma``; a correlated term's loading replaced by the Cholesky factor of
    ``T T' + sigma^2 d d' + (sigma / 10)^2 N N'``, its covariance of reduced rank moved
    along the rising direction ``d`` and a tenth of that along the rest of its null space
    ``N``."""
    if not block.matrix:
        return np.full(len(values), sigma)
    term = layout.terms[block.term]
    T = loading(term, values)
    cov = (T @ T.T + sigma**2 * np.outer(direction, direction)
           + (0.1 * sigma) ** 2 * null @ null.T)
    return theta_of(term, np.linalg.cholesky(cov))


def maximise(problem, start: np.ndarray, held: dict[int, float] | None = None,
             profile: bool = False, curvature: np.ndarray | None = None) -> Optimum:
    """The maximum of the objective over the parameters not ``held``, boundary checked.

    A local fit; then, for the blocks that ended near their boundary, the fit on the face
    (:func:`_faces_near`) and its slopes. All slopes <= 0 and the face's fit no lower: the
    boundary is the estimate. Some slope > 0: restarts inward (``RESTART_SIGMAS``), the best
    optimum kept, and the check repeated on it (at most ``_MAX_ROUNDS``). ``profile``: the
    looser tolerances of a profile point (``_PROFILE_METHODS``); ``curvature``, a negative
    Hessian near ``start`` (the fit's, for its profile points), starts Newton's method.
    """
    held = dict(held or {})
    methods = _PROFILE_METHODS if profile else _METHODS
    best = local_fit(problem, np.asarray(start, float), held, methods, curvature,
                     stop_near_face=True)
    evaluations, iterations, restarts = best.evaluations, best.iterations, 0
    for _ in range(_MAX_ROUNDS):
        # the faces ``best`` already sits on stay held; a fit on them may end near others
        fixed = {**held, **dict.fromkeys(best.at_zero, 0.0)}
        near = _faces_near(problem, best.theta, fixed, best.faces)
        if not near:
            break
        on_face = {i: 0.0 for face in near for i in face.held}
        boundary = local_fit(problem, _on_face(problem, best.theta, near),
                             {**fixed, **on_face}, methods, best.curvature)
        evaluations += boundary.evaluations
        iterations += boundary.iterations
        deeper = {face.block for face in near}
        faces = _slopes(problem, boundary.theta,
                        [face for face in best.faces if face.block not in deeper] + near)
        inward = [face for face in faces if face.slope > SLOPE_TOLERANCE]
        tolerance = 1e-9 * (1.0 + abs(best.value))
        if not inward and boundary.value >= best.value - tolerance:
            boundary.faces = faces
            best = boundary
            continue
        if not best.settled:     # the interior end is higher or the face rises: finish it
            finished = _scipy_fit(problem, best.theta, fixed, methods)
            finished.faces = _slopes(problem, finished.theta, best.faces)
            evaluations += finished.evaluations
            iterations += finished.iterations
            best = finished
            continue
        if not inward:
            break
        if best.value > boundary.value + tolerance:
            break        # a small interior SD, higher than the boundary: a true estimate
        # Moving inward raises l, yet the local fit did not get away from the face (a flat
        # start): restart from interior points, keep the best, check again.
        improved = False
        for sigma in RESTART_SIGMAS:
            candidate = local_fit(problem, _inward(problem, boundary.theta, inward, sigma),
                                  held, methods)
            evaluations += candidate.evaluations
            iterations += candidate.iterations
            restarts += 1
            if candidate.value > best.value + 1e-10 * (1.0 + abs(best.value)):
                best, improved = candidate, True
        if not improved:
            best = boundary      # report the boundary with the slope that says it is not
            best.faces = faces   # a maximum: the fit is then flagged unconverged
            break
    problem.objective(best.theta, grad=False)   # the warm start at the optimum
    best.evaluations, best.iterations, best.restarts = evaluations, iterations, restarts
    return best


def boundary_failures(opt: Optimum) -> list[Face]:
    """The faces whose variance-scale slope says moving inward raises l."""
    return [face for face in opt.faces if face.slope > SLOPE_TOLERANCE]
