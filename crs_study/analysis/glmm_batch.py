"""Maximum-likelihood fits of many studies at once, at the maximum ``fit_glmm`` finds.

A power simulation fits the same model to thousands of datasets of one design, a parametric
bootstrap to a thousand of one dataset's. :func:`fit_batch` maximises the Laplace
log-likelihood (:class:`~crs_study.analysis.glmm_laplace.LaplaceLikelihood`, read through
lme4's theta by a :class:`~crs_study.analysis.glmm_terms.ThetaLayout`) for every study of a
batch by Newton's method: the exact gradient, the Hessian by forward differences of it
(refreshed every ``REFRESH_EVERY`` iterations where the secant updates are slow, BFGS
updates between), a step-halving line
search, every study on its own and frozen once its gradient is below ``GRADIENT_TOL`` (far
inside lme4's convergence check, ``2 max |g| < 2e-3``, and inside the ``2e-5`` that
:mod:`crs_study.analysis.glmm_optimise` accepts). Theta is unconstrained, as there; the
estimate is made lme4's (non-negative diagonals) at the end.

The boundary is then decided exactly as :func:`crs_study.analysis.glmm_optimise.maximise`
decides it, with its constants: a block near its boundary after the local fit (an SD below
``NEAR_ZERO``, a correlated term with an eigenvalue of its covariance below ``NEAR_ZERO^2``)
is put on it (held at 0, or the term's loading of reduced rank), the rest refitted, and the
variance-scale slope read there; no slope above ``SLOPE_TOLERANCE`` and a boundary fit no
lower: the boundary is the estimate; an inward slope and an interior optimum higher than the
boundary: the interior one; an inward slope where the interior iteration had not settled is
where ``maximise`` restarts from interior points: Newton's method once more from the face
moved inward along its rising direction (``RESTART_SIGMAS[0]``), its end taken when it is
above the face's and, if near a face itself, that face decided as above. Any other study
is marked ``needs_reference`` and left to ``fit_glmm`` itself, as is every study whose
Newton iteration stalls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from crs_study.analysis.glmm_fit import _variances, describe_face
from crs_study.analysis.glmm_laplace import LaplaceLikelihood
from crs_study.analysis.glmm_newton import newton
from crs_study.analysis.glmm_optimise import (
    NEAR_ZERO,
    RESTART_SIGMAS,
    SLOPE_TOLERANCE,
    Face,
    inward_entries,
)
from crs_study.analysis.glmm_start import MomentStart
from crs_study.analysis.glmm_terms import (
    ThetaLayout,
    loading,
    rank_deficient_loading,
    theta_of,
)

MIN_START_SIGMA = 0.25
_SLOPE_STEP = 1e-3  # glmm_optimise._SLOPE_STEP: the slope is read at sigma = 1e-3


class BatchObjective:
    """``l(beta, theta)`` of ``S`` studies: the likelihood and the layout of its parameters.
    The conditional modes of every study (``likelihood.u``) are the warm starts."""

    def __init__(self, likelihood: LaplaceLikelihood, layout: ThetaLayout):
        self.likelihood = likelihood
        self.layout = layout

    @property
    def n_fixed(self) -> int:
        return self.layout.n_fixed

    def __len__(self) -> int:
        return self.likelihood.n_studies

    def evaluate(self, theta: np.ndarray, grad: bool = True):
        """``(value (S,), gradient (S, n) or None)`` at ``theta`` (S, n)."""
        layout = self.layout
        value, g_beta, g_loadings = self.likelihood.evaluate(
            theta[:, :layout.n_fixed], layout.loadings(theta), grad)
        if not grad:
            return value, None
        return value, layout.gradient(g_beta, g_loadings)

    def subset(self, index) -> BatchObjective:
        return BatchObjective(self.likelihood.subset(index), self.layout)

    def gradients(self, theta: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The gradient at each ``theta[i]`` (K, n) of study ``rows[i]``, from that study's
        warm start (left as it was), in one pass."""
        return self.subset(rows).evaluate(theta)[1]

    def moment_starts(self) -> np.ndarray:
        """Each study's start read off its own data (S, n; :class:`~.glmm_start.MomentStart`,
        the design's poolings found once): nearer each study's maximum than any one start
        for all of them."""
        lik = self.likelihood
        start = MomentStart(lik.X, lik.m, lik.terms, self.layout)
        return np.array([start(y) for y in lik.Y])

    def normalised(self, theta: np.ndarray) -> np.ndarray:
        return self.layout.normalised(theta)

    def diagonals(self, held: np.ndarray) -> np.ndarray:
        return self.layout.diagonals(held)

    @property
    def capped(self) -> np.ndarray:
        """The loading entries (within ``THETA_CAP``)."""
        return np.arange(self.layout.n_fixed + self.layout.n_theta) >= self.layout.n_fixed

    @property
    def warm(self) -> np.ndarray:
        return self.likelihood.u

    @warm.setter
    def warm(self, u: np.ndarray) -> None:
        self.likelihood.u = u


