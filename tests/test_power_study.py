"""Each simulated study is tested exactly as ``analyze`` tests a dataset; the simulation's
common random numbers; the power against a closed form; parameter recovery.

Outside references: ``primary_test`` (what ``analyze`` runs) for the decisions; the normal
approximation for two proportions (Fleiss, Levin & Paik 2003, Statistical Methods for Rates
and Proportions, 3rd ed., eq. 4.14; Cohen 1988, ch. 6) for the power without random effects.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from crs_study.analysis import primary, primary_fit
from crs_study.analysis.glmm import GlmmFitError, fit_glmm, lrt
from crs_study.power_analysis import PowerDesign, design_from_protocol, model_from_parameters
from crs_study.power_analysis.simulate import simulate_studies
from crs_study.power_analysis.study import (
    FISHER,
    LR,
    SEPARATED,
    WALD,
    PowerTask,
    _expand,
    cells_frame,
    decide_studies,
    decide_trials,
    lr_pvalue,
    run_task,
)


@pytest.fixture(scope="module")
def design():
    return design_from_protocol("digit_identification")


def _analyze_p(design, Y, repetitions, monkeypatch):
    """The primary comparison's p as analyze reports it (primary_test on the 0/1 trials),
    without its profile-likelihood intervals of the odds ratios (Wald ones instead): they
    do not enter the p, and on the maximal model of four participants they cost seconds."""
    monkeypatch.setattr(primary, "_profile_odds", lambda *args: None)
    trials = _expand(cells_frame(design, Y, design.cell_trials(repetitions)))
    result = primary.primary_test(trials, list(design.conditions), design.reference,
                                  design.random_effects, design.method, design.n_quadrature,
                                  design.alpha, **design.model_options())
    return result.comparisons[0]


def test_studies_are_decided_as_analyze_decides_them(design, monkeypatch):
    """Fast path and reference path alike: the p analyze reports, to 1e-6 relative, for
    studies with a variance at 0, ordinary ones and a separated one (CRS at 100 %)."""
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.62},
                                  participant_sd=0.3, digit_sd=0.3)
    Y = simulate_studies(model, 3, range(5), 4, 2)[:, :, -1].astype(float)
    Y[4, :, :, 1] = 2.0                         # every CRS trial of study 4 right
    out = decide_studies(design, Y, 2)
    assert out["kind"][4, 0] == SEPARATED and out["reference"][4]
    assert (out["kind"][:4, 0] == LR).all() and out["boundary"][:4].any()
    for s in range(5):
        comparison = _analyze_p(design, Y[s], 2, monkeypatch)
        assert out["p_value"][s, 0] == pytest.approx(comparison.p_value, rel=1e-6)
        assert (out["p_value"][s, 0] < design.alpha) == (comparison.p_value < design.alpha)


def test_a_full_model_that_cannot_be_fitted_is_fishers_test_as_in_analyze(design,
                                                                          monkeypatch):
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.6},
                                  participant_sd=0.3)
    Y = simulate_studies(model, 1, range(1), 3, 2)[0, :, -1].astype(float)

    def fail(*args, **kwargs):
        raise GlmmFitError("numerical failure (test)")

    monkeypatch.setattr(primary_fit, "fit_model", fail)
    expected = _analyze_p(design, Y, 2, monkeypatch)
    assert expected.method.startswith("Fisher")
    out = decide_trials(design, cells_frame(design, Y, design.cell_trials(2)))
    assert out["kind"][0] == FISHER
    assert out["p_value"][0] == pytest.approx(expected.p_value, rel=1e-12)


def test_a_reduced_model_that_cannot_be_fitted_is_the_wald_p_as_in_analyze(design,
                                                                          monkeypatch):
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.6},
                                  participant_sd=0.3)
    Y = simulate_studies(model, 2, range(1), 3, 2)[0, :, -1].astype(float)
    real = primary_fit.fit_model

    def reduced_fails(data, design_matrix, *args, **kwargs):
        if design_matrix.shape[1] == 1:
            raise GlmmFitError("numerical failure (test)")
        return real(data, design_matrix, *args, **kwargs)

    monkeypatch.setattr(primary_fit, "fit_model", reduced_fails)
    expected = _analyze_p(design, Y, 2, monkeypatch)
    assert expected.p_lr is None and expected.p_wald is not None
    out = decide_trials(design, cells_frame(design, Y, design.cell_trials(2)))
    assert out["kind"][0] == WALD
    assert out["p_value"][0] == pytest.approx(expected.p_value, rel=1e-12)


def test_the_fast_paths_p_is_lrts(design):
    """lr_pvalue of 2 (l_full - l_reduced) equals glmm.lrt's p for the same fits."""
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.56},
                                  participant_sd=0.5, digit_sd=0.4)
    Y = simulate_studies(model, 4, range(3), 6, 5)[:, :, -1].astype(float)
    for s in range(3):
        frame = cells_frame(design, Y[s], design.cell_trials(5))
        full_design = primary.design(frame, list(design.conditions), design.reference)
        groups = ["participant_id", "digit"]
        full = fit_glmm(frame, "correct", full_design, groups, trials="n_trials")
        reduced = fit_glmm(frame, "correct", full_design[["Intercept"]], groups,
                           trials="n_trials")
        test = lrt(full, reduced)
        assert lr_pvalue(np.array([test.statistic]))[0] == pytest.approx(test.pvalue,
                                                                         rel=1e-12)
    assert lr_pvalue(np.array([5e-7, -1e-3]))[0] == 1.0     # below optimiser precision: 0


