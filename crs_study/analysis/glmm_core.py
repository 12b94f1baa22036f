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
* :class:`CrossedTerms` -- any random terms (intercepts, slopes, correlated or not, crossed
  factors), Laplace only (as lme4): the likelihood of :mod:`crs_study.analysis.glmm_laplace`
  for one response vector (of :mod:`crs_study.analysis.glmm_dense`, the same numbers, for
  crossed intercepts of few levels), its parameters laid out as lme4's theta
  (:class:`~crs_study.analysis.glmm_terms.ThetaLayout`).
* :class:`NoRandom` -- plain logistic regression (used for the penalised fallback).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from crs_study.analysis.glmm_dense import DENSE_MAX_Q, DenseLaplace
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows
from crs_study.analysis.glmm_terms import RandomTerm, ThetaLayout

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
    Z: tuple[np.ndarray, ...] | None = None  # each term's design (n, r); None: intercepts


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


class CrossedTerms:
    """Random terms of any shape, crossed: intercepts and slopes, correlated or not (Laplace).

    Parameters are ``theta = (beta, theta_1, theta_2, ...)``, each term's theta the entries of
    its loading ``T_k`` in lme4's order (:class:`~crs_study.analysis.glmm_terms.ThetaLayout`);
    any real values (the likelihood depends on ``T_k T_k'`` only), made lme4's (non-negative
    diagonal) by :meth:`ThetaLayout.normalised`.
    """

    analytic_gradient = True

    def __init__(self, data: BinomialData, terms: Sequence[RandomTerm]):
        n = len(data.trials)
        Z = data.Z or tuple(np.ones((n, 1)) for _ in data.group_codes)
        rows = [TermRows(codes, levels, z) for codes, levels, z in
                zip(data.group_codes, data.n_levels, Z, strict=True)]
        # crossed intercepts of few levels (a demo's participants and symbols): H whole
        dense = (all(r.size == 1 for r in rows)
                 and sum(r.levels * r.size for r in rows) <= DENSE_MAX_Q)
        self.likelihood = (DenseLaplace if dense else LaplaceLikelihood)(
            data.X, data.trials, data.successes, rows)
        self.layout = ThetaLayout(data.X.shape[1], terms)
        self.n_variance = self.layout.n_theta
        self._last = None     # (theta, value, gradient or None) of the last evaluation

    def loadings_loglik(self, beta: np.ndarray, loadings: list[np.ndarray],
                        grad: bool = True):
        """Value, ``dl/dbeta`` and every ``dl/dT_k`` (r_k, r_k) at loadings given directly
        (any real matrices: the boundary checks use ones outside theta's pattern)."""
        self._last = None     # the warm start moves to these loadings' modes
        value, g_beta, g_loadings = self.likelihood.evaluate(
            np.asarray(beta, float)[None], [np.asarray(T, float)[None] for T in loadings], grad)
        if not grad:
            return float(value[0])
        return float(value[0]), g_beta[0], [g[0] for g in g_loadings]

    def gradients(self, thetas: np.ndarray) -> np.ndarray:
        """The gradient at each of ``thetas`` (K, size), in one batched evaluation, each from
        the conditional modes of the last evaluation (left as they were): the points of a
        differenced Hessian."""
        layout = self.layout
        thetas = np.asarray(thetas, dtype=float)
        lik = self.likelihood.subset(np.zeros(len(thetas), dtype=int))
        _, g_beta, g_loadings = lik.evaluate(thetas[:, :layout.n_fixed],
                                             layout.loadings(thetas))
        return layout.gradient(g_beta, g_loadings)

    def loglik(self, theta: np.ndarray, grad: bool = True):
        """The value (and gradient) at ``theta``; asked again at the point of the last
        evaluation (a fit reads its optimum several times), the numbers of that one."""
        layout = self.layout
        theta = np.array(theta, dtype=float)
        last = self._last
        same = last is not None and last[0].shape == theta.shape and bool(
            (last[0] == theta).all())      # numpy.array_equal, without its overhead
        if same and (last[2] is not None or not grad):
            return last[1] if not grad else (last[1], last[2].copy())
        value, g_beta, g_loadings = self.likelihood.evaluate(
            theta[None, :layout.n_fixed], layout.loadings(theta[None]), grad)
        gradient = layout.gradient(g_beta, g_loadings)[0] if grad else None
        self._last = (theta, float(value[0]), gradient)
        if not grad:
            return float(value[0])
        return float(value[0]), gradient.copy()