@dataclass
class BatchFit:
    """The maxima of a batch: ``theta`` (S, n) lme4's, ``value`` (S,) the log-likelihood
    kernel, ``at_zero`` (S, n) the parameters held at 0 on a boundary, ``deficiency`` (S,
    blocks) how many dimensions each block's covariance lacks there, ``slopes`` (S, blocks)
    their variance-scale slopes (NaN off the boundary), ``needs_reference`` (S,) the studies to
    refit with ``fit_glmm``, ``iterations`` (S,), ``curvature`` (S, n, n) the last
    negative-Hessian approximation of the interior fit (a start for a nested model's)."""

    theta: np.ndarray
    value: np.ndarray
    at_zero: np.ndarray
    deficiency: np.ndarray
    slopes: np.ndarray
    needs_reference: np.ndarray
    iterations: np.ndarray
    curvature: np.ndarray


# ----------------------------------------------------------------------------- the boundary
def _near(layout: ThetaLayout, theta: np.ndarray) -> np.ndarray:
    """How many dimensions each block's covariance is within ``NEAR_ZERO`` (SD scale) of
    losing, per study: (S, blocks)."""
    out = np.zeros((len(theta), len(layout.blocks)), dtype=int)
    for b, block in enumerate(layout.blocks):
        if not block.matrix:
            out[:, b] = np.abs(theta[:, block.indices[0]]) < NEAR_ZERO
            continue
        T = loading(layout.terms[block.term], theta[:, list(block.indices)])
        eig = np.linalg.eigvalsh(T @ np.swapaxes(T, 1, 2))
        out[:, b] = (np.sqrt(np.clip(eig, 0.0, None)) < NEAR_ZERO).sum(axis=1)
    return out


def _on_faces(layout: ThetaLayout, theta: np.ndarray, deficiency: np.ndarray):
    """``theta`` moved onto the faces (held SDs 0, loadings of reduced rank) and the held
    mask (S, n)."""
    out = theta.copy()
    held = np.zeros(theta.shape, dtype=bool)
    for b, block in enumerate(layout.blocks):
        rows = np.flatnonzero(deficiency[:, b])
        if not len(rows):
            continue
        if not block.matrix:
            out[rows, block.indices[0]] = 0.0
            held[rows, block.indices[0]] = True
            continue
        term = layout.terms[block.term]
        idx = list(block.indices)
        for s in rows:
            d = int(deficiency[s, b])
            out[s, idx] = theta_of(term, rank_deficient_loading(loading(term, theta[s, idx]),
                                                                d))
            held[s, idx] = [col >= term.size - d for _, col in term.entries]
    return out, held


