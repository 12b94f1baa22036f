"""Parameter recovery: data simulated from known values are fitted back at the nominal rate.

The design is the study's: participants x trials, two conditions within participants, a random
intercept per participant (and per digit for the crossed model). Seeds are fixed, so each test
is deterministic; the tolerances are what sampling variability allows, so a wrong standard error
or a biased estimator fails them.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import stats

from crs_study.analysis.glmm import fit_glmm, lrt, profile_sd_conf_int
from crs_study.analysis.glmm_simulate import simulate_trials

INTERCEPT, EFFECT, VARIANCE = 0.3, 0.8, 0.5


def _fits(n_seeds: int, method: str, **design):
    out = []
    for seed in range(n_seeds):
        df = simulate_trials(np.random.default_rng(seed), design.get("participants", 20),
                             design.get("trials", 50), [INTERCEPT, INTERCEPT + EFFECT], VARIANCE)
        out.append(fit_glmm(df, "correct", "condition", "participant", method=method))
    return out


def _binomial_band(n: int, level: float = 0.95, width: float = 3.0) -> tuple[int, int]:
    """Counts within ``width`` binomial standard deviations of ``n * level``."""
    sd = np.sqrt(n * level * (1 - level))
    return int(np.floor(n * level - width * sd)), int(np.ceil(n * level + width * sd))


@pytest.mark.slow
def test_wald_interval_covers_condition_effect_at_nominal_rate():
    # 200 datasets of 20 participants x 100 trials (50 per condition): the 95 % Wald interval
    # of the condition effect must cover the true 0.8 in 95 % +- 3 binomial sd (181..199).
    fits = _fits(200, "laplace")
    assert all(f.converged and not f.warnings for f in fits)
    ci = np.array([f.conf_int().iloc[1].to_numpy() for f in fits])
    covered = int(np.sum((ci[:, 0] <= EFFECT) & (EFFECT <= ci[:, 1])))
    low, high = _binomial_band(200)
    assert low <= covered <= high, f"coverage {covered}/200 outside {low}..{high}"
    # unbiased: the mean estimate within 3 standard errors of the mean of the truth
    effects = np.array([f.params.iloc[1] for f in fits])
    assert abs(effects.mean() - EFFECT) < 3 * effects.std(ddof=1) / np.sqrt(len(effects))
    # the model standard error matches the spread of the estimates across datasets (+-15 %)
    mean_se = np.mean([f.bse.iloc[1] for f in fits])
    assert mean_se == pytest.approx(effects.std(ddof=1), rel=0.15)
    # the ML variance is biased low by about (J - 1)/J for J = 20 groups, plus the Laplace
    # error: "unbiased-ish" = the mean within 15 % of the truth
    variances = np.array([f.variance_components.iloc[0] for f in fits])
    assert variances.mean() == pytest.approx(VARIANCE, rel=0.15)
    # the intercept (a between-participant quantity) is covered less well with 20 groups;
    # still within the band a Wald interval with an estimated variance reaches
    intercepts = np.array([f.conf_int().iloc[0].to_numpy() for f in fits])
    covered0 = int(np.sum((intercepts[:, 0] <= INTERCEPT) & (INTERCEPT <= intercepts[:, 1])))
    assert covered0 >= _binomial_band(200, 0.93)[0]


@pytest.mark.parametrize(("sd", "n_datasets"), [
    pytest.param(0.7, 60, id="sd-0.7"),
    pytest.param(0.25, 40, id="sd-0.25-near-the-boundary"),
])
def test_sd_profile_interval_covers_the_true_sd(sd, n_datasets):
    # 12 participants x 40 trials (20 per condition), a random intercept of known SD. The
    # profile interval (lower end 0 when the profile at 0 is within the cutoff) must cover
    # the true SD at about the nominal rate: measured over 300 datasets of this shape (with
    # intercept 0), 94.0 % at SD 0.7 and 98.3 % at SD 0.25, where 84 % of the intervals start
    # at 0 (here: 54/60 and 37/40, 34 from 0). With the boundary the plain
    # chi2(1) cutoff is conservative, as in lme4). Accepted: coverage no lower than 3 binomial
    # standard deviations below 95 % (n_datasets is small to keep the test fast: 0.1 s a fit
    # and its profile).
    covered, from_zero = 0, 0
    for seed in range(n_datasets):
        df = simulate_trials(np.random.default_rng(3000 + seed), 12, 20,
                             [INTERCEPT, INTERCEPT + EFFECT], sd**2)
        fit = fit_glmm(df, "correct", "condition", "participant")
        _, low, high = profile_sd_conf_int(fit).iloc[0]
        covered += low <= sd <= high
        from_zero += low == 0.0
    low_count, _ = _binomial_band(n_datasets)
    assert covered >= low_count, f"coverage {covered}/{n_datasets} below {low_count}"
    if sd < 0.5:
        assert from_zero > n_datasets / 2          # the boundary rule is what is exercised


def test_agq_recovers_the_same_values():
    fits = _fits(40, "agq")
    laplace = _fits(40, "laplace")
    effects = np.array([f.params.iloc[1] for f in fits])
    assert abs(effects.mean() - EFFECT) < 3 * effects.std(ddof=1) / np.sqrt(len(effects))
    # with 50 Bernoulli trials per participant and condition, Laplace is close to AGQ
    for a, b in zip(fits, laplace, strict=True):
        assert a.params.iloc[1] == pytest.approx(b.params.iloc[1], abs=0.01)
        assert a.variance_components.iloc[0] >= b.variance_components.iloc[0] - 1e-3


def test_crossed_model_recovers_both_variances():
    est = []
    for seed in range(30):
        df = simulate_trials(np.random.default_rng(1000 + seed), 20, 40, [0.0, 0.8], 0.5,
                             n_digits=10, digit_variance=0.3)
        r = fit_glmm(df, "correct", "condition", ["participant", "digit"])
        assert r.converged
        est.append([r.params.iloc[1], *r.variance_components.to_numpy()])
    est = np.array(est)
    se = est.std(axis=0, ddof=1) / np.sqrt(len(est))
    assert abs(est[:, 0].mean() - 0.8) < 3 * se[0]
    assert est[:, 1].mean() == pytest.approx(0.5, rel=0.2)
    # 10 digits: the ML variance is biased low by about 10 %; allow 35 %
    assert est[:, 2].mean() == pytest.approx(0.3, rel=0.35)


def test_lrt_size_for_a_null_condition_effect():
    # Under no condition effect the LRT p-values are uniform: about 5 % below .05.
    pvalues = []
    for seed in range(60):
        df = simulate_trials(np.random.default_rng(500 + seed), 15, 30, [0.4, 0.4], VARIANCE)
        full = fit_glmm(df, "correct", "condition", "participant")
        reduced = fit_glmm(df, "correct", "1", "participant")
        pvalues.append(lrt(full, reduced).pvalue)
    assert stats.kstest(pvalues, "uniform").pvalue > 0.01


def test_speed_40_participants_400_trials():
    # Least we accept: the GLMM on 40 participants x 400 trials (16,000 rows) within 2 s.
    df = simulate_trials(np.random.default_rng(11), 40, 200, [0.0, 0.7], VARIANCE)
    assert len(df) == 16_000
    start = time.monotonic()
    r = fit_glmm(df, "correct", "condition", "participant")
    assert time.monotonic() - start < 2.0
    assert r.converged and r.params.iloc[1] == pytest.approx(0.7, abs=0.15)
