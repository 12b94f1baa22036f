"""The batched Laplace likelihood and fits of crs_study.power_analysis against the GLMM's own.

Outside references: the objective is ``glmm_core``'s (``CrossedFactors`` / ``SingleFactor``,
whose maxima tests/test_glmm_lme4_corpus.py checks against lme4 1.1-31 and glmmTMB on 65
datasets); the fits must reach ``fit_glmm``'s maximum, boundary rule included. The fits
against lme4 itself are tests/test_power_lme4.py.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import expit, gammaln

from crs_study.analysis.glmm import fit_glmm
from crs_study.analysis.glmm_core import BinomialData, CrossedFactors, SingleFactor
from crs_study.power_analysis.laplace import BatchLaplace, CellDesign
from crs_study.power_analysis.maximise import fit_batch

X2 = np.array([[1.0, 0.0], [1.0, 1.0]])
X3 = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, 1.0]])


def _simulate(rng, S, P, D, X, beta, sp, sd, reps=5):
    m = np.full((D, len(X)), float(reps))
    b = rng.normal(0, sp, (S, P))
    d = rng.normal(0, sd, (S, D))
    eta = (X @ beta)[None, None, None, :] + b[:, :, None, None] + d[:, None, :, None]
    return rng.binomial(reps, expit(eta)).astype(float), m


def _binomial_data(Y, m, X, digit):
    P, D, C = Y.shape
    p, d, c = np.meshgrid(np.arange(P), np.arange(D), np.arange(C), indexing="ij")
    codes = (p.ravel(), d.ravel()) if digit else (p.ravel(),)
    return BinomialData(X[c.ravel()], Y.ravel(), np.broadcast_to(m, Y.shape).ravel().copy(),
                        codes, (P, D) if digit else (P,))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), P=st.integers(2, 9), D=st.integers(2, 6),
       conditions=st.sampled_from([2, 3]), digit=st.booleans(),
       scale=st.floats(0.0, 3.0))
def test_value_and_gradient_equal_glmm_core(seed, P, D, conditions, digit, scale):
    """Laplace log-likelihood kernel and its exact gradient, any data and parameters (sigmas
    of either sign, zero included): the same numbers as glmm_core's, to rounding."""
    rng = np.random.default_rng(seed)
    X = X2 if conditions == 2 else X3
    S = 3
    m = rng.integers(1, 6, (D, conditions)).astype(float)
    Y = rng.binomial(m.astype(int)[None, None], rng.uniform(0.05, 0.95),
                     size=(S, P, D, conditions)).astype(float)
    design = CellDesign(X, m, digit)
    theta = rng.normal(0, 1, (S, design.n_params))
    theta[:, X.shape[1]:] *= scale
    value, gradient = BatchLaplace(design, Y).evaluate(theta)
    for s in range(S):
        data = _binomial_data(Y[s], m, X, digit)
        model = CrossedFactors(data) if digit else SingleFactor(data, 1)
        v, g = model.loglik(theta[s])
        assert value[s] == pytest.approx(v, abs=1e-9 * (1 + abs(v)))
        np.testing.assert_allclose(gradient[s], g, rtol=1e-7, atol=1e-8)


def _reference_fit(Y, m, X, digit):
    """fit_glmm on one study's cells: (log-likelihood, estimates with SDs)."""
    P, D, C = Y.shape
    p, d, c = np.meshgrid(np.arange(P), np.arange(D), np.arange(C), indexing="ij")
    frame = pd.DataFrame({"y": Y.ravel(), "m": np.broadcast_to(m, (P, D, C)).ravel(),
                          "participant": p.ravel(), "digit": d.ravel()})
    design = pd.DataFrame(X[c.ravel()], columns=[f"x{k}" for k in range(X.shape[1])])
    groups = ["participant", "digit"] if digit else ["participant"]
    result = fit_glmm(frame, "y", design, groups, trials="m")
    return result.loglike, np.r_[result.params.to_numpy(),
                                 np.sqrt(result.variance_components.to_numpy())]


@pytest.mark.parametrize("truth, digit, P, seed", [
    pytest.param((0.0, 0.7, 0.5, 0.5), True, 6, 1, id="crossed"),
    pytest.param((0.3, 0.4, 0.0, 0.0), True, 4, 2, id="no-variance-boundary"),
    pytest.param((-0.2, 0.5, 1.2, 0.0), True, 8, 3, id="digit-variance-at-0"),
    pytest.param((0.0, 0.6, 0.8), False, 5, 4, id="participant-only"),
])
def test_fits_reach_fit_glmms_maximum(truth, digit, P, seed):
    """Every study's maximum equals fit_glmm's (boundary decisions included): the same
    log-likelihood to 1e-7 and the same estimates to 1e-3."""
    rng = np.random.default_rng(seed)
    S = 24
    Y, m = _simulate(rng, S, P, 10, X2, np.array(truth[:2]), truth[2],
                     truth[3] if digit else 0.0)
    design = CellDesign(X2, m, digit)
    fit = fit_batch(BatchLaplace(design, Y), np.tile(truth, (S, 1)))
    constant = (gammaln(m + 1) - gammaln(Y + 1) - gammaln(m - Y + 1)).sum(axis=(1, 2, 3))
    checked = 0
    for s in np.flatnonzero(~fit.needs_reference):
        loglike, estimates = _reference_fit(Y[s], m, X2, digit)
        assert fit.value[s] + constant[s] == pytest.approx(loglike, abs=1e-7)
        np.testing.assert_allclose(fit.theta[s], estimates, atol=1e-3)
        assert fit.at_zero[s].any() == bool((estimates[2:] == 0).any())
        checked += 1
    assert checked >= S - 2          # the rest go to fit_glmm itself (study.py)
    if truth[2:] == (0.0, 0.0):
        assert fit.at_zero.any()     # the boundary is met, and decided as fit_glmm does


def test_a_studys_fit_does_not_depend_on_its_batch():
    """The same study alone or among others: the same bits (so any split of the studies
    over workers gives the same answer)."""
    rng = np.random.default_rng(5)
    Y, m = _simulate(rng, 12, 6, 10, X2, np.array([0.0, 0.5]), 0.4, 0.3)
    design = CellDesign(X2, m, True)
    start = np.tile([0.0, 0.5, 0.4, 0.3], (12, 1))
    together = fit_batch(BatchLaplace(design, Y), start)
    for s in (0, 7, 11):
        alone = fit_batch(BatchLaplace(design, Y[s:s + 1]), start[:1])
        assert alone.theta[0].tobytes() == together.theta[s].tobytes()
        assert alone.value[0] == together.value[s]
