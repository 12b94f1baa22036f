"""The Laplace log-likelihood of a binomial GLMM with crossed, vector-valued random effects.

The model (lme4's, Bates, Maechler, Bolker & Walker 2015, J. Stat. Softw. 67(1), eqs. 2-4 and
sec. 3 with the GLMM weights of sec. 5)::

    y_i ~ Binomial(m_i, p_i),   logit p_i = x_i' beta + sum_k z_ik' T_k u_{k, g_k(i)},
    u ~ N(0, I)

for terms ``k`` (lme4's ``(1 + condition | participant)``): ``g_k(i)`` the level of row ``i``'s
grouping factor, ``z_ik`` its row of the term's design (the intercept and the condition
contrasts), ``T_k`` the term's loading (``Sigma_k = T_k T_k'``; any real ``r x r`` matrix here,
lower-triangular or diagonal in a fit, see :mod:`crs_study.analysis.glmm_terms`). With ``a_i``
the row of ``Z Lambda`` (its nonzeros ``alpha_ik = T_k' z_ik`` at the positions of row ``i``'s
levels), the Laplace approximation of the marginal log-likelihood is::

    l(beta, T) = h(u*) - log det H / 2,   h(u) = sum_i kernel(y_i, m_i, eta_i) - |u|^2 / 2,
    H = sum_i w_i a_i a_i' + I,   w_i = m_i p_i (1 - p_i),

``u*`` the conditional mode (penalised IRLS: Newton's method on ``h``, step-halved where it
would fall) and ``kernel = y eta - m log(1 + e^eta)`` (binomial constants left to the caller).

**The solve.** ``H`` is split by the term with the most random effects (``L``: its block is
block-diagonal, one ``r_L x r_L`` block ``A_l`` per level, since each row has one level of
it) and the others (``R``: a dense block, the symbols' effects): ``H = [[A, B], [B', C]]``,
solved through the Schur complement ``S = C - B' A^-1 B`` (Golub & Van Loan 2013, Matrix
Computations, sec. 3.2.10): ``log det H = sum_l log det A_l + log det S``. No dense ``q x q``
work: the participants' blocks stay small whatever their number.

**The data enter through sums only.** ``a_i = Lambda' z_i``, so every sum over rows is a
product of the weights with a fixed sparse matrix of the design (scipy.sparse), the loadings
applied to the small result: the score ``Lambda' Z' r``, ``H``'s blocks ``I + T' (sum_i w_i
z_i z_i') T``, and, read the other way, ``eta = X beta + Z (Lambda u)`` and the quadratic forms
``d_i = z_i' (Lambda H^-1 Lambda') z_i``. No array has more than one number per row and study.

**The gradient** is exact and costs one more solve, whatever the number of parameters. For
any parameter ``t``, by the implicit function theorem at ``g(u*) = dh/du = 0``::

    dl/dt = sum_i rho_i d eta_i/dt |_u  -  sum_i w_i (d a_i/dt)' H^-1 a_i
            - sum_i r_i s' (d a_i/dt) / 2,
    rho_i = r_i - q_i / 2 + w_i (s' a_i) / 2,  q_i = w'_i d_i,  d_i = a_i' H^-1 a_i,
    s = H^-1 sum_i q_i a_i,

``r_i = y_i - m_i p_i``, ``w'_i = w_i (1 - 2 p_i)`` (from ``dl/dt = dh/dt - tr(H^-1 dH/dt)/2``
with ``du*/dt = H^-1 dg/dt``; the one solve for ``s`` replaces one per parameter, the adjoint
of that linear system). For ``beta`` that is ``X' rho``; for the whole loading of term ``k``,
``dl/dT_k = Z_k' Q_k`` with row ``i`` of ``Q_k`` equal to ``rho_i u_{k,g} - w_i (H^-1 a_i)_k -
r_i s_{k,g} / 2``. Only the entries of ``H^-1`` at each row's own pairs of positions enter
(``d_i`` and ``(H^-1 a_i)_k``), read off the Schur pieces.

Every array carries a leading axis of ``S`` response vectors sharing one design (a power
simulation's or a bootstrap's studies; ``S = 1`` for one fit), each with its own parameters:
the same likelihood for all of them in one pass of array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from crs_study.analysis.glmm_irls import (
    StudyBatch,
)


@dataclass(frozen=True)
class TermRows:
    """One term as the rows meet it: the level of each row (``codes``, 0..levels-1) and the
    term's design ``Z`` (n, r)."""

    codes: np.ndarray
    levels: int
    Z: np.ndarray

    @property
    def size(self) -> int:
        return self.Z.shape[1]


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` over the last two axes (broadcast), the inner sum written out when it is
    short: numpy's matmul calls BLAS once per tiny matrix, thousands of calls here."""
    k = A.shape[-1]
    if k > 3:
        return A @ B
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for j in range(1, k):
        out = out + A[..., :, j:j + 1] * B[..., j:j + 1, :]
    return out


def _outer_contract(F: np.ndarray, E: np.ndarray) -> np.ndarray:
    """``F @ E'`` over the last two axes for stacks of short, wide blocks (..., r, q)."""
    return (F[..., :, None, :] * E[..., None, :, :]).sum(axis=-1)


def small_inverse(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses and log-determinants of a stack of small symmetric positive-definite blocks
    (..., r, r): closed forms for r = 1 and 2, LAPACK beyond."""
    r = A.shape[-1]
    if r == 1:
        return 1.0 / A, np.log(A[..., 0, 0])
    if r == 2:
        a, b, d = A[..., 0, 0], A[..., 0, 1], A[..., 1, 1]
        det = a * d - b * b
        inv = np.empty_like(A)
        inv[..., 0, 0], inv[..., 1, 1] = d / det, a / det
        inv[..., 0, 1] = inv[..., 1, 0] = -b / det
        return inv, np.log(det)
    L = np.linalg.cholesky(A)
    logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
    return np.linalg.inv(A), logdet


class _Sums:
    """A fixed sparse map between rows and bins, ``k`` entries a row: ``to_bins(v)`` sums
    ``v`` (S, n) into the bins, ``to_rows(b)`` reads bins (S, bins) back row by row (the
    transpose). Each output of a study depends on that study's numbers alone, in a fixed
    order. Rows are read by a gather (every row has its ``k`` entries); bins are filled by
    ``np.bincount`` for a single study and by a sparse product for many (scipy's call
    overhead is what one study's sums cost)."""

    def __init__(self, rows: np.ndarray, bins: np.ndarray, values: np.ndarray, n: int,
                 size: int):
        k = len(rows) // n
        order = np.argsort(rows, kind="stable")
        self.row_bins = bins[order].reshape(n, k)
        self.row_values = values[order].reshape(n, k)
        self.flat_rows, self.flat_bins = rows[order], bins[order]
        self.flat_values = values[order]
        self.to_bins_matrix = sp.csr_matrix((values, (bins, rows)), shape=(size, n))
        self.size = size

    def to_bins(self, v: np.ndarray) -> np.ndarray:
        if len(v) == 1:
            return np.bincount(self.flat_bins, v[0, self.flat_rows] * self.flat_values,
                               minlength=self.size)[None]
        return np.asarray(self.to_bins_matrix @ v.T).T

    def to_rows(self, b: np.ndarray) -> np.ndarray:
        gathered = b[:, self.row_bins]                  # (S, n, k); summed in a fixed order
        out = gathered[..., 0] * self.row_values[:, 0]
        for j in range(1, self.row_bins.shape[1]):
            out += gathered[..., j] * self.row_values[:, j]
        return out


def _outer_sums(n: int, left_pos: np.ndarray, left_z: np.ndarray, right_pos: np.ndarray,
                right_z: np.ndarray, right_size: int, size: int) -> _Sums:
    """The map of ``sum_i v_i z_ia z_ib`` into bins ``left_pos[i, a] * right_size +
    right_pos[i, b]``."""
    a, b = left_pos.shape[1], right_pos.shape[1]
    rows = np.repeat(np.arange(n), a * b)
    bins = (left_pos[:, :, None] * right_size + right_pos[:, None, :]).ravel()
    values = (left_z[:, :, None] * right_z[:, None, :]).ravel()
    return _Sums(rows, bins, values, n, size)


@dataclass(frozen=True)
class _Loadings:
    """Every term's loading (S, r_k, r_k), indexed by term, with the rest terms' applied as
    one block-diagonal matrix ``Lambda_R`` (S, qR, qR; None without rest terms), built once
    per evaluation and shared by every product of it."""

    terms: list
    rest: np.ndarray | None

    def __getitem__(self, k: int) -> np.ndarray:
        return self.terms[k]

    def take(self, index) -> _Loadings:       # the studies ``index``
        return _Loadings([T[index] for T in self.terms],
                         None if self.rest is None else self.rest[index])


class LaplaceLikelihood(StudyBatch):
    """``l(beta, T_1..T_K)`` and its exact gradient for ``S`` response vectors at once.

    ``X`` (n, p) the fixed design of the (pooled) rows, ``trials`` (n,), ``Y`` (S, n) the
    successes, ``terms`` the random terms' rows (:class:`TermRows`). :meth:`evaluate` takes
    ``beta`` (S, p) and one loading (S, r_k, r_k) per term. The conditional modes of each
    study are kept as the warm start of its next evaluation (``u``).
    """

    def __init__(self, X: np.ndarray, trials: np.ndarray, Y: np.ndarray,
                 terms: list[TermRows]):
        super().__init__(X, trials, Y, terms)
        self.large = int(np.argmax([t.levels * t.size for t in terms]))
        self.rest = [k for k in range(len(terms)) if k != self.large]
        big = terms[self.large]
        self.n_large, self.r_large = big.levels, big.size
        self.q_large = big.levels * big.size
        n = len(self.m)
        self.rest_blocks = []        # (term index, slice of the rest positions)
        positions, position = [], 0
        for k in self.rest:
            t = terms[k]
            positions.append(position + t.codes[:, None] * t.size + np.arange(t.size))
            self.rest_blocks.append((k, slice(position, position + t.levels * t.size)))
            position += t.levels * t.size
        self.q_rest = position
        self.rest_rows, self.rest_cols, self.rest_source = self._rest_positions()
        self.q = self.q_large + self.q_rest
        rL, nL, qR = self.r_large, self.n_large, self.q_rest
        large_pos = big.codes[:, None] * rL + np.arange(rL)                  # (n, rL)
        self.large_sums = _Sums(np.repeat(np.arange(n), rL), large_pos.ravel(),
                                big.Z.ravel(), n, self.q_large)
        self.A_sums = _outer_sums(n, big.codes[:, None] * rL + np.arange(rL), big.Z,
                                  np.tile(np.arange(rL), (n, 1)), big.Z, rL, nL * rL * rL)
        if qR:
            rest_pos = np.concatenate(positions, axis=1)
            rest_z = np.concatenate([terms[k].Z for k in self.rest], axis=1)
            self.rest_sums = _Sums(np.repeat(np.arange(n), rest_pos.shape[1]),
                                   rest_pos.ravel(), rest_z.ravel(), n, qR)
            self.B_sums = _outer_sums(n, large_pos, big.Z, rest_pos, rest_z, qR, nL * rL * qR)
            self.C_sums = _outer_sums(n, rest_pos, rest_z, rest_pos, rest_z, qR, qR * qR)
        self.u = np.zeros((len(self.Y), self.q))

    def _rest_positions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each rest loading's entries sit in ``Lambda_R`` (rows, columns) and which
        entry of the terms' flattened loadings each is."""
        rows, cols, source, offset = [], [], [], 0
        for k, cut in self.rest_blocks:
            t = self.terms[k]
            level, i, j = np.meshgrid(np.arange(t.levels), np.arange(t.size),
                                      np.arange(t.size), indexing="ij")
            rows.append((cut.start + level * t.size + i).ravel())
            cols.append((cut.start + level * t.size + j).ravel())
            source.append((offset + i * t.size + j).ravel())
            offset += t.size * t.size
        if not rows:
            return (np.zeros(0, dtype=int),) * 3
        return np.concatenate(rows), np.concatenate(cols), np.concatenate(source)

    # ------------------------------------------------------------------ pieces
    def _split(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A q-vector per study as (large part (S, nL, rL), rest part (S, qR))."""
        return v[:, :self.q_large].reshape(len(v), self.n_large, self.r_large), \
            v[:, self.q_large:]

    def _loadings(self, loadings: list[np.ndarray]) -> _Loadings:
        """The loadings with ``Lambda_R`` (S, qR, qR), each rest term's loading repeated
        along its diagonal once per level: one BLAS product applies them all."""
        if not self.q_rest:
            return _Loadings(loadings, None)
        S = len(loadings[self.large])
        out = np.zeros((S, self.q_rest, self.q_rest))
        values = np.concatenate([loadings[k].reshape(S, -1) for k in self.rest], axis=1)
        out[:, self.rest_rows, self.rest_cols] = values[:, self.rest_source]
        return _Loadings(loadings, out)

    def _effects(self, u: np.ndarray, loadings) -> tuple[np.ndarray, np.ndarray]:
        """``Lambda u`` in the design's space: (S, nL * rL) and (S, qR)."""
        uL, uR = self._split(u)
        bL = _mm(uL, np.swapaxes(loadings[self.large], 1, 2)).reshape(len(u), -1)
        if not self.q_rest:
            return bL, uR
        return bL, (loadings.rest @ uR[:, :, None])[:, :, 0]

    def _linear(self, offset, u, loadings) -> np.ndarray:
        """``X beta + Z Lambda u`` per row (S, n)."""
        bL, bR = self._effects(u, loadings)
        eta = offset + self.large_sums.to_rows(bL)
        return eta + self.rest_sums.to_rows(bR) if self.q_rest else eta

    def _adjoint(self, v: np.ndarray, loadings) -> np.ndarray:
        """``Lambda' Z' v`` (S, q) for row values ``v`` (S, n)."""
        S = len(v)
        gL = self.large_sums.to_bins(v).reshape(S, self.n_large, self.r_large)
        gL = _mm(gL, loadings[self.large]).reshape(S, -1)
        if not self.q_rest:
            return gL
        gR = (self.rest_sums.to_bins(v)[:, None, :] @ loadings.rest)[:, 0]
        return np.concatenate([gL, gR], axis=1)

    def _take(self, loadings, index) -> _Loadings:
        return loadings.take(index)

    def _newton_step(self, w, rhs, loadings) -> np.ndarray:
        return _Factor(self, w, loadings).solve(rhs)

    # ------------------------------------------------------------------ objective
    def _design(self, loadings: list[np.ndarray]) -> _Loadings:
        return self._loadings(loadings)

    def _curvature(self, w, loadings, full: bool):
        """``(log det H, the factorisation)`` (:class:`_Factor`: its inverse's blocks only
        when ``full``)."""
        factor = _Factor(self, w, loadings, full=full)
        return factor.logdet, factor

    def _gradient(self, u, p, w, loadings, factor: _Factor):
        """The exact gradient (module docstring), every sum over rows a sparse product."""
        S = len(u)
        r = self.Y - self.m * p
        d = factor.row_quadratic_forms()                  # a_i' H^-1 a_i
        q = w * (1.0 - 2.0 * p) * d
        s = factor.solve(self._adjoint(q, loadings))
        sa = self._linear(np.zeros_like(q), s, loadings)   # a_i' s
        rho = r - 0.5 * q + 0.5 * w * sa
        g_beta = (self.X.T @ rho[:, :, None])[:, :, 0]
        grads: list[np.ndarray] = [None] * len(self.terms)
        wz = factor.weighted_inverse_blocks()              # sum_i w_i z_i (H^-1 a_i)_k
        uL, uR = self._split(u)
        sL, sR = self._split(s)
        big = self.large_sums
        rho_L = big.to_bins(rho).reshape(S, self.n_large, self.r_large)
        r_L = big.to_bins(r).reshape(S, self.n_large, self.r_large)
        grads[self.large] = (np.swapaxes(rho_L, 1, 2) @ uL - wz[self.large]
                             - 0.5 * np.swapaxes(r_L, 1, 2) @ sL)
        if self.q_rest:
            rho_R, r_R = self.rest_sums.to_bins(rho), self.rest_sums.to_bins(r)
            for k, cut in self.rest_blocks:
                t = self.terms[k]

                def blocks(v, t=t, cut=cut):
                    return v[:, cut].reshape(S, t.levels, t.size)

                grads[k] = (np.swapaxes(blocks(rho_R), 1, 2) @ blocks(uR) - wz[k]
                            - 0.5 * np.swapaxes(blocks(r_R), 1, 2) @ blocks(sR))
        return g_beta, grads


class _Factor:
    """``H = [[A, B], [B', C]]`` of each study at weights ``w`` (module docstring): solves,
    ``log det H``, and (``full``) what the gradient needs of ``H^-1``."""

    def __init__(self, lik: LaplaceLikelihood, w, loadings, full: bool = False):
        self.lik, self.loadings = lik, loadings
        S = len(w)
        rL, nL, qR = lik.r_large, lik.n_large, lik.q_rest
        TL = loadings[lik.large][:, None]                                  # (S, 1, rL, rL)
        TLt = np.swapaxes(TL, 2, 3)
        self.WL = lik.A_sums.to_bins(w).reshape(S, nL, rL, rL)            # sum w z z'
        A = _mm(_mm(TLt, self.WL), TL) + np.eye(rL)
        self.A_inv, logdet_A = small_inverse(A)
        self.logdet = logdet_A.sum(axis=1)
        self.E = None
        if qR == 0:
            return
        self.WB = lik.B_sums.to_bins(w).reshape(S, nL, rL, qR)
        self.BL = _mm(TLt, self.WB)                                       # T_L' sum w zL zR'
        self.LR = LR = loadings.rest                                      # Lambda_R
        B = (self.BL.reshape(S, nL * rL, qR) @ LR).reshape(S, nL, rL, qR)
        self.WC = lik.C_sums.to_bins(w).reshape(S, qR, qR)
        self.WC_LR = self.WC @ LR
        C = np.swapaxes(LR, 1, 2) @ self.WC_LR + np.eye(qR)
        self.E = _mm(self.A_inv, B)                                        # (S, nL, rL, qR)
        schur = C - np.swapaxes(B.reshape(S, nL * rL, qR), 1, 2) @ self.E.reshape(
            S, nL * rL, qR)
        chol = np.linalg.cholesky(schur)
        self.logdet = self.logdet + 2.0 * np.log(
            np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
        self.schur = schur
        self.S_inv = np.linalg.inv(schur) if full else None
        self.F = None if self.S_inv is None else (
            self.E.reshape(S, nL * rL, qR) @ self.S_inv).reshape(S, nL, rL, qR)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``H^-1 b`` for ``b`` (S, q)."""
        lik = self.lik
        S = len(b)
        bL, bR = lik._split(b)
        if self.E is None:
            return _mm(self.A_inv, bL[..., None])[..., 0].reshape(S, -1)
        rhs = bR - np.einsum("slar,sla->sr", self.E, bL)
        if self.S_inv is None:
            xR = np.linalg.solve(self.schur, rhs[..., None])[..., 0]
        else:
            xR = (self.S_inv @ rhs[..., None])[..., 0]
        xL = _mm(self.A_inv, bL[..., None])[..., 0] - (
            self.E.reshape(S, -1, self.E.shape[-1]) @ xR[:, :, None]).reshape(bL.shape)
        return np.concatenate([xL.reshape(S, -1), xR], axis=1)

    def _P_LL(self) -> np.ndarray:
        """The large term's diagonal blocks of ``H^-1``: ``A^-1 + E S^-1 E'``."""
        if self.E is None:
            return self.A_inv
        return self.A_inv + _outer_contract(self.F, self.E)

    def row_quadratic_forms(self) -> np.ndarray:
        """``d_i = a_i' H^-1 a_i = z_i' (Lambda H^-1 Lambda') z_i`` for every row (S, n)."""
        lik, loadings = self.lik, self.loadings
        S = len(self.A_inv)
        TL = loadings[lik.large][:, None]
        K_LL = _mm(_mm(TL, self._P_LL()), np.swapaxes(TL, 2, 3))
        d = lik.A_sums.to_rows(K_LL.reshape(S, -1))
        if self.E is None:
            return d
        nL, rL, qR = lik.n_large, lik.r_large, lik.q_rest
        LRt = np.swapaxes(self.LR, 1, 2)
        K_LR = -(_mm(TL, self.F).reshape(S, nL * rL, qR) @ LRt)
        K_RR = self.LR @ self.S_inv @ LRt
        return (d + 2.0 * lik.B_sums.to_rows(K_LR.reshape(S, -1))
                + lik.C_sums.to_rows(K_RR.reshape(S, -1)))

    def weighted_inverse_blocks(self) -> list[np.ndarray]:
        """Per term ``k``: ``sum_i w_i z_ik (H^-1 a_i)_k'`` (S, r_k, r_k), the diagonal
        blocks of ``W_z Lambda H^-1`` summed over the term's levels."""
        lik, loadings = self.lik, self.loadings
        S = len(self.A_inv)
        TL = loadings[lik.large][:, None]
        out: list[np.ndarray] = [None] * len(lik.terms)
        large = _mm(_mm(self.WL, TL), self._P_LL()).sum(axis=1)
        if self.E is None:
            out[lik.large] = large
            return out
        nL, rL, qR = lik.n_large, lik.r_large, lik.q_rest
        WBT = (self.WB.reshape(S, nL * rL, qR) @ self.LR).reshape(S, nL, rL, qR)
        out[lik.large] = large - _outer_contract(WBT, self.F).sum(axis=1)
        # rest: W_RR T_R S^-1 + W_RL T_L P_LR, its diagonal blocks per term
        M = (self.WC_LR @ self.S_inv
             - np.swapaxes(self.BL.reshape(S, nL * rL, qR), 1, 2)
             @ self.F.reshape(S, nL * rL, qR))
        for k, cut in lik.rest_blocks:
            t = lik.terms[k]
            block = M[:, cut, cut].reshape(S, t.levels, t.size, t.levels, t.size)
            out[k] = np.diagonal(block, axis1=1, axis2=3).sum(axis=-1)
        return out
