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
from scipy.special import expit

#: Penalised IRLS stops when no coordinate of u moves more than this.
INNER_TOL = 1e-11
INNER_MAXITER = 60
#: Newton steps longer than this (in any coordinate of u) are checked for ascent first;
#: shorter ones lie where Newton's method on this strongly concave function converges.
FULL_STEP = 0.05


def kernel(y: np.ndarray, m: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """``y eta - m log(1 + e^eta)``, elementwise and stable."""
    return y * eta - m * np.logaddexp(0.0, eta)


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


def scatter(values: np.ndarray, index: np.ndarray, size: int) -> np.ndarray:
    """Sums of ``values`` (S, n, ...) into ``size`` bins per study by ``index`` (n, ...)."""
    S = values.shape[0]
    flat = (index[None] + (size * np.arange(S)).reshape((S,) + (1,) * index.ndim)).ravel()
    return np.bincount(flat, values.ravel(), minlength=S * size).reshape(S, size)


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


class LaplaceLikelihood:
    """``l(beta, T_1..T_K)`` and its exact gradient for ``S`` response vectors at once.

    ``X`` (n, p) the fixed design of the (pooled) rows, ``trials`` (n,), ``Y`` (S, n) the
    successes, ``terms`` the random terms' rows (:class:`TermRows`). :meth:`evaluate` takes
    ``beta`` (S, p) and one loading (S, r_k, r_k) per term. The conditional modes of each
    study are kept as the warm start of its next evaluation (``u``).
    """

    def __init__(self, X: np.ndarray, trials: np.ndarray, Y: np.ndarray,
                 terms: list[TermRows]):
        self.X = np.asarray(X, dtype=float)
        self.m = np.asarray(trials, dtype=float)
        Y = np.asarray(Y, dtype=float)
        self.Y = Y[None] if Y.ndim == 1 else Y
        if not terms:
            raise ValueError("the Laplace likelihood needs a random term")
        self.terms = terms
        self.large = int(np.argmax([t.levels * t.size for t in terms]))
        big = terms[self.large]
        self.rest = [k for k in range(len(terms)) if k != self.large]
        self.n_large, self.r_large = big.levels, big.size
        self.q_large = big.levels * big.size
        offsets, columns, position = [], [], 0
        for k in self.rest:
            t = terms[k]
            offsets.append(position)
            columns.append(position + t.codes[:, None] * t.size + np.arange(t.size))
            position += t.levels * t.size
        self.q_rest = position
        self.rest_offsets = offsets
        n = len(self.m)
        self.rest_cols = (np.concatenate(columns, axis=1) if columns
                          else np.zeros((n, 0), dtype=np.intp))
        self.rest_slices = []
        start = 0
        for k in self.rest:
            self.rest_slices.append(slice(start, start + terms[k].size))
            start += terms[k].size
        rL = self.r_large
        self.large_index = big.codes[:, None] * rL + np.arange(rL)               # (n, rL)
        self.A_index = (big.codes[:, None, None] * rL * rL + np.arange(rL)[:, None] * rL
                        + np.arange(rL)[None, :])                                 # (n, rL, rL)
        qR = self.q_rest
        self.B_index = (self.large_index[:, :, None] * qR + self.rest_cols[:, None, :])
        self.C_index = self.rest_cols[:, :, None] * qR + self.rest_cols[:, None, :]
        self.q = self.q_large + self.q_rest
        self.u = np.zeros((len(self.Y), self.q))

    @property
    def n_studies(self) -> int:
        return len(self.Y)

    def subset(self, index) -> LaplaceLikelihood:
        """The studies ``index`` (their warm starts included) as a likelihood of their own."""
        out = LaplaceLikelihood.__new__(LaplaceLikelihood)
        out.__dict__.update(self.__dict__)
        out.Y = self.Y[index]
        out.u = self.u[index].copy()
        return out

    # ------------------------------------------------------------------ pieces
    def _alphas(self, loadings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``alpha`` of each row: the large term's (S, n, rL) and the others' (S, n, cR)."""
        big = self.terms[self.large]
        aL = np.einsum("na,sab->snb", big.Z, loadings[self.large])
        if not self.rest:
            return aL, np.zeros(aL.shape[:2] + (0,))
        aR = np.concatenate([np.einsum("na,sab->snb", self.terms[k].Z, loadings[k])
                             for k in self.rest], axis=2)
        return aL, aR

    def _rows(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each row's random effects ``u`` at its levels: (S, n, rL) and (S, n, cR)."""
        S = len(u)
        uL = u[:, :self.q_large].reshape(S, self.n_large, self.r_large)
        big = self.terms[self.large]
        return uL[:, big.codes], u[:, self.q_large:][:, self.rest_cols]

    def _eta(self, offset, aL, aR, u):
        uL, uR = self._rows(u)
        return offset + (aL * uL).sum(axis=2) + (aR * uR).sum(axis=2)

    def _h(self, Y, offset, aL, aR, u) -> np.ndarray:
        eta = self._eta(offset, aL, aR, u)
        return kernel(Y, self.m, eta).sum(axis=1) - 0.5 * np.einsum("sq,sq->s", u, u)

    def _factor(self, w, aL, aR, full: bool = False) -> _Factor:
        return _Factor(self, w, aL, aR, full)

    def _score(self, r, aL, aR, u) -> np.ndarray:
        """``dh/du = sum_i r_i a_i - u`` (S, q)."""
        gL = scatter(r[:, :, None] * aL, self.large_index, self.q_large)
        if not self.rest:
            return gL - u
        gR = scatter(r[:, :, None] * aR, self.rest_cols, self.q_rest)
        return np.concatenate([gL, gR], axis=1) - u

    def modes(self, offset, aL, aR, u0, Y=None) -> np.ndarray:
        """Penalised IRLS from ``u0``; each study stops when its step is below ``INNER_TOL``
        (frozen thereafter, so its answer never depends on its batch). A step longer than
        ``FULL_STEP`` in some coordinate is halved until ``h`` does not fall."""
        Y = self.Y if Y is None else Y
        u = u0.copy()
        active = np.arange(len(u))
        for _ in range(INNER_MAXITER):
            if not len(active):
                break
            o, a_L, a_R, ua, y = offset[active], aL[active], aR[active], u[active], Y[active]
            eta = self._eta(o, a_L, a_R, ua)
            p = expit(eta)
            mp = self.m * p
            factor = self._factor(mp * (1.0 - p), a_L, a_R)
            step = factor.solve(self._score(y - mp, a_L, a_R, ua))
            size = np.max(np.abs(step), axis=1)
            t = np.ones(len(active))
            long = np.flatnonzero(size > FULL_STEP)
            if len(long):
                current = kernel(y[long], self.m, eta[long]).sum(axis=1) - 0.5 * np.einsum(
                    "sq,sq->s", ua[long], ua[long])
                for _ in range(31):
                    value = self._h(y[long], o[long], a_L[long], a_R[long],
                                    ua[long] + t[long, None] * step[long])
                    worse = ~(value >= current - 1e-12 * (1.0 + np.abs(current)))
                    if not worse.any():
                        break
                    t[long[worse]] *= 0.5
            u[active] = ua + t[:, None] * step
            done = size * t < INNER_TOL
            active = active[~done]
        return u

    # ------------------------------------------------------------------ objective
    def evaluate(self, beta: np.ndarray, loadings: list[np.ndarray], grad: bool = True):
        """``(value (S,), d/dbeta (S, p), [d/dT_k (S, r_k, r_k)])`` (the last two None when
        ``grad`` is false); updates the warm starts ``u``."""
        beta = np.asarray(beta, dtype=float)
        offset = np.einsum("sp,np->sn", beta, self.X)   # per study: no batch-wide BLAS
        aL, aR = self._alphas(loadings)
        u = self.modes(offset, aL, aR, self.u)
        bad = ~np.isfinite(u).all(axis=1)
        if bad.any():                       # a diverged start: retry those from 0
            u[bad] = self.modes(offset[bad], aL[bad], aR[bad], np.zeros((bad.sum(), self.q)),
                                self.Y[bad])
        self.u = u
        eta = self._eta(offset, aL, aR, u)
        p = expit(eta)
        w = self.m * p * (1.0 - p)
        factor = self._factor(w, aL, aR, full=grad)
        value = (kernel(self.Y, self.m, eta).sum(axis=1) - 0.5 * np.einsum("sq,sq->s", u, u)
                 - 0.5 * factor.logdet)
        if not grad:
            return value, None, None
        return (value,) + self._gradient(u, p, w, aL, aR, factor)

    def _gradient(self, u, p, w, aL, aR, factor: _Factor):
        """The exact gradient (module docstring)."""
        r = self.Y - self.m * p
        hL, hR = factor.inverse_times_rows(aL, aR)                   # (H^-1 a_i) at row i
        d = (aL * hL).sum(axis=2) + (aR * hR).sum(axis=2)
        q = w * (1.0 - 2.0 * p) * d
        v = self._score(q, aL, aR, np.zeros_like(u))                   # sum_i q_i a_i
        s = factor.solve(v)
        sL, sR = self._rows(s)
        rho = r - 0.5 * q + 0.5 * w * ((aL * sL).sum(axis=2) + (aR * sR).sum(axis=2))
        g_beta = np.einsum("sn,np->sp", rho, self.X)
        uL, uR = self._rows(u)
        grads: list[np.ndarray] = [None] * len(self.terms)
        QL = rho[:, :, None] * uL - w[:, :, None] * hL - 0.5 * r[:, :, None] * sL
        grads[self.large] = np.einsum("na,snb->sab", self.terms[self.large].Z, QL)
        for k, cut in zip(self.rest, self.rest_slices, strict=True):
            Qk = (rho[:, :, None] * uR[:, :, cut] - w[:, :, None] * hR[:, :, cut]
                  - 0.5 * r[:, :, None] * sR[:, :, cut])
            grads[k] = np.einsum("na,snb->sab", self.terms[k].Z, Qk)
        return g_beta, grads


class _Factor:
    """``H = [[A, B], [B', C]]`` of each study at weights ``w`` (module docstring): solves,
    ``log det H``, and (``full``) the entries of ``H^-1`` the gradient needs."""

    def __init__(self, lik: LaplaceLikelihood, w, aL, aR, full: bool):
        self.lik = lik
        S = len(w)
        rL, nL, qR = lik.r_large, lik.n_large, lik.q_rest
        wa = w[:, :, None] * aL
        A = scatter(wa[:, :, :, None] * aL[:, :, None, :], lik.A_index, nL * rL * rL)
        A = A.reshape(S, nL, rL, rL) + np.eye(rL)
        self.A_inv, logdet_A = small_inverse(A)
        self.logdet = logdet_A.sum(axis=1)
        self.E = None
        if qR == 0:
            return
        B = scatter(wa[:, :, :, None] * aR[:, :, None, :], lik.B_index, nL * rL * qR)
        B = B.reshape(S, nL, rL, qR)
        C = scatter((w[:, :, None] * aR)[:, :, :, None] * aR[:, :, None, :], lik.C_index,
                    qR * qR).reshape(S, qR, qR) + np.eye(qR)
        self.E = self.A_inv @ B                                        # (S, nL, rL, qR)
        schur = C - np.swapaxes(B.reshape(S, nL * rL, qR), 1, 2) @ self.E.reshape(
            S, nL * rL, qR)
        chol = np.linalg.cholesky(schur)
        self.logdet = self.logdet + 2.0 * np.log(
            np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
        self.schur = schur
        self.S_inv = np.linalg.inv(schur) if full else None

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``H^-1 b`` for ``b`` (S, q)."""
        lik = self.lik
        S = len(b)
        bL = b[:, :lik.q_large].reshape(S, lik.n_large, lik.r_large)
        if self.E is None:
            return (self.A_inv @ bL[..., None])[..., 0].reshape(S, -1)
        bR = b[:, lik.q_large:]
        rhs = bR - np.einsum("slar,sla->sr", self.E, bL)
        if self.S_inv is None:
            xR = np.linalg.solve(self.schur, rhs[..., None])[..., 0]
        else:
            xR = np.einsum("srt,st->sr", self.S_inv, rhs)
        xL = (self.A_inv @ bL[..., None])[..., 0] - np.einsum("slar,sr->sla", self.E, xR)
        return np.concatenate([xL.reshape(S, -1), xR], axis=1)

    def inverse_times_rows(self, aL, aR) -> tuple[np.ndarray, np.ndarray]:
        """``(H^-1 a_i)`` at row ``i``'s own positions: (S, n, rL) and (S, n, cR)."""
        lik = self.lik
        codes = lik.terms[lik.large].codes
        if self.E is None:
            return np.einsum("snab,snb->sna", self.A_inv[:, codes], aL), aR
        F = self.E @ self.S_inv[:, None]                              # E S^-1 (S, nL, rL, qR)
        P_LL = self.A_inv + np.einsum("slar,slbr->slab", F, self.E)
        rL = lik.r_large
        cols = lik.rest_cols
        F_rows = F[:, codes[:, None, None], np.arange(rL)[None, :, None], cols[:, None, :]]
        S_rows = self.S_inv[:, cols[:, :, None], cols[:, None, :]]
        hL = (np.einsum("snab,snb->sna", P_LL[:, codes], aL)
              - np.einsum("snab,snb->sna", F_rows, aR))
        hR = (np.einsum("snab,snb->sna", S_rows, aR)
              - np.einsum("snab,sna->snb", F_rows, aL))
        return hL, hR
