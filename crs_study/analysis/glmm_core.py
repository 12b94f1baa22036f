"""Numerical core of the binomial-logit GLMM: marginal log-likelihoods and their gradients.

The model (lme4's parameterisation, Bates et al. 2015, J. Stat. Softw. 67(1), eqs. 2-4)::

    y_i ~ Binomial(m_i, p_i),   logit p_i = x_i' beta + sum_k sigma_k u_{k, g_k(i)},
    u ~ N(0, I)    (spherical random effects; b_k = sigma_k u_k)

Every objective here is the marginal log-likelihood *kernel* ``sum y eta - m log(1 + e^eta)``
with the random effects integrated out; the binomial constants are added by the caller.

* :class:`SingleFactor` -- one random intercept. The Hessian of the conditional log density in
  ``u`` is diagonal, so the conditional modes come from a vectorised Newton iteration on
  per-group sums (``np.add.reduceat`` over rows sorted by group). The Laplace approximation
  (Pinheiro & Bates 1995, J. Comput. Graph. Stat. 4:12, eq. 8) and adaptive Gauss-Hermite
  quadrature centred at the mode and scaled by the curvature (Pinheiro & Bates 1995, eq. 11;
  Liu & Pierce 1994, Biometrika 81:624) both have exact analytic gradients: the mode and the
  curvature depend on ``(beta, sigma)`` and are differentiated implicitly.
* :class:`CrossedFactors` -- two or more crossed random intercepts, Laplace only (as lme4):
  penalised IRLS; the Newton steps, the log-determinant of ``Lambda' Z' W Z Lambda + I`` and
  the entries of its inverse that the exact gradient needs come from the Schur complement of
  the factor with most levels (:class:`_Schur`: its block is diagonal); beyond a few thousand
  random effects a sparse ``splu`` and central differences.
* :class:`NoRandom` -- plain logistic regression (used for the penalised fallback).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.special import expit

_INNER_TOL = 1e-11
_INNER_MAXITER = 60
#: Most adaptive Gauss-Hermite points accepted, by ``fit_glmm`` and by the analysis plan alike.
#: 100 points still give finite weights (the smallest is ~6e-79) and cbpp's fit equals the
#: 25-point one to 1e-6; more would only cost time.
MAX_QUADRATURE = 100


@dataclass(frozen=True)
class BinomialData:
    """Aggregated binomial rows: ``successes`` of ``trials`` at design row ``X[i]``."""

    X: np.ndarray  # (n, p) fixed-effects design
    successes: np.ndarray  # (n,)
    trials: np.ndarray  # (n,)
    group_codes: tuple[np.ndarray, ...]  # one (n,) int array per grouping factor
    n_levels: tuple[int, ...]


def _kernel(y: np.ndarray, m: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """Binomial log-likelihood kernel ``y eta - m log(1 + e^eta)``, elementwise and stable."""
    return y * eta - m * np.logaddexp(0.0, eta)


class NoRandom:
    """Logistic regression without random effects: ``l(beta) = sum y eta - m log(1 + e^eta)``."""

    n_variance = 0
    analytic_gradient = True

    def __init__(self, data: BinomialData):
        self.X, self.y, self.m = data.X, data.successes, data.trials

    def loglik(self, theta: np.ndarray, grad: bool = True):
        eta = self.X @ theta
        value = float(_kernel(self.y, self.m, eta).sum())
        if not grad:
            return value
        return value, self.X.T @ (self.y - self.m * expit(eta))


class SingleFactor:
    """One random intercept: Laplace (``n_quadrature == 1``) or adaptive Gauss-Hermite.

    Parameters are ``theta = (beta, sigma)``; ``sigma`` may be any real (the likelihood is even
    in it), the optimiser keeps it >= 0.
    """

    n_variance = 1
    analytic_gradient = True

    def __init__(self, data: BinomialData, n_quadrature: int = 1):
        order = np.argsort(data.group_codes[0], kind="stable")
        codes = data.group_codes[0][order]
        self.X = data.X[order]
        self.y = data.successes[order]
        self.m = data.trials[order]
        self.codes = codes
        self.starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
        self.n_groups = len(self.starts)
        self.u = np.zeros(self.n_groups)  # warm start of the conditional modes
        self.n_quadrature = int(n_quadrature)
        if self.n_quadrature > 1:
            nodes, weights = np.polynomial.hermite.hermgauss(self.n_quadrature)
            self.nodes = nodes
            self.log_weights = np.log(weights) + nodes**2  # e^{x^2} undoes the Hermite weight

    def _sum(self, values: np.ndarray) -> np.ndarray:
        """Per-group sums over rows (axis 0)."""
        return np.add.reduceat(values, self.starts, axis=0)

    def _modes(self, offset: np.ndarray, sigma: float) -> np.ndarray:
        """Conditional modes ``u_j`` maximising ``sum_{i in j} kernel - u_j^2 / 2`` (Newton)."""
        y, m, codes = self.y, self.m, self.codes
        u = self.u.copy()
        if not np.all(np.isfinite(u)):
            u[:] = 0.0

        def per_group(u_: np.ndarray) -> np.ndarray:
            return self._sum(_kernel(y, m, offset + sigma * u_[codes])) - 0.5 * u_**2

        current = per_group(u)
        for _ in range(_INNER_MAXITER):
            p = expit(offset + sigma * u[codes])
            r = self._sum(y - m * p)
            w = self._sum(m * p * (1.0 - p))
            step = (sigma * r - u) / (1.0 + sigma**2 * w)
            candidate = u + step
            value = per_group(candidate)
            # Step-halving for the groups where the full Newton step overshoots (1-D concave).
            for _ in range(30):
                worse = value < current - 1e-12 * (1.0 + np.abs(current))
                if not worse.any():
                    break
                step = np.where(worse, 0.5 * step, step)
                candidate = u + step
                value = per_group(candidate)
            u, current = candidate, value
            if np.max(np.abs(step)) < _INNER_TOL:
                break
        self.u = u
        return u

    def loglik(self, theta: np.ndarray, grad: bool = True):
        """Marginal log-likelihood kernel and (optionally) its exact gradient in ``theta``."""
        X, y, m, codes = self.X, self.y, self.m, self.codes
        beta, sigma = theta[:-1], float(theta[-1])
        offset = X @ beta
        u = self._modes(offset, sigma)
        eta = offset + sigma * u[codes]
        p = expit(eta)
        w_i = m * p * (1.0 - p)
        W = self._sum(w_i)
        D = 1.0 + sigma**2 * W  # -(d^2/du_j^2) of the conditional log density
        if self.n_quadrature == 1:
            value = float(_kernel(y, m, eta).sum() - 0.5 * (u @ u) - 0.5 * np.log(D).sum())
        else:
            value, agq = self._agq(offset, sigma, u, D)
        if not grad:
            return value

        # Implicit derivatives of the mode u_j and the curvature D_j.
        resid = y - m * p
        r = self._sum(resid)
        dw_i = w_i * (1.0 - 2.0 * p)  # d w_i / d eta_i
        T = self._sum(dw_i)
        WX = self._sum(w_i[:, None] * X)
        TX = self._sum(dw_i[:, None] * X)
        du_dbeta = -sigma * WX / D[:, None]  # (J, p)
        du_dsigma = (r - sigma * W * u) / D  # (J,)
        dD_dbeta = sigma**2 * (TX + sigma * T[:, None] * du_dbeta)
        dD_dsigma = 2.0 * sigma * W + sigma**2 * T * (u + sigma * du_dsigma)
        if self.n_quadrature == 1:
            g_beta = X.T @ resid - 0.5 * (dD_dbeta / D[:, None]).sum(axis=0)
            g_sigma = float(u @ r) - 0.5 * float((dD_dsigma / D).sum())
            return value, np.r_[g_beta, g_sigma]
        return value, self._agq_gradient(agq, sigma, D, du_dbeta, du_dsigma, dD_dbeta, dD_dsigma)

    def _agq(self, offset: np.ndarray, sigma: float, u: np.ndarray, D: np.ndarray):
        """Adaptive Gauss-Hermite quadrature of each group's integral.

        ``log L_j = -log(D_j)/2 - log(pi)/2 + logsumexp_k(A_jk)`` with nodes
        ``v_jk = u_j + sqrt(2) x_k / sqrt(D_j)`` and
        ``A_jk = sum_{i in j} kernel(eta_ik) - v_jk^2/2 + log w_k + x_k^2``.
        """
        scale = np.sqrt(2.0) / np.sqrt(D)
        v = u[:, None] + scale[:, None] * self.nodes[None, :]  # (J, K)
        eta = offset[:, None] + sigma * v[self.codes]  # (n, K)
        A = self._sum(_kernel(self.y[:, None], self.m[:, None], eta)) - 0.5 * v**2
        A += self.log_weights[None, :]
        top = A.max(axis=1, keepdims=True)
        weights = np.exp(A - top)
        total = weights.sum(axis=1, keepdims=True)
        lse = top[:, 0] + np.log(total[:, 0])
        value = float((-0.5 * np.log(D) - 0.5 * np.log(np.pi) + lse).sum())
        return value, (v, eta, weights / total)

    def _agq_gradient(self, agq, sigma, D, du_dbeta, du_dsigma, dD_dbeta, dD_dsigma):
        """Exact gradient of the AGQ log-likelihood: nodes move with the mode and the scale."""
        v, eta, post = agq  # post: (J, K) normalised quadrature weights
        X, y, m = self.X, self.y, self.m
        resid = y[:, None] - m[:, None] * expit(eta)  # (n, K)
        R = self._sum(resid)  # (J, K)
        # explicit beta-derivative at fixed nodes: sum_k post_jk sum_{i in j} resid_ik x_i
        weighted = (resid * post[self.codes]).sum(axis=1)  # (n,)
        g_beta = X.T @ weighted
        g_sigma = float((post * R * v).sum())
        dh_dv = sigma * R - v  # (J, K)
        # dv_jk = du_j + sqrt(2) x_k d(D_j^{-1/2}) = du_j - x_k D_j^{-3/2} dD_j / sqrt(2)
        coef = -self.nodes[None, :] * D[:, None] ** -1.5 / np.sqrt(2.0)  # (J, K)
        slope = (post * dh_dv).sum(axis=1)  # (J,)
        slope_x = (post * dh_dv * coef).sum(axis=1)  # (J,)
        g_beta = g_beta + (slope[:, None] * du_dbeta + slope_x[:, None] * dD_dbeta).sum(axis=0)
        g_beta -= 0.5 * (dD_dbeta / D[:, None]).sum(axis=0)
        g_sigma += float((slope * du_dsigma + slope_x * dD_dsigma).sum())
        g_sigma -= 0.5 * float((dD_dsigma / D).sum())
        return np.r_[g_beta, g_sigma]


class _Schur:
    """``H = Lambda Z'WZ Lambda + I`` split as ``[[A, B], [B', C]]``: ``A`` the block of the
    factor with the most levels (diagonal: each row has one level of it), ``C`` the block of
    the other factors (``r x r``, small: the digits). Solves, the log-determinant and the
    entries of ``H^-1`` that the gradient needs go through the Schur complement
    ``S = C - B' A^-1 B`` (Golub & Van Loan 2013, sec. 3.2.10):
    ``log det H = sum log a + log det S``, ``H^-1 = [[A^-1 + E S^-1 E', -E S^-1], [., S^-1]]``
    with ``E = A^-1 B``. The work is ``O(n K^2 + L r^2 + r^3)`` instead of the dense ``q^3``
    (110 x 110 for 100 participants and 10 digits), and no LAPACK call sees more than the
    ``r x r`` block, so a multithreaded BLAS has nothing to spread over a busy machine.
    """

    def __init__(self, model: CrossedFactors, lam: np.ndarray, w: np.ndarray):
        self.model = model
        rows_l, rows_r = model.rows_large, model.rows_rest
        n_l, r = model.n_large, model.n_rest
        lam_l, lam_r = lam[model.large_cols], lam[model.rest_cols]
        self.a = lam_l**2 * np.bincount(rows_l, w, minlength=n_l) + 1.0
        B = sum(np.bincount(rows_l * r + rows_r[:, t], w, minlength=n_l * r)
                for t in range(rows_r.shape[1])).reshape(n_l, r)
        self.B = lam_l[:, None] * B * lam_r[None, :]
        C = sum(np.bincount(rows_r[:, s] * r + rows_r[:, t], w, minlength=r * r)
                for s in range(rows_r.shape[1]) for t in range(rows_r.shape[1]))
        C = lam_r[:, None] * C.reshape(r, r) * lam_r[None, :] + np.eye(r)
        self.E = self.B / self.a[:, None]
        S = C - self.B.T @ self.E
        sign, logdet_s = np.linalg.slogdet(S)
        if sign <= 0:
            raise np.linalg.LinAlgError("the Schur complement is not positive definite")
        self.S_inv = np.linalg.inv(S)
        self.logdet = float(np.log(self.a).sum() + logdet_s)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``H^-1 b`` for ``b`` of shape (q,) or (q, k)."""
        model = self.model
        b_l, b_r = b[model.large_cols], b[model.rest_cols]
        a = self.a if b.ndim == 1 else self.a[:, None]
        x_r = self.S_inv @ (b_r - self.E.T @ b_l)
        x = np.empty_like(b, dtype=float)
        x[model.large_cols] = b_l / a - self.E @ x_r
        x[model.rest_cols] = x_r
        return x

    def pairs(self) -> np.ndarray:
        """``G[i, a, b] = (H^-1)[col_ia, col_ib]`` for every row ``i`` and factors ``a, b``."""
        model = self.model
        F = self.E @ self.S_inv
        diag_l = 1.0 / self.a + np.einsum("jm,jm->j", F, self.E)
        rows_l, rows_r = model.rows_large, model.rows_rest
        K = model.n_variance
        G = np.empty((len(rows_l), K, K))
        big = model.large
        rest = [k for k in range(K) if k != big]
        G[:, big, big] = diag_l[rows_l]
        for t, k in enumerate(rest):
            G[:, big, k] = G[:, k, big] = -F[rows_l, rows_r[:, t]]
            for s, j in enumerate(rest):
                G[:, j, k] = self.S_inv[rows_r[:, s], rows_r[:, t]]
        return G


class CrossedFactors:
    """Two or more crossed random intercepts, Laplace approximation.

    ``l(beta, sigma) = sum kernel(X beta + Z Lambda u*) - |u*|^2/2 - log det(H)/2`` with
    ``H = Lambda Z'WZ Lambda + I`` (Bates et al. 2015, eq. 35 with the GLMM weights). ``Z`` has
    one 1 per factor in each row, so ``Z v``, ``Z' r`` and ``Z'WZ`` are gathers and
    ``np.bincount`` sums. ``H`` is handled by :class:`_Schur` (the factor with the most levels
    eliminated, its block being diagonal) and the gradient is exact (implicit differentiation
    of ``u*``, ``tr(H^-1 dH)`` from the entries of ``H^-1`` on the rows' pairs of levels) up to
    ``MAX_DENSE`` random effects; beyond, ``H`` is a sparse
    matrix factorised by ``scipy.sparse.linalg.splu`` and the gradient is taken by central
    differences.
    """

    MAX_DENSE = 3000

    def __init__(self, data: BinomialData):
        self.X, self.y, self.m = data.X, data.successes, data.trials
        self.n_variance = len(data.group_codes)
        offsets = np.cumsum((0,) + data.n_levels)
        self.cols = np.column_stack([c + o for c, o in
                                     zip(data.group_codes, offsets[:-1], strict=True)])
        self.factor_of_column = np.repeat(np.arange(self.n_variance), data.n_levels)
        self.q = int(offsets[-1])
        self.u = np.zeros(self.q)
        self.large = int(np.argmax(data.n_levels))
        self.large_cols = np.flatnonzero(self.factor_of_column == self.large)
        self.rest_cols = np.flatnonzero(self.factor_of_column != self.large)
        self.n_large, self.n_rest = len(self.large_cols), len(self.rest_cols)
        self.rows_large = data.group_codes[self.large].astype(np.intp)
        position = np.full(self.q, -1, dtype=np.intp)
        position[self.rest_cols] = np.arange(self.n_rest)
        self.rows_rest = np.column_stack([position[self.cols[:, k]]
                                          for k in range(self.n_variance) if k != self.large])
        self.analytic_gradient = self.q <= self.MAX_DENSE

    def _Z(self, v: np.ndarray) -> np.ndarray:
        """``Z v`` for ``v`` of shape (q,) or (q, k)."""
        return sum(v[self.cols[:, k]] for k in range(self.n_variance))

    def _Zt(self, r: np.ndarray) -> np.ndarray:
        """``Z' r`` for ``r`` of shape (n,) or (n, k)."""
        if r.ndim == 2:
            return np.column_stack([self._Zt(r[:, j]) for j in range(r.shape[1])])
        return sum(np.bincount(self.cols[:, k], r, minlength=self.q)
                   for k in range(self.n_variance))

    def _factor(self, lam: np.ndarray, w: np.ndarray):
        """``H = Lambda Z'WZ Lambda + I``: (solve, log det H, :class:`_Schur` or None)."""
        q = self.q
        if self.analytic_gradient:
            schur = _Schur(self, lam, w)
            return schur.solve, schur.logdet, schur
        if not hasattr(self, "_sparse_Z"):
            rows = np.repeat(np.arange(len(w)), self.n_variance)
            self._sparse_Z = sp.csr_matrix((np.ones(rows.size), (rows, self.cols.ravel())),
                                           shape=(len(w), q))
        A = self._sparse_Z @ sp.diags(lam)
        lu = splu((A.T @ sp.diags(w) @ A + sp.identity(q)).tocsc())
        return lu.solve, float(np.log(np.abs(lu.U.diagonal())).sum()), None

    def _mode(self, theta: np.ndarray, u0: np.ndarray):
        """Penalised IRLS for ``u*``; returns what the value and the gradient need."""
        p_fixed = self.X.shape[1]
        beta, sigmas = theta[:p_fixed], theta[p_fixed:]
        offset = self.X @ beta
        lam = sigmas[self.factor_of_column]
        y, m = self.y, self.m

        def h(u_: np.ndarray) -> float:
            return float(_kernel(y, m, offset + self._Z(lam * u_)).sum() - 0.5 * (u_ @ u_))

        u = u0.copy()
        current = h(u)
        for _ in range(_INNER_MAXITER):
            p = expit(offset + self._Z(lam * u))
            solve, _, _ = self._factor(lam, m * p * (1.0 - p))
            step = solve(lam * self._Zt(y - m * p) - u)
            t = 1.0
            for _ in range(30):
                candidate = u + t * step
                value = h(candidate)
                if value >= current - 1e-12 * (1.0 + abs(current)):
                    break
                t *= 0.5
            u, current = candidate, value
            if np.max(np.abs(t * step)) < _INNER_TOL:
                break
        p = expit(offset + self._Z(lam * u))
        w = m * p * (1.0 - p)
        _, logdet, H = self._factor(lam, w)
        return current - 0.5 * logdet, u, (lam, p, w, H)

    def loglik(self, theta: np.ndarray, grad: bool = True):
        value, u, state = self._mode(theta, self.u)
        self.u = u
        if not grad:
            return value
        if not self.analytic_gradient:
            g = np.empty_like(theta)
            for k in range(len(theta)):
                h = 1e-5 * max(1.0, abs(theta[k]))
                up, down = theta.copy(), theta.copy()
                up[k] += h
                down[k] -= h
                g[k] = (self._mode(up, u)[0] - self._mode(down, u)[0]) / (2.0 * h)
            return value, g
        return value, self._gradient(u, state)

    def _gradient(self, u: np.ndarray, state) -> np.ndarray:
        """``dl/dt = explicit(t) - tr(H^-1 dH/dt) / 2`` with ``du*/dt = H^-1 dg/dt``.

        ``g(u) = Lambda Z'(y - mu) - u`` is the score in ``u``; ``dH/dt`` has the terms of
        ``dLambda`` and ``A' diag(w' deta/dt) A`` whose trace is ``sum_i w'_i d_i deta_i/dt``
        with ``d_i = a_i' H^-1 a_i`` (``a_i`` row ``i`` of ``Z Lambda``); the ``dLambda`` term
        of factor ``k`` is ``sum_i w_i sum_b (H^-1)[col_ik, col_ib] lambda_ib``. Only the
        entries of ``H^-1`` at each row's pairs of levels are needed (:meth:`_Schur.pairs`).
        """
        lam, p, w, schur = state
        X, cols, y, m = self.X, self.cols, self.y, self.m
        resid = y - m * p
        dw = w * (1.0 - 2.0 * p)
        lam_cols = lam[cols]
        pairs = schur.pairs()
        weighted = pairs * lam_cols[:, None, :]                  # G[i, a, b] lambda_ib
        d = (weighted.sum(axis=2) * lam_cols).sum(axis=1)
        du_dbeta = schur.solve(-(lam[:, None] * self._Zt(w[:, None] * X)))  # (q, p)
        g_beta = X.T @ resid - 0.5 * (dw * d) @ (X + self._Z(lam[:, None] * du_dbeta))
        Zr = self._Zt(resid)
        trace = w @ weighted.sum(axis=2)
        K = self.n_variance
        masks = (self.factor_of_column[:, None] == np.arange(K)[None, :]).astype(float)
        Zu = self._Z(masks * u[:, None])                                     # (n, K)
        du = schur.solve(masks * Zr[:, None] - lam[:, None] * self._Zt(w[:, None] * Zu))
        deta = Zu + self._Z(lam[:, None] * du)
        g_sigma = (masks * u[:, None]).T @ Zr - trace - 0.5 * (dw * d) @ deta
        return np.r_[g_beta, g_sigma]