def test_participant_k_is_the_same_person_at_every_n_and_any_split(design):
    """Common random numbers: a study with N participants is the first N of a larger one,
    the first r repetitions are the same whatever the most asked, and splitting the studies
    over tasks changes nothing."""
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.65},
                                  participant_sd=0.5, digit_sd=0.4)
    big = simulate_studies(model, 9, range(6), 12, 6)
    small = simulate_studies(model, 9, range(6), 5, 3)
    assert np.array_equal(big[:, :5, :3], small)
    parts = np.concatenate([simulate_studies(model, 9, range(0, 2), 12, 6),
                            simulate_studies(model, 9, range(2, 6), 12, 6)])
    assert np.array_equal(parts, big)
    assert not np.array_equal(simulate_studies(model, 10, range(6), 12, 6), big)


def test_simulated_accuracy_is_the_models():
    """Without random effects every trial is correct with the model's probability (exact
    binomial test per condition)."""
    design = PowerDesign(("a", "b"), "a", tuple(range(4)), (None,), 3)
    model = model_from_parameters(design, {"a": 0.3, "b": 0.8}, participant_sd=0.0)
    Y = simulate_studies(model, 1, range(50), 10, 3)[:, :, -1]
    for c, p in ((0, 0.3), (1, 0.8)):
        k, n = int(Y[..., c].sum()), 50 * 10 * 4 * 3
        assert stats.binomtest(k, n, p).pvalue > 0.001


def _two_proportions_power(p0: float, p1: float, n: int, alpha: float) -> float:
    """Normal approximation, n trials per group, two-sided (Fleiss et al. 2003, eq. 4.14)."""
    z = stats.norm.ppf(1 - alpha / 2)
    pbar = (p0 + p1) / 2
    return float(stats.norm.cdf((abs(p1 - p0) * np.sqrt(n) - z * np.sqrt(2 * pbar * (1 - pbar)))
                                / np.sqrt(p0 * (1 - p0) + p1 * (1 - p1))))


def test_without_random_effects_the_power_is_the_two_proportion_formulas(design):
    """No participant or digit variance in the truth: the GLMM's LR test has the power of
    the test of two proportions, within the Monte Carlo error (3 SE) plus 0.02 for the
    variances the GLMM still estimates (each study's SDs are 0 or small). Random intercepts
    and the chi2 p: the formula is a model's without slopes, and the null studies of the
    plan's bootstrap (below 20 participants) would double the cost for a p not checked."""
    design = dataclasses.replace(design, structure="intercepts", p_value="chi2")
    model = model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.6},
                                  participant_sd=0.0, digit_sd=0.0)
    studies = 400
    result = run_task(PowerTask(design, model, 11, (4, 10), (2,), (0, studies)))
    for i, n in enumerate((4, 10)):
        simulated = float((result.p_value[i, :, 0] < design.alpha).mean())
        expected = _two_proportions_power(0.5, 0.6, n * 10 * 2, design.alpha)
        se = np.sqrt(expected * (1 - expected) / studies)
        assert abs(simulated - expected) < 3 * se + 0.02, (n, simulated, expected)


def test_the_fits_recover_the_generating_parameters(design):
    """Mean estimates over 400 studies of 40 participants within 2 SE, random intercepts:
    the fixed effects and the participant variance of the truth, the digit variance of the
    truth times (G - 1) / G with G = 10 digits, the first-order downward bias of a
    maximum-likelihood variance (Searle, Casella & McCulloch 1992, Variance Components,
    sec. 3.7; with 40 participants that bias, 0.6 % of the variance, is within the Monte
    Carlo error). 400 studies: the digit variance without its factor, 10 % too high, is
    2.8 SE off (measured), a fixed effect or an SD off by a tenth more than ten."""
    design = dataclasses.replace(design, structure="intercepts")
    model = model_from_parameters(design, log_odds={"pixel-only": -0.2, "crs": 0.5},
                                  participant_sd=0.5, digit_sd=0.6)
    studies = 400
    result = run_task(PowerTask(design, model, 21, (40,), (5,), (0, studies)))
    estimates = result.theta[0][:, [0, 1, 2, 4]].copy()       # no slopes in this model
    assert np.isfinite(estimates).all() and not result.reference.any()
    assert (result.theta[0][:, [3, 5]] == 0).all()
    estimates[:, 2:] **= 2                                   # SDs to variances
    mean = estimates.mean(axis=0)
    se = estimates.std(axis=0, ddof=1) / np.sqrt(studies)
    expected = np.array([-0.2, 0.7, 0.5**2, 0.6**2 * 9 / 10])
    assert np.all(np.abs(mean - expected) < 2 * se), (mean, expected, se)


