"""A start for the GLMM's maximisation read off the data: empirical logits and moments.

lme4 starts every loading at the identity (SDs 1, correlations 0) and ``beta`` at 0; from
there Newton's method spends most of its iterations finding the region of the maximum. The
rows here are pooled binomial cells (a participant, a symbol, a condition), so each carries
an estimate of its own linear predictor, the empirical logit (Cox 1970, The Analysis of
Binary Data, sec. 3.2; Gart & Zweifel 1967, Biometrika 54:181)::

    e_i = log((y_i + 1/2) / (m_i - y_i + 1/2)),   v_i = 1 / (y_i + 1/2) + 1 / (m_i - y_i + 1/2)

with ``v_i`` its sampling variance, each taken on the counts pooled as far as the quantity
allows (the 1/2 shrinks a logit of few trials towards 0). By weighted least squares
(weights ``1 / v_i``):

* ``beta`` from the logits of the rows pooled by their fixed design ``x_i`` on ``X``;
* for each term ``k`` and level ``l``, ``b_l`` from the residuals ``e - X beta`` of the
  level's rows pooled by (``x_i``, ``z_ik``) (over the other terms' levels) on the term's
  design ``Z_k``, with sampling covariance ``V_l = (Z_l' W Z_l)^-1``;
* ``Sigma_k = cov_l(b_l) - mean_l(V_l)`` (the spread of the levels' coefficients less the
  part their noise explains: the method of moments), diagonal for an uncorrelated term, its
  eigenvalues floored at ``MIN_START_SD^2`` (a start on a boundary never leaves it), and
  ``T_k`` its Cholesky factor.

Only the start changes: the maximum is decided by the likelihood, and a term whose levels
cannot be estimated this way (a level without every column's rows, too few levels) starts
at lme4's identity.
"""

from __future__ import annotations

import numpy as np

from crs_study.analysis.glmm_data import row_codes
from crs_study.analysis.glmm_terms import ThetaLayout, theta_of

#: Smallest SD (logit scale) of a start's loading: away from the boundary, where the
#: gradient in a zero column vanishes whatever the data.
MIN_START_SD = 0.1
#: A level's coefficients enter the moments only when its design is this well conditioned.
_MIN_RCOND = 1e-8


class MomentStart:
    """The start of any responses on one design (module docstring): the poolings (which
    rows share ``x_i``, which share a level, ``z_ik`` and ``x_i``) are the design's, found
    once; a call reads the logits of one study's successes. ``terms`` are the likelihood's
    term rows (``codes``, ``levels``, ``Z``), in the layout's order."""

    def __init__(self, X: np.ndarray, trials: np.ndarray, terms, layout: ThetaLayout):
        self.m = np.asarray(trials, float)
        self.layout = layout
        self.fixed = _Pooling(X, self.m)
        self.terms = []            # (pooling, levels, r) per term
        for term_rows in terms:
            self.terms.append((_Pooling(np.column_stack([term_rows.codes, term_rows.Z, X]),
                                        self.m), term_rows.levels, term_rows.Z.shape[1]))

    def __call__(self, successes: np.ndarray) -> np.ndarray:
        """``(beta, theta_1, ...)`` for one study's successes."""
        y = np.asarray(successes, float)
        layout = self.layout
        e, weight = self.fixed.logits(y)
        beta = _weighted_fit(self.fixed.keys, e, weight)
        if beta is None:
            return np.r_[np.zeros(self.fixed.keys.shape[1]), layout.start()]
        parts = [beta]
        for (pooling, levels, r), term in zip(self.terms, layout.terms, strict=True):
            keys = pooling.keys
            e, weight = pooling.logits(y)
            sigma = _level_moments(keys[:, 0].astype(int), levels, keys[:, 1:1 + r],
                                   e - keys[:, 1 + r:] @ beta, weight)
            if sigma is None:
                parts.append(theta_of(term, np.eye(term.size)))
                continue
            if r == 1:       # its one eigenvalue floored, its Cholesky factor the root
                parts.append(np.sqrt(np.maximum(sigma[0], MIN_START_SD ** 2)))
                continue
            if not term.correlated:
                sigma = np.diag(np.diag(sigma))
            values, vectors = np.linalg.eigh(sigma)
            sigma = (vectors * np.maximum(values, MIN_START_SD ** 2)) @ vectors.T
            parts.append(theta_of(term, np.linalg.cholesky(sigma)))
        return np.concatenate(parts)


def moment_start(X: np.ndarray, successes: np.ndarray, trials: np.ndarray, terms,
                 layout: ThetaLayout) -> np.ndarray:
    """``(beta, theta_1, ...)`` of one study (:class:`MomentStart`)."""
    return MomentStart(X, trials, terms, layout)(successes)


class _Pooling:
    """The distinct rows of ``keys`` (``row_codes``) and, per call, the empirical logit of
    each one's pooled counts with that logit's inverse sampling variance: pooled, a logit
    is less shrunk by the 1/2."""

    def __init__(self, keys: np.ndarray, trials: np.ndarray):
        self.inverse, self.keys = row_codes(np.asarray(keys, float))
        self.m = np.bincount(self.inverse, trials)

    def logits(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y_, m_ = np.bincount(self.inverse, y, minlength=len(self.m)), self.m
        e = np.log((y_ + 0.5) / (m_ - y_ + 0.5))
        return e, 1.0 / (1.0 / (y_ + 0.5) + 1.0 / (m_ - y_ + 0.5))


def _weighted_fit(X: np.ndarray, e: np.ndarray, weight: np.ndarray) -> np.ndarray | None:
    root = np.sqrt(weight)
    coef, _, rank, _ = np.linalg.lstsq(X * root[:, None], e * root, rcond=None)
    return coef if rank == X.shape[1] and np.all(np.isfinite(coef)) else None


def _level_moments(codes: np.ndarray, levels: int, Z: np.ndarray, residual: np.ndarray,
                   weight: np.ndarray) -> np.ndarray | None:
    """``cov_l(b_l) - mean_l(V_l)`` over the levels whose design is well conditioned."""
    r = Z.shape[1]
    cells = codes[:, None] * r + np.arange(r)                       # (n, r)
    ZWZ = np.bincount((cells[:, :, None] * r + np.arange(r)).ravel(),
                      (weight[:, None, None] * Z[:, :, None] * Z[:, None, :]).ravel(),
                      minlength=levels * r * r).reshape(levels, r, r)
    ZWe = np.bincount(cells.ravel(), ((weight * residual)[:, None] * Z).ravel(),
                      minlength=levels * r).reshape(levels, r)
    if r == 1:      # a 1 x 1 block is well conditioned unless it is 0
        conditioned = ZWZ[:, 0, 0] > 0
    else:
        conditioned = np.linalg.cond(ZWZ) < 1.0 / _MIN_RCOND
    if conditioned.sum() < r + 2:
        return None
    inverse = 1.0 / ZWZ[conditioned] if r == 1 else np.linalg.inv(ZWZ[conditioned])
    b = (inverse @ ZWe[conditioned][:, :, None])[:, :, 0]
    # numpy.cov's sample covariance, without its overhead (a sum over n is numpy.mean's sum)
    centred = b - b.sum(axis=0) / len(b)
    return centred.T @ centred * (1.0 / (len(b) - 1)) - inverse.sum(axis=0) / len(inverse)
