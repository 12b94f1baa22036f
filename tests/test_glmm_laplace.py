"""The Laplace likelihood of vector-valued crossed random effects (glmm_laplace).

Outside references: the value against the textbook Laplace approximation computed densely
here, written apart from the module (Newton's method on the full ``q``-vector of random effects,
``numpy.linalg.slogdet`` of the dense ``H = Lambda' Z' W Z Lambda + I``; Bates et al. 2015,
J. Stat. Softw. 67(1), eqs. 2-4 and sec. 5); the gradient against central differences of that
value; the intercept-only case against the one-factor core (``SingleFactor``), validated
against lme4 and scipy's quadrature in test_glmm.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import expit

from crs_study.analysis.glmm_core import BinomialData, CrossedTerms, SingleFactor
from crs_study.analysis.glmm_irls import kernel
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows, small_inverse
from crs_study.analysis.glmm_terms import RandomTerm


def _data(seed: int, P: int, D: int, C: int = 2):
    """Cells of P participants x D symbols x C conditions with random trial counts."""
    rng = np.random.default_rng(seed)
    p, d, c = (a.ravel() for a in np.meshgrid(np.arange(P), np.arange(D), np.arange(C),
                                              indexing="ij"))
    X = np.column_stack([np.ones(len(p))] + [(c == k).astype(float) for k in range(1, C)])
    m = rng.integers(1, 6, len(p)).astype(float)
    y = rng.binomial(m.astype(int), 0.6).astype(float)
    return p, d, X, m, y


def _dense(X, m, y, codes, Z, beta, loadings):
    """The Laplace value computed the long way: a dense ``Z Lambda`` and ``H``."""
    n = len(y)
    blocks, offset = [], 0
    for g, z, T in zip(codes, Z, loadings, strict=True):
        r = T.shape[0]
        levels = int(g.max()) + 1
        block = np.zeros((n, levels * r))
        for i in range(n):
            block[i, g[i] * r:(g[i] + 1) * r] = z[i] @ T
        blocks.append(block)
        offset += levels * r
    A = np.concatenate(blocks, axis=1)
    u = np.zeros(A.shape[1])
    for _ in range(100):
        p = expit(X @ beta + A @ u)
        H = A.T @ (A * (m * p * (1 - p))[:, None]) + np.eye(len(u))
        step = np.linalg.solve(H, A.T @ (y - m * p) - u)
        u = u + step
        if np.max(np.abs(step)) < 1e-13:
            break
    eta = X @ beta + A @ u
    p = expit(eta)
    H = A.T @ (A * (m * p * (1 - p))[:, None]) + np.eye(len(u))
    return kernel(y, m, eta).sum() - u @ u / 2 - np.linalg.slogdet(H)[1] / 2


matrices = st.lists(st.floats(-1.2, 1.2), min_size=4, max_size=4).map(
    lambda v: np.array(v).reshape(2, 2))


@settings(max_examples=12, deadline=None)
@given(beta=st.lists(st.floats(-1.5, 1.5), min_size=2, max_size=2), Tp=matrices, Td=matrices,
       sizes=st.sampled_from([(6, 4), (3, 7), (5, 5)]))
def test_value_and_gradient_of_slopes_equal_the_dense_laplace(beta, Tp, Td, sizes):
    """Any loadings (not only triangular, zero columns included), either factor the larger."""
    P, D = sizes
    p, d, X, m, y = _data(7, P, D)
    beta = np.asarray(beta)
    lik = LaplaceLikelihood(X, m, y, [TermRows(p, P, X), TermRows(d, D, X)])
    value, g_beta, g_T = lik.evaluate(beta[None], [Tp[None], Td[None]])
    dense = _dense(X, m, y, (p, d), (X, X), beta, (Tp, Td))
    assert value[0] == pytest.approx(dense, abs=1e-9)
    h = 1e-6
    for k in range(2):
        numeric = np.zeros((2, 2))
        for a in range(2):
            for b in range(2):
                E = np.zeros((2, 2))
                E[a, b] = h
                up = [Tp + E, Td] if k == 0 else [Tp, Td + E]
                down = [Tp - E, Td] if k == 0 else [Tp, Td - E]
                numeric[a, b] = (_dense(X, m, y, (p, d), (X, X), beta, up)
                                 - _dense(X, m, y, (p, d), (X, X), beta, down)) / (2 * h)
        np.testing.assert_allclose(g_T[k][0], numeric, rtol=1e-5, atol=1e-5)
    numeric_beta = [(_dense(X, m, y, (p, d), (X, X), beta + h * e, (Tp, Td))
                     - _dense(X, m, y, (p, d), (X, X), beta - h * e, (Tp, Td))) / (2 * h)
                    for e in np.eye(2)]
    np.testing.assert_allclose(g_beta[0], numeric_beta, rtol=1e-5, atol=1e-5)


def test_three_conditions_and_one_factor_alone():
    """A 3 x 3 loading (LAPACK's path) and a term with no other factor beside it."""
    p, d, X, m, y = _data(3, 5, 4, C=3)
    rng = np.random.default_rng(0)
    T = np.tril(rng.normal(0, 0.6, (3, 3)))
    beta = np.array([0.2, -0.3, 0.5])
    lik = LaplaceLikelihood(X, m, y, [TermRows(p, 5, X)])
    value, _, g = lik.evaluate(beta[None], [T[None]])
    assert value[0] == pytest.approx(_dense(X, m, y, (p,), (X,), beta, (T,)), abs=1e-9)
    lik2 = LaplaceLikelihood(X, m, y, [TermRows(p, 5, X), TermRows(d, 4, X[:, :1])])
    value2, _, _ = lik2.evaluate(beta[None], [T[None], np.array([[[0.4]]])])
    assert value2[0] == pytest.approx(
        _dense(X, m, y, (p, d), (X, X[:, :1]), beta, (T, np.array([[0.4]]))), abs=1e-9)


def test_random_intercept_alone_equals_the_one_factor_core():
    p, d, X, m, y = _data(5, 8, 3)
    data = BinomialData(X, y, m, (p,), (8,))
    theta = np.array([0.3, -0.2, 0.7])
    single_value, single_grad = SingleFactor(data, 1).loglik(theta)
    value, grad = CrossedTerms(data, [RandomTerm("participant")]).loglik(theta)
    assert value == pytest.approx(single_value, abs=1e-10)
    np.testing.assert_allclose(grad, single_grad, atol=1e-9)


def test_a_study_in_a_batch_is_the_study_alone():
    """Each study has its own parameters and converges on its own: batch or not, same value."""
    p, d, X, m, y = _data(2, 6, 4)
    rng = np.random.default_rng(9)
    Y = np.stack([y, rng.binomial(m.astype(int), 0.3), rng.binomial(m.astype(int), 0.9)])
    beta = np.array([[0.1, 0.2], [-0.5, 1.0], [1.2, -0.4]])
    Tp = np.stack([np.eye(2) * 0.5, [[0.9, 0], [0.4, 0.2]], [[0.0, 0], [0.0, 0.0]]])
    Td = np.stack([np.eye(2) * 0.2, [[0.3, 0], [-0.1, 0.6]], [[1.1, 0], [0.5, 0.5]]])
    terms = [TermRows(p, 6, X), TermRows(d, 4, X)]
    values, g_beta, _ = LaplaceLikelihood(X, m, Y, terms).evaluate(beta, [Tp, Td])
    for s in range(3):
        alone, g_alone, _ = LaplaceLikelihood(X, m, Y[s], terms).evaluate(
            beta[s:s + 1], [Tp[s:s + 1], Td[s:s + 1]])
        assert values[s] == pytest.approx(alone[0], abs=1e-10)
        np.testing.assert_allclose(g_beta[s], g_alone[0], atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(r=st.sampled_from([1, 2, 3]), seed=st.integers(0, 2**16))
def test_small_inverse_is_numpys(r, seed):
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(4, r, r))
    A = M @ np.swapaxes(M, 1, 2) + np.eye(r)
    inverse, logdet = small_inverse(A)
    np.testing.assert_allclose(inverse, np.linalg.inv(A), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(A)[1], rtol=1e-12, atol=1e-12)