def _face_slopes(objective: BatchObjective, theta: np.ndarray, deficiency: np.ndarray):
    """The variance-scale slope of every face (S, blocks), NaN where there is none: ``g(h) /
    2h`` for an SD, the largest eigenvalue of ``N' G N`` for a correlated term (as
    :func:`~crs_study.analysis.glmm_optimise.rank_slope`), with the nulls and the directions
    of steepest rise (per block, per study: (r, d) and (r,) arrays)."""
    layout = objective.layout
    slopes = np.full(deficiency.shape, np.nan)
    nulls: dict[tuple[int, int], np.ndarray] = {}
    directions: dict[tuple[int, int], np.ndarray] = {}
    h = _SLOPE_STEP
    for b, block in enumerate(layout.blocks):
        rows = np.flatnonzero(deficiency[:, b])
        if not len(rows):
            continue
        part = objective.subset(rows)
        if not block.matrix:
            shifted = theta[rows].copy()
            shifted[:, block.indices[0]] = h
            _, g = part.evaluate(shifted)
            slopes[rows, b] = g[:, block.indices[0]] / (2.0 * h)
            continue
        term_index = block.term
        r = layout.terms[term_index].size
        for d in np.unique(deficiency[rows, b]):
            sel = rows[deficiency[rows, b] == d]
            sub = objective.subset(sel)
            loadings = layout.loadings(theta[sel])
            T = loadings[term_index]
            _, vectors = np.linalg.eigh(T @ np.swapaxes(T, 1, 2))
            null = vectors[:, :, :d]
            extended = T.copy()
            extended[:, :, r - d:] = h * null
            loadings[term_index] = extended
            _, _, g_loadings = sub.likelihood.evaluate(theta[sel, :layout.n_fixed], loadings)
            G = g_loadings[term_index][:, :, r - d:]
            M = np.swapaxes(null, 1, 2) @ G / (2.0 * h)
            values, vectors = np.linalg.eigh(0.5 * (M + np.swapaxes(M, 1, 2)))
            slopes[sel, b] = values[:, -1]
            for k, s in enumerate(sel):
                nulls[(s, b)] = null[k]
                directions[(s, b)] = null[k] @ vectors[k, :, -1]
    return slopes, nulls, directions


def _inward(layout: ThetaLayout, theta: np.ndarray, slopes: np.ndarray, nulls: dict,
            directions: dict, sigma: float) -> np.ndarray:
    """``theta`` (S, n) on faces moved off those that rise (slope above
    ``SLOPE_TOLERANCE``) by ``sigma`` (SD scale) along their directions, as
    :func:`~crs_study.analysis.glmm_optimise.maximise` restarts inward."""
    out = theta.copy()
    for s, b in zip(*np.nonzero(np.nan_to_num(slopes, nan=-np.inf) > SLOPE_TOLERANCE),
                    strict=True):
        block = layout.blocks[b]
        idx = list(block.indices)
        out[s, idx] = inward_entries(layout, block, theta[s, idx], directions.get((s, b)),
                                     nulls.get((s, b)), sigma)
    return out


