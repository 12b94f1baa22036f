"""The Laplace log-likelihood of a binomial GLMM with few random effects, ``H`` formed whole.

The same function as :class:`~crs_study.analysis.glmm_laplace.LaplaceLikelihood` (the model,
the penalised IRLS with its stopping rules, the exact gradient: see that module's
docstring), computed another way. With ``A = Z Lambda`` the ``n x q`` design of the
spherical random effects (row ``i`` is ``a_i'``)::

    H = A' W A + I,    log det H = 2 sum_j log L_jj   (H = L L', Cholesky)

formed whole: ``q x q`` for ``q`` random effects (12 participants and 10 symbols: 22). There
the Schur complement's split into per-level blocks saves nothing and costs a few dozen
array operations per solve, each a Python call on a few hundred numbers; the whole matrix
costs one sum and one factorisation (Golub & Van Loan 2013, Matrix Computations, sec.
4.2), ``O(q^3)``, so it is chosen only for small ``q`` (:data:`DENSE_MAX_Q`).

``A`` itself is never formed: row ``i`` has ``R = sum_k r_k`` nonzeros (one level of each
term), so ``A u``, ``A' v`` and ``A' W A`` are gathers and ``bincount`` sums over ``n R``
(``n R^2``) entries, with no BLAS call on an ``n``-long axis (OpenBLAS threads those, and
on a shared machine its threads spin). The gradient's row quantities read off the entries of
``H^-1`` at each row's own positions ``P_i``: ``G_i = H^-1[P_i, P_i]`` (R x R), so
``(H^-1 a_i)`` at ``P_i`` is ``G_i V_i`` and ``d_i = a_i' H^-1 a_i = V_i' G_i V_i`` (``V_i``
the nonzeros of ``a_i``).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from crs_study.analysis.glmm_irls import (
    StudyBatch,
)
from crs_study.analysis.glmm_laplace import TermRows

#: Most random effects (``q``) of a model fitted with ``H`` whole; beyond, the Schur
#: complement's per-level blocks (``glmm_laplace``) cost less. Measured (CPU time, the
#: machine shared): 50 participants and 10 symbols (q = 60) took 5x longer whole, LAPACK's
#: factorisations of 60 x 60 running threaded; 12 and 10 (q = 22) a third less.
DENSE_MAX_Q = 32


def solve(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``H^-1 b`` per study for positive-definite ``H`` (S, q, q), ``b`` (S, q) or (S, q, k)
    (LAPACK's ``dposv``, Cholesky: a tenth of ``numpy.linalg.solve``'s call overhead on
    one small matrix); NaN where ``H`` is not positive definite (a diverged point)."""
    out = np.empty(b.shape)
    for s in range(len(H)):
        _, out[s], info = lapack.dposv(H[s], b[s])
        if info:
            out[s] = np.nan
    return out


def factor(H: np.ndarray, inverse: bool, eye: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray | None]:
    """``log det H`` per study (S,) from the Cholesky factor, and with ``inverse`` ``H^-1``
    (S, q, q): LAPACK's ``dposv`` on the identity gives the factor and the inverse in one
    call (a third of ``numpy.linalg.inv``'s time on one small matrix); raises
    ``LinAlgError``, as ``numpy.linalg.cholesky``, where ``H`` is not positive definite.
    ``eye``: the q x q identity, when the caller keeps one (LAPACK does not overwrite it)."""
    S, q = H.shape[:2]
    diagonals = np.empty((S, q))
    out = np.empty(H.shape) if inverse else None
    eye = np.eye(q) if eye is None else eye
    for s in range(S):
        if inverse:
            chol, out[s], info = lapack.dposv(H[s], eye)
        else:
            chol, info = lapack.dpotrf(H[s])
        if info:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        diagonals[s] = np.diagonal(chol)
    return 2.0 * np.log(diagonals).sum(axis=1), out


