"""The batched fits (glmm_batch) against fit_glmm, the single fit checked against lme4.

Outside reference: ``fit_glmm`` reaches lme4's and glmmTMB's maximum on the parity corpora
(tests/test_glmm_lme4_corpus.py, tests/test_glmm_slopes_corpus.py); here the batched Newton
fits of many studies must reach the same maximum, boundary decisions included (a slope's
variance at 0, a correlation at +-1), and a study's answer must not depend on its batch.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.special import gammaln

from crs_study.analysis.glmm import fit_glmm
from crs_study.analysis.glmm_batch import BatchObjective, fit_batch, study_fit
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows
from crs_study.analysis.glmm_newton import newton
from crs_study.analysis.glmm_simulate import simulate_cells, slope_covariance
from crs_study.analysis.glmm_terms import RandomTerm, ThetaLayout

P, D = 8, 6
TERMS = {"maximal": [RandomTerm("participant_id", ("Intercept", "c")),
                     RandomTerm("digit", ("Intercept", "c"))],
         "uncorrelated": [RandomTerm("participant_id", ("Intercept", "c"), False),
                          RandomTerm("digit", ("Intercept", "c"), False)]}
TEXT = {"maximal": "(1 + c | participant_id) + (1 + c | digit)",
        "uncorrelated": "(1 + c || participant_id) + (1 + c || digit)"}


def _studies(n: int, slope_sd: float, seed: int):
    frames = [simulate_cells(np.random.default_rng(seed + s), P, D, 6, [0.0, 0.6],
                             slope_covariance(0.7, slope_sd, 0.4),
                             slope_covariance(0.3, 0.0)) for s in range(n)]
    return [f.assign(c=(f["condition"] == "c1").astype(float)) for f in frames]


def _objective(frames, structure: str) -> BatchObjective:
    first = frames[0]
    X = np.column_stack([np.ones(len(first)), first["c"].to_numpy()])
    codes = pd.factorize(first["participant_id"], sort=True)[0]
    rows = [TermRows(codes, P, X), TermRows(first["digit"].to_numpy(), D, X)]
    Y = np.array([f["correct"].to_numpy() for f in frames])
    likelihood = LaplaceLikelihood(X, first["n_trials"].to_numpy(), Y, rows)
    return BatchObjective(likelihood, ThetaLayout(2, TERMS[structure]))


@pytest.mark.parametrize("structure", ["maximal", "uncorrelated"])
@pytest.mark.parametrize("slope_sd", [0.0, 0.8])
def test_every_study_reaches_fit_glmms_maximum(structure, slope_sd):
    frames = _studies(8, slope_sd, 300 if slope_sd else 400)
    objective = _objective(frames, structure)
    n = objective.layout.size
    fit = fit_batch(objective, np.tile(np.r_[0.0, 0.5, np.full(n - 2, 0.5)], (8, 1)))
    boundary = 0
    for s, frame in enumerate(frames):
        single = fit_glmm(frame, "correct", "c", random=TEXT[structure], trials="n_trials")
        if fit.needs_reference[s]:
            continue
        m, y = frame["n_trials"].to_numpy(), frame["correct"].to_numpy()
        constant = np.sum(gammaln(m + 1) - gammaln(y + 1) - gammaln(m - y + 1))
        assert fit.value[s] + constant == pytest.approx(single.loglike, abs=1e-6)
        np.testing.assert_allclose(fit.theta[s, :2], single.params.to_numpy(), atol=2e-4)
        summary = study_fit(fit, objective, s)
        assert len(summary.faces) == len(single.faces)
        boundary += bool(single.faces)
        assert [f.kind for f in summary.faces] == [f.kind for f in single.faces]
    assert fit.needs_reference.sum() <= 1
    if slope_sd == 0.0:
        assert boundary >= 4          # the digit's slope, absent from the data, hits 0


def test_a_study_is_fitted_alike_alone_and_in_a_batch():
    """Each study iterates and stops on its own, and no product sums across studies: the
    same bits alone and in a batch."""
    frames = _studies(5, 0.6, 500)
    start = np.tile(np.r_[0.0, 0.5, 0.5, 0.0, 0.5, 0.5, 0.0, 0.5], (5, 1))
    together = fit_batch(_objective(frames, "maximal"), start)
    for s in range(5):
        alone = fit_batch(_objective(frames[s:s + 1], "maximal"), start[:1])
        assert alone.theta[0].tobytes() == together.theta[s].tobytes()
        assert alone.value[0] == together.value[s]


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_face_fit_moves_a_free_diagonal_that_starts_at_zero(sign):
    """On the rank-one face of a correlated term (its second column held at 0) the loading's
    first column ``(a, b)`` is free: ``a`` at 0 is the intercept's SD at 0 with the slope's
    at ``|b|``, an ordinary point of the face that a step may cross (the correlation then
    turns from +1 to -1). Newton's method from ``a`` = 1e-38 must not treat it as a boundary
    (each step shortened to a tenth of ``a``: a stall at the start, as found in power runs).
    From either sign of ``a`` one of the two directions is across zero."""
    frames = _studies(1, 0.8, 300)
    objective = _objective(frames, "maximal")
    n = objective.layout.size
    fit = fit_batch(objective, np.tile(np.r_[0.0, 0.5, np.full(n - 2, 0.5)], (1, 1)))
    start = fit.theta.copy()
    start[0, 5:8] = [sign * 1e-38, 0.2, 0.0]                # the digits' (1 + c | digit) loading
    held = np.zeros((1, n), dtype=bool)
    held[0, 7] = True
    theta, value, converged, iterations, _ = newton(objective, start, held)
    assert converged[0] and iterations[0] < 20
    assert abs(theta[0, 5]) > 1e-6 or abs(theta[0, 6]) > 1e-6     # it moved off the start
    _, gradient = objective.evaluate(theta)
    assert np.max(np.abs(gradient[0, ~held[0]])) < 1e-5


def test_only_a_correlated_term_on_a_face_has_diagonals_that_may_cross_zero():
    layout = ThetaLayout(2, TERMS["maximal"])
    held = np.zeros((2, layout.size), dtype=bool)
    held[1, 7] = True                                 # study 1: the digits' term on a face
    marks = layout.diagonals(held)
    assert marks[0].tolist() == layout.diagonal.tolist()
    assert marks[1].tolist() == [False, False, True, False, True, False, False, False]


def test_stacked_gradients_are_each_studys_own_evaluation():
    """The points of a differenced Hessian, every study's in one pass: the same bits as each
    point evaluated alone from its study's warm start, and the warm starts left as they
    were."""
    frames = _studies(3, 0.6, 700)
    objective = _objective(frames, "maximal")
    n = objective.layout.size
    centre = np.tile(np.r_[0.1, 0.5, 0.6, 0.1, 0.4, 0.3, 0.0, 0.2], (3, 1))
    objective.evaluate(centre)
    warm = objective.warm.copy()
    rows = np.array([0, 1, 2, 0, 2])
    points = centre[rows] + 1e-5 * np.eye(n)[[0, 3, 5, 7, 2]]
    stacked = objective.gradients(points, rows)
    np.testing.assert_array_equal(objective.warm, warm)
    for i, s in enumerate(rows):
        alone = objective.subset([s])
        _, g = alone.evaluate(points[i:i + 1])
        np.testing.assert_array_equal(stacked[i], g[0])