@pytest.mark.slow
def test_the_maximal_fits_recover_the_random_slopes(design):
    """The plan's maximal model, singular fits kept: mean estimates over 300 studies of 30
    participants within 2.5 SE of the truth, every variance times its first-order ML factor
    (G - 1) / G (G = 30 participants, 10 digits; Searle, Casella & McCulloch 1992, sec. 3.7)
    (with slopes the factor is that of each variance of a balanced design's covariance)."""
    design = dataclasses.replace(design, singular_fit="keep")
    model = model_from_parameters(design, log_odds={"pixel-only": -0.2, "crs": 0.5},
                                  participant_sd=0.5, digit_sd=0.5, participant_slope_sd=0.6,
                                  participant_correlation=0.3, symbol_slope_sd=0.4)
    studies = 300
    result = run_task(PowerTask(design, model, 22, (30,), (5,), (0, studies)))
    estimates = result.theta[0].copy()
    assert np.isfinite(estimates).all() and not result.reduced.any()
    estimates[:, 2:] **= 2
    mean = estimates.mean(axis=0)
    se = estimates.std(axis=0, ddof=1) / np.sqrt(studies)
    expected = np.array([-0.2, 0.7, 0.5**2 * 29 / 30, 0.6**2 * 29 / 30, 0.5**2 * 9 / 10,
                         0.4**2 * 9 / 10])
    assert np.all(np.abs(mean - expected) < 2.5 * se), (mean, expected, se)


def test_three_conditions_each_tested_against_the_reference_as_analyze_does():
    """Two comparisons per study, each the LR test of dropping its own coefficient. Random
    intercepts: what is tested is the comparisons; the maximal model's two 3 x 3 covariances
    on five participants and five digits are mostly singular, so most studies would go the
    reference path and the fast path's comparisons would go untested."""
    design = PowerDesign(("a", "b", "c"), "a", tuple(range(5)), (None,), 2,
                         structure="intercepts")
    model = model_from_parameters(design, {"a": 0.5, "b": 0.6, "c": 0.7},
                                  participant_sd=0.4, digit_sd=0.3)
    Y = simulate_studies(model, 8, range(6), 5, 2)[:, :, -1].astype(float)
    out = decide_studies(design, Y, 2)
    assert (~out["reference"]).sum() >= 4 and (out["kind"] == LR).all()
    for s in range(6):
        expected = decide_trials(design, cells_frame(design, Y[s], design.cell_trials(2)))
        np.testing.assert_allclose(out["p_value"][s], expected["p_value"], rtol=1e-6)
        np.testing.assert_allclose(out["log_odds"][s], expected["log_odds"], atol=1e-4)


def test_a_studys_outcome_does_not_depend_on_how_the_studies_are_split(design):
    """Studies 0-2 as one unit of work or as two: the same bits at every point, the null
    studies of the plan's bootstrap too (each study's fits start from its own numbers only,
    the next N's from its own curvature, so any chunking gives the same answer)."""
    model = model_from_parameters(design, {"pixel-only": 0.45, "crs": 0.6},
                                  participant_sd=0.4, digit_sd=0.3)
    points = dict(participants=(4, 6), repetitions=(1, 2))
    whole = run_task(PowerTask(design, model, 3, studies=(0, 3), **points))
    parts = [run_task(PowerTask(design, model, 3, studies=s, **points))
             for s in ((0, 1), (1, 3))]
    assert np.isfinite(whole.null_statistic).any()
    for key in ("p_value", "theta", "loglike", "loglike_reduced", "boundary", "reference",
                "null_statistic"):
        joined = np.concatenate([getattr(p, key) for p in parts], axis=1)
        assert np.array_equal(joined, getattr(whole, key), equal_nan=True), key


def test_near_singular_studies_are_settled_by_the_batch_at_fit_glmms_maximum(design):
    """Twelve participants of the shipped protocol, where the maximal model is often near
    singular: the batched fits settle all but a few studies (a face whose free diagonal
    starts at 0 once stalled them, and an interior iteration that crawled toward a face
    rising inward is restarted from it, as ``fit_glmm`` restarts), each at the maximum of
    the full model that ``fit_primary`` reaches to 1e-6."""
    model = model_from_parameters(design, {"pixel-only": 0.453, "crs": 0.676},
                                  participant_sd=0.42, digit_sd=0.29)
    R = design.repetitions
    Y = simulate_studies(model, 7, range(20), 12, R)[:, :, R - 1].astype(float)
    out = decide_studies(design, Y, R)
    assert out["reference"].sum() <= 1
    assert out["boundary"].sum() >= 8
    for s in np.flatnonzero(~out["reference"]):
        expected = decide_trials(design, cells_frame(design, Y[s], design.cell_trials(R)))
        assert out["loglike"][s] == pytest.approx(expected["loglike"], abs=1e-6)