def fit_batch(objective: BatchObjective, start: np.ndarray,
              curvature: np.ndarray | None = None) -> BatchFit:
    """Maximise every study's likelihood from ``start`` (S, n), boundary checked;
    ``curvature`` (S, n, n), a negative Hessian near the start (the full model's at its
    maximum, for the reduced model), saves the first differences."""
    layout = objective.layout
    S, n = start.shape
    start = _floored(layout, start)
    held = np.zeros((S, n), dtype=bool)
    theta, value, converged, iterations, N = newton(objective, start, held, curvature)
    needs = ~converged
    at_zero = np.zeros((S, n), dtype=bool)
    blocks = len(layout.blocks)
    deficiency = np.zeros((S, blocks), dtype=int)
    slopes = np.full((S, blocks), np.nan)
    pending = np.arange(S)
    restarted = np.zeros(S, dtype=bool)
    for _ in range(2):          # the decision, and once more after a restart
        near = _near(layout, theta[pending])
        # Near a boundary Newton's method slows to a linear crawl (l ~ a s^2 + b s^4): a
        # study that has not converged there is decided on the face, where the problem is
        # regular.
        check, near = pending[near.any(axis=1)], near[near.any(axis=1)]
        if not len(check):
            break
        sub = objective.subset(check)
        b_start, b_held = _on_faces(layout, theta[check], near)
        b_theta, b_value, b_ok, b_iter, _ = newton(sub, b_start, b_held)
        iterations[check] += b_iter
        face_slopes, nulls, directions = _face_slopes(sub, b_theta, near)
        inward = (np.nan_to_num(face_slopes, nan=-np.inf) > SLOPE_TOLERANCE).any(axis=1)
        best = value[check]
        tolerance = 1e-9 * (1.0 + np.abs(best))
        take_boundary = b_ok & ~inward & (b_value >= best - tolerance)
        # a restarted study's interior end near a face is not checked against the faces
        # between (a correlated term near rank 0 but not on it): left to fit_glmm
        keep_interior = (~take_boundary & (best > b_value + tolerance) & converged[check]
                         & ~restarted[check])
        rows = check[take_boundary]
        theta[rows] = b_theta[take_boundary]
        value[rows] = b_value[take_boundary]
        at_zero[rows] = b_held[take_boundary]
        deficiency[rows] = near[take_boundary]
        slopes[rows] = face_slopes[take_boundary]
        objective.warm[rows] = sub.warm[take_boundary]
        needs[check[take_boundary]] = False
        needs[check[~take_boundary & ~keep_interior]] = True
        # The face rises inward yet the interior iteration did not settle there (it crawled
        # toward the face from elsewhere): Newton's method again from the face moved inward,
        # where ``maximise`` restarts. An interior maximum found there above the face's
        # settles the study, unless it ends near a face itself: the next round decides that.
        retry = np.flatnonzero(b_ok & inward & ~keep_interior & ~restarted[check])
        if not len(retry):
            break
        part = sub.subset(retry)
        rising = np.full(face_slopes.shape, np.nan)        # the retried studies' faces only
        rising[retry] = face_slopes[retry]
        moved = _inward(layout, b_theta, rising, nulls, directions, RESTART_SIGMAS[0])[retry]
        r_theta, r_value, r_ok, r_iter, _ = newton(part, moved, np.zeros_like(moved, bool))
        iterations[check[retry]] += r_iter
        higher = r_ok & (r_value > b_value[retry] + tolerance[retry])
        pending = check[retry[higher]]
        theta[pending], value[pending] = r_theta[higher], r_value[higher]
        converged[pending] = restarted[pending] = True
        objective.warm[pending] = part.warm[higher]
        needs[pending] = False
    return BatchFit(theta, value, at_zero, deficiency, slopes, needs, iterations, N)


def _floored(layout: ThetaLayout, start: np.ndarray) -> np.ndarray:
    """A start with every loading's diagonal at least ``MIN_START_SIGMA`` (at a zero column
    the gradient of the even likelihood is 0 whatever the data: a start there never leaves
    it)."""
    out = layout.normalised(start)
    for term, cut in zip(layout.terms, layout.slices, strict=True):
        positions = [cut.start + e for e, (i, j) in enumerate(term.entries) if i == j]
        out[:, positions] = np.maximum(out[:, positions], MIN_START_SIGMA)
    return out


# ----------------------------------------------------------------------------- per study
@dataclass(frozen=True)
class StudyFit:
    """One study of a batch as the reduction rule of :mod:`crs_study.analysis.structure`
    reads a fit: ``converged``, ``faces`` (:class:`~.glmm_result.BoundaryFace`) and the
    ``variance_components`` (as :attr:`GlmmResult.variance_components`)."""

    converged: bool
    faces: tuple
    variance_components: pd.Series


def study_fit(fit: BatchFit, objective: BatchObjective, s: int) -> StudyFit:
    """The :class:`StudyFit` of study ``s`` of ``fit``."""
    layout = objective.layout
    theta = fit.theta[s]
    faces = []
    for b, block in enumerate(layout.blocks):
        d = int(fit.deficiency[s, b])
        if not d:
            continue
        null = None
        if block.matrix:
            T = loading(layout.terms[block.term], theta[list(block.indices)])
            null = np.linalg.eigh(T @ T.T)[1][:, :d]
        held = tuple(i for i in block.indices if fit.at_zero[s, i])
        face = Face(block, held, d, float(fit.slopes[s, b]), None, null)
        faces.append(describe_face(face, layout.terms, theta, layout.n_fixed))
    return StudyFit(not fit.needs_reference[s], tuple(faces),
                    _variances(layout.terms, theta[layout.n_fixed:]))