class DenseLaplace(StudyBatch):
    """``l(beta, T_1..T_K)`` and its exact gradient for ``S`` response vectors at once, as
    :class:`~crs_study.analysis.glmm_laplace.LaplaceLikelihood` (same arguments, same
    :meth:`evaluate`, :meth:`subset` and warm starts ``u``), with ``H`` formed whole.

    Row ``i`` of ``A`` has ``R = sum_k r_k`` nonzeros, at positions ``P_i`` (term ``k``'s:
    its level's effects) with values ``V_i`` (term ``k``'s: ``T_k' z_ik``), so every product
    with ``A`` is a gather or a ``bincount`` over ``n R`` (``H``: ``n R^2``) entries, and
    only the factorisation of ``H`` is dense: no BLAS call on an ``n``-long axis.
    """

    def __init__(self, X: np.ndarray, trials: np.ndarray, Y: np.ndarray,
                 terms: list[TermRows]):
        super().__init__(X, trials, Y, terms)
        positions, self.columns, start = [], [], 0
        for t in terms:
            positions.append(start + t.codes[:, None] * t.size + np.arange(t.size))
            self.columns.append(slice(sum(c.stop - c.start for c in self.columns),
                                      sum(c.stop - c.start for c in self.columns) + t.size))
            start += t.levels * t.size
        self.q = start
        self.P = np.concatenate(positions, axis=1)                       # (n, R)
        self.diagonal = all(t.size == 1 for t in terms)
        self.Z = np.concatenate([t.Z for t in terms], axis=1)            # (n, R)
        self.pairs = (self.P[:, :, None] * self.q + self.P[:, None, :]).ravel()  # (n R R)
        self.eye = np.eye(self.q)
        self.u = np.zeros((len(self.Y), self.q))

    def values(self, loadings: list[np.ndarray]) -> np.ndarray:
        """``V`` (S, n, R): row ``i``'s nonzeros of ``A``, term ``k``'s ``T_k' z_ik``."""
        if self.diagonal:
            return self.Z * np.concatenate([T[:, 0] for T in loadings], axis=1)[:, None, :]
        return np.concatenate([np.einsum("nb,sba->sna", t.Z, T)
                               for t, T in zip(self.terms, loadings, strict=True)], axis=2)

    def _bins(self, flat: np.ndarray, bins: np.ndarray, size: int) -> np.ndarray:
        """Sums of ``flat`` (S, n k) into ``size`` bins per study, bins ``bins`` (n k)."""
        S = len(flat)
        if S == 1:
            return np.bincount(bins, flat[0], minlength=size)[None]
        index = (np.arange(S)[:, None] * size + bins).ravel()
        return np.bincount(index, flat.ravel(), minlength=S * size).reshape(S, size)

    def _times(self, u: np.ndarray, V: np.ndarray) -> np.ndarray:
        """``A u`` (S, n)."""
        return np.einsum("snr,snr->sn", V, u[:, self.P])

    def _adjoint(self, v: np.ndarray, V: np.ndarray) -> np.ndarray:
        """``A' v`` (S, q) for row values ``v`` (S, n)."""
        return self._bins((v[:, :, None] * V).reshape(len(v), -1), self.P.ravel(), self.q)

    def _H(self, w: np.ndarray, V: np.ndarray) -> np.ndarray:
        """``A' W A + I`` (S, q, q)."""
        S = len(w)
        # (w V_a) V_b: the weighted row first, three axes, then the one four-axis product
        outer = ((w[:, :, None] * V)[:, :, :, None] * V[:, :, None, :]).reshape(S, -1)
        return self._bins(outer, self.pairs, self.q * self.q).reshape(S, self.q, self.q) \
            + self.eye

    def _linear(self, offset, u, V) -> np.ndarray:
        """``X beta + A u`` (S, n)."""
        return offset + self._times(u, V)

    def _newton_step(self, w, rhs, V) -> np.ndarray:
        return solve(self._H(w, V), rhs)

    def _design(self, loadings: list[np.ndarray]) -> np.ndarray:
        return self.values(loadings)

    def _curvature(self, w, V, full: bool):
        """``(log det H, H^-1)`` (:func:`factor`; ``H^-1`` only when ``full``)."""
        return factor(self._H(w, V), full, self.eye)

    def _gradient(self, u, p, w, V, H_inv):
        """The exact gradient (``glmm_laplace``'s docstring) from ``G_i = H^-1[P_i, P_i]``:
        ``(H^-1 a_i)`` at row ``i``'s positions is ``G_i V_i``, ``d_i = V_i' G_i V_i``."""
        r = self.Y - self.m * p
        S, (n, R) = len(H_inv), self.P.shape      # G (S, n, R, R): one gather on the flat H^-1
        G = H_inv.reshape(S, -1)[:, self.pairs].reshape(S, n, R, R)
        GV = G[..., 0] * V[:, :, None, 0]      # R is a few terms' sizes: a sum beats einsum
        for b in range(1, V.shape[2]):
            GV += G[..., b] * V[:, :, None, b]
        q = w * (1.0 - 2.0 * p) * np.einsum("sna,sna->sn", GV, V)
        s = (H_inv @ self._adjoint(q, V)[:, :, None])[:, :, 0]
        rho = r - 0.5 * q + 0.5 * w * self._times(s, V)
        g_beta = (self.X.T @ rho[:, :, None])[:, :, 0]
        Q = (rho[:, :, None] * u[:, self.P] - w[:, :, None] * GV
             - 0.5 * r[:, :, None] * s[:, self.P])                # (S, n, R)
        if self.diagonal:      # intercepts (r_k = 1): every term's sum at once
            sums = np.einsum("nr,snr->sr", self.Z, Q)
            return g_beta, [sums[:, k, None, None] for k in range(len(self.terms))]
        return g_beta, [np.einsum("na,snb->sab", t.Z, Q[:, :, cut])
                        for t, cut in zip(self.terms, self.columns, strict=True)]
