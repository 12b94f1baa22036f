"""The fit's start read off the data (empirical logits and moments): a valid start anywhere,
and the maximum it leads to is never below the one lme4's start (beta 0, every loading the
identity) leads to."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis.glmm import fit_glmm
from crs_study.analysis.glmm_laplace import TermRows
from crs_study.analysis.glmm_optimise import maximise
from crs_study.analysis.glmm_simulate import simulate_cells, slope_covariance
from crs_study.analysis.glmm_start import MIN_START_SD, moment_start
from crs_study.analysis.glmm_terms import RandomTerm, ThetaLayout, loading

MAXIMAL = "(1 + c | participant_id) + (1 + c | digit)"


def _cells(seed: int, participants: int, slope_sd: float, rho: float, digit_slope: float,
           repetitions: int = 6):
    cells = simulate_cells(np.random.default_rng(seed), participants, 8, repetitions,
                           [0.0, 0.7], slope_covariance(0.7, slope_sd, rho),
                           slope_covariance(0.3, digit_slope))
    return cells.assign(c=(cells["condition"] == "c1").astype(float))


def _start_of(result):
    lik, layout = result._model.problem.model.likelihood, result._model.problem.model.layout
    return moment_start(lik.X, lik.Y[0], lik.m, lik.terms, layout), layout


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 9), st.sampled_from([0.0, 0.6, 1.5]),
       st.sampled_from([-0.9, 0.0, 0.9]), st.sampled_from([1, 3]), st.booleans(),
       st.booleans())
def test_the_start_is_finite_and_off_every_boundary(seed, participants, slope_sd, rho,
                                                     repetitions, correlated, separated):
    cells = _cells(seed, participants, slope_sd, rho, 0.0, repetitions)
    if separated:          # cells all correct or all wrong: logits bounded by the 1/2
        cells["correct"] = np.where(cells["condition"] == "c1", cells["n_trials"], 0)
    X = np.column_stack([np.ones(len(cells)), cells["c"].to_numpy()])
    terms = [RandomTerm("participant_id", ("Intercept", "c"), correlated),
             RandomTerm("digit", ("Intercept", "c"))]
    rows = [TermRows(*_codes(cells[t.group]), X) for t in terms]
    layout = ThetaLayout(2, terms)
    start = moment_start(X, cells["correct"].to_numpy(float),
                         cells["n_trials"].to_numpy(float), rows, layout)
    assert start.shape == (layout.size,) and np.all(np.isfinite(start))
    for term, cut in zip(layout.terms, layout.slices, strict=True):
        T = loading(term, start[cut])
        assert np.all(np.diag(T) >= MIN_START_SD - 1e-12), (term.label(), T)
        if not term.correlated:
            assert np.count_nonzero(T - np.diag(np.diag(T))) == 0


def _codes(column):
    codes, levels = pd.factorize(column, sort=True)
    return codes.astype(np.intp), len(levels)


@pytest.mark.parametrize("seed, participants, slope_sd, rho, digit_slope", [
    (1, 6, 0.6, 0.3, 0.0), (2, 12, 1.0, -0.5, 0.2), (3, 24, 0.0, 0.0, 0.0),
    (4, 8, 1.5, 0.9, 0.3), (5, 16, 0.3, -0.9, 0.0), (6, 4, 0.6, 0.0, 0.0)])
def test_the_maximum_is_not_below_the_one_from_lme4s_start(seed, participants, slope_sd, rho,
                                                            digit_slope):
    cells = _cells(seed, participants, slope_sd, rho, digit_slope)
    result = fit_glmm(cells, "correct", "c", random=MAXIMAL, trials="n_trials")
    problem = result._model.problem
    lme4_start = np.r_[np.zeros(problem.n_fixed), problem.model.layout.start()]
    from_lme4s = maximise(problem, lme4_start)
    kernel = problem.objective(np.asarray(result._model.theta), grad=False)
    assert kernel >= from_lme4s.value - 1e-6
    start, _ = _start_of(result)
    # and the start is nearer the maximum than lme4's
    assert problem.objective(start, grad=False) > problem.objective(lme4_start, grad=False)
