"""The dense-``H`` Laplace likelihood (glmm_dense) against the Schur-complement one.

Both compute the Laplace approximation of Bates et al. 2015 (J. Stat. Softw. 67(1), eqs.
2-4 and sec. 5); the Schur path is validated against lme4 (test_glmm_lme4_corpus.py) and
against a textbook dense computation (test_glmm_laplace.py). Here: on many seeded datasets
and parameters, the two give the same value and gradient, and whole fits through
``fit_glmm`` (which picks the dense path for few crossed intercepts) the same
log-likelihood and estimates as with the Schur path forced.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis import glmm_core
from crs_study.analysis.glmm import fit_glmm
from crs_study.analysis.glmm_core import BinomialData, CrossedTerms
from crs_study.analysis.glmm_dense import DenseLaplace
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows
from crs_study.analysis.glmm_terms import RandomTerm


def _cells(seed: int, P: int, D: int, C: int):
    """Cells of P participants x D symbols x C conditions, random trial counts and rates."""
    rng = np.random.default_rng(seed)
    p, d, c = (a.ravel() for a in np.meshgrid(np.arange(P), np.arange(D), np.arange(C),
                                              indexing="ij"))
    X = np.column_stack([np.ones(len(p))] + [(c == k).astype(float) for k in range(1, C)])
    m = rng.integers(1, 8, len(p)).astype(float)
    rate = 1.0 / (1.0 + np.exp(-(0.3 + rng.normal(0, 1.0, P)[p] + rng.normal(0, 0.5, D)[d])))
    return p, d, X, m, rng.binomial(m.astype(int), rate).astype(float)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**20), P=st.integers(2, 14), D=st.integers(2, 10),
       C=st.integers(1, 3), slopes=st.booleans(),
       scale=st.floats(0.0, 2.0))
def test_value_and_gradient_equal_the_schur_path(seed, P, D, C, slopes, scale):
    """Any loadings (zero, non-triangular), intercepts or slopes, a batch of three studies."""
    p, d, X, m, y = _cells(seed, P, D, C)
    rng = np.random.default_rng(seed + 1)
    Zp = X if slopes and C > 1 else np.ones((len(p), 1))
    terms = [TermRows(p, P, Zp), TermRows(d, D, np.ones((len(p), 1)))]
    Y = np.stack([y, rng.binomial(m.astype(int), 0.5), rng.binomial(m.astype(int), 0.8)])
    beta = rng.normal(0, 1, (3, X.shape[1]))
    loadings = [scale * rng.normal(0, 1, (3, t.size, t.size)) for t in terms]
    schur = LaplaceLikelihood(X, m, Y, terms).evaluate(beta, loadings)
    dense = DenseLaplace(X, m, Y, terms).evaluate(beta, loadings)
    assert np.allclose(dense[0], schur[0], rtol=0, atol=1e-8)
    assert np.allclose(dense[1], schur[1], rtol=1e-7, atol=1e-7)
    for a, b in zip(dense[2], schur[2], strict=True):
        assert np.allclose(a, b, rtol=1e-7, atol=1e-7)


def test_a_study_in_a_batch_is_the_study_alone():
    """Each study's numbers depend on its own data only (the warm starts included)."""
    p, d, X, m, y = _cells(3, 6, 5, 2)
    terms = [TermRows(p, 6, np.ones((len(p), 1))), TermRows(d, 5, np.ones((len(p), 1)))]
    Y = np.stack([y, m - y, np.round(m / 2)])
    beta = np.array([[0.2, -0.1], [0.0, 0.5], [1.0, 0.3]])
    loadings = [np.array([[[0.8]], [[0.3]], [[1.5]]]), np.array([[[0.4]], [[0.0]], [[0.9]]])]
    batch = DenseLaplace(X, m, Y, terms).evaluate(beta, loadings)
    for s in range(3):
        alone = DenseLaplace(X, m, Y[s], terms).evaluate(beta[s:s + 1],
                                                         [T[s:s + 1] for T in loadings])
        assert batch[0][s] == alone[0][0]
        assert np.array_equal(batch[1][s], alone[1][0])


def test_fit_glmm_takes_the_dense_path_for_few_crossed_intercepts():
    p, d, X, m, y = _cells(5, 12, 10, 2)
    data = BinomialData(X, y, m, (p, d), (12, 10))
    terms = [RandomTerm("participant"), RandomTerm("digit")]
    assert isinstance(CrossedTerms(data, terms).likelihood, DenseLaplace)
    slopes = BinomialData(X, y, m, (p, d), (12, 10), (X, np.ones((len(p), 1))))
    slope_terms = [RandomTerm("participant", ("Intercept", "c1")), terms[1]]
    assert isinstance(CrossedTerms(slopes, slope_terms).likelihood, LaplaceLikelihood)


def _trials(seed: int, P: int, D: int, per_cell: int, sd_p: float, sd_d: float):
    rng = np.random.default_rng(seed)
    p, d, c = (a.ravel() for a in np.meshgrid(np.arange(P), np.arange(D), np.arange(2),
                                              np.arange(per_cell), indexing="ij")[:3])
    eta = 0.4 + 0.6 * c + rng.normal(0, sd_p, P)[p] + rng.normal(0, sd_d, D)[d]
    return pd.DataFrame({"participant": [f"p{i}" for i in p], "digit": d, "c": c.astype(float),
                         "correct": rng.binomial(1, 1.0 / (1.0 + np.exp(-eta))).astype(float)})


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**20), P=st.integers(3, 14), D=st.integers(3, 10),
       per_cell=st.integers(1, 6), sd_p=st.floats(0.0, 1.5), sd_d=st.floats(0.0, 1.0))
def test_whole_fits_equal_the_schur_path(seed, P, D, per_cell, sd_p, sd_d):
    """The fit's log-likelihood to 1e-8 (zero variances and boundaries included)."""
    data = _trials(seed, P, D, per_cell, sd_p, sd_d)
    dense = fit_glmm(data, "correct", "c", ["participant", "digit"])
    assert isinstance(dense._model.problem.model.likelihood, DenseLaplace)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(glmm_core, "DENSE_MAX_Q", 0)
        schur = fit_glmm(data, "correct", "c", ["participant", "digit"])
    assert isinstance(schur._model.problem.model.likelihood, LaplaceLikelihood)
    assert dense.loglike == pytest.approx(schur.loglike, abs=1e-8)
    assert np.allclose(dense.params, schur.params, atol=1e-4)
    assert np.allclose(dense.variance_components, schur.variance_components, atol=1e-4)
    assert dense.converged == schur.converged
