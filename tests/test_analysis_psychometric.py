"""Psychometric functions: parameter recovery, thresholds, skipping without a varied level."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from crs_study.analysis.psychometric import (
    analyse_psychometric,
    fit_counts,
    psi,
    threshold_level,
)


@pytest.mark.parametrize(("function", "alpha", "beta"), [
    pytest.param("logistic", 1.0, 4.0, id="logistic"),
    pytest.param("logistic", 1.0, -4.0, id="logistic-falling"),
    pytest.param("weibull", 1.0, 3.0, id="weibull"),
])
def test_fit_recovers_known_parameters(function, alpha, beta):
    levels = np.linspace(0.4, 1.6, 7)
    n = np.full(levels.size, 4000)
    rng = np.random.default_rng(9)
    k = rng.binomial(n, psi(levels, function, alpha, beta, 0.1, 0.04))
    a, b, lam, _ = fit_counts(levels, n, k, function, 0.1, 0.1)
    assert a == pytest.approx(alpha, abs=0.05)
    assert b == pytest.approx(beta, rel=0.15)
    assert lam == pytest.approx(0.04, abs=0.02)


def test_threshold_is_where_f_reaches_the_criterion():
    for function, a, b in (("logistic", 1.2, 3.0), ("weibull", 1.2, 3.0)):
        level = threshold_level(function, a, b, 0.75)
        # psi at the threshold = guess + (1 - guess - lapse) * 0.75
        assert psi(np.array([level]), function, a, b, 0.1, 0.0)[0] == pytest.approx(
            0.1 + 0.9 * 0.75)


def _trials(seed=1):
    rng = np.random.default_rng(seed)
    rows = []
    for condition, shift in (("pixel-only", 0.0), ("crs", -0.3)):
        for level in (0.5, 0.75, 1.0, 1.25, 1.5):
            p = psi(np.array([level]), "logistic", 1.0 + shift, 6.0, 0.1, 0.02)[0]
            for _ in range(150):
                rows.append({"participant_id": "p", "condition": condition,
                             "digit_height": level, "correct": float(rng.random() < p)})
    return pd.DataFrame(rows)


def test_analysis_per_condition_with_seeded_bootstrap():
    trials = _trials()
    result = analyse_psychometric(trials, ["pixel-only", "crs"], 0.1, n_bootstrap=40, seed=2)
    assert result.level_column == "digit_height" and not result.skipped
    pixel, crs = result.fits["pixel-only"], result.fits["crs"]
    assert crs.threshold < pixel.threshold
    for fit, truth in ((pixel, 1.0), (crs, 0.7)):
        assert fit.threshold_ci95[0] < fit.threshold < fit.threshold_ci95[1]
        assert fit.threshold == pytest.approx(truth, abs=0.1)
    again = analyse_psychometric(trials, ["pixel-only", "crs"], 0.1, n_bootstrap=40, seed=2)
    assert again.fits["crs"].threshold_ci95 == crs.threshold_ci95


def test_without_a_varied_level_it_is_skipped_with_a_note():
    trials = _trials().drop(columns="digit_height")
    result = analyse_psychometric(trials, ["crs"], 0.1)
    assert result.skipped and "no stimulus level varies" in result.note
    flat = _trials().assign(digit_height=1.0)
    assert analyse_psychometric(flat, ["crs"], 0.1).skipped


def test_too_few_levels_skip_that_condition_with_a_warning():
    trials = _trials()
    trials = trials.loc[trials["digit_height"].isin([0.5, 1.5])]
    result = analyse_psychometric(trials, ["crs"], 0.1, n_bootstrap=0)
    assert not result.fits and any("a fit needs 3 or more" in w for w in result.warnings)
    assert result.skipped and "no condition has 3 or more levels" in result.note


def test_a_flat_function_warns_and_reports_no_threshold():
    """No level effect (accuracy 0.6 at every level): the fit's alpha is an extrapolation
    (before this check it reported a 'threshold' of -0.3 on levels 1..6); now the slope's
    likelihood-ratio test (statsmodels binomial GLM, chi2(1)) is not significant, so no
    threshold or interval is reported and a warning says why."""
    rng = np.random.default_rng(3)
    levels = np.repeat([1.0, 2, 3, 4, 5, 6], 60)
    trials = pd.DataFrame({"condition": "crs", "digit_height": levels,
                           "correct": (rng.random(levels.size) < 0.6).astype(int)})
    result = analyse_psychometric(trials, ["crs"], 0.1, n_bootstrap=20)
    fit = result.fits["crs"]
    assert np.isnan(fit.threshold) and fit.threshold_ci95 is None
    assert fit.to_dict()["threshold"] is None
    assert any("does not change with 'digit_height'" in w and "no threshold" in w
               for w in result.warnings)


def test_level_effect_pvalue_matches_a_hand_likelihood_ratio():
    """LR slope test against scipy: the GLM log-likelihood maximised directly."""
    from scipy import optimize, stats
    from scipy.special import expit

    from crs_study.analysis.psychometric import level_effect_pvalue

    levels, n, k = np.array([1.0, 2, 3, 4]), np.array([30, 30, 30, 30]), np.array([8, 12, 17, 22])

    def nll(b):
        p = expit(b[0] + b[1] * levels)
        return -np.sum(k * np.log(p) + (n - k) * np.log1p(-p))

    full = -optimize.minimize(nll, [0.0, 0.0], method="Nelder-Mead",
                              options={"xatol": 1e-10, "fatol": 1e-12}).fun
    p0 = k.sum() / n.sum()
    null = np.sum(k * np.log(p0) + (n - k) * np.log1p(-p0))
    expected = stats.chi2.sf(2 * (full - null), 1)
    assert level_effect_pvalue(levels, n, k) == pytest.approx(expected, rel=1e-4)
    assert level_effect_pvalue(levels, n, np.zeros(4)) == 1.0
    separated = level_effect_pvalue(levels, n, np.array([0, 0, 30, 30]))
    assert 0.0 < separated < 1e-10


@pytest.mark.parametrize(("k", "best"), [
    pytest.param([6, 8, 9, 10, 7, 10], -24.7654, id="lapse-near-its-bound"),
    pytest.param([1, 2, 9, 8, 10, 10], -18.8537, id="steep"),
])
def test_three_starts_reach_the_best_of_many(k, best):
    # Weibull fits of 10 trials at each of six levels, guess 0.1, lapse <= 0.1: data where one
    # start from the grid (at lapse 0.02) stopped in a local optimum with the lapse at 0,
    # 0.23 and 0.52 log-likelihood units short, with L-BFGS-B as with TNC. The fit must reach
    # the best of 36 starts spread over the parameter space.
    levels, n = np.array([1.0, 1.5, 2.0, 2.5, 3.0, 4.0]), np.full(6, 10)
    fitted = fit_counts(levels, n, np.array(k), "weibull", 0.1, 0.1)
    reference = max(fit_counts(levels, n, np.array(k), "weibull", 0.1, 0.1,
                               start=(a0, b0, lam0))[3]
                    for a0 in (1.0, 2.5, 4.0) for b0 in (0.5, 2.0, 8.0, 20.0)
                    for lam0 in (0.0, 0.05, 0.1))
    assert fitted[3] == pytest.approx(best, abs=1e-4)
    assert fitted[3] >= reference - 1e-6


def test_a_lapse_rate_at_its_bound_is_warned_about():
    # accuracy levels off at 80 %: the lapse rate wants 0.2, the plan allows 0.05
    rows = [{"participant_id": "p", "condition": "crs", "digit_height": level,
             "correct": float(i < round(150 * float(psi(np.array([level]), "logistic", 1.0,
                                                        8.0, 0.1, 0.2)[0])))}
            for level in (0.5, 0.75, 1.0, 1.25, 1.5, 2.0) for i in range(150)]
    result = analyse_psychometric(pd.DataFrame(rows), ["crs"], 0.1, lapse_max=0.05,
                                  n_bootstrap=0)
    assert result.fits["crs"].lapse == pytest.approx(0.05, rel=1e-3)
    assert any("the lapse rate sits at its upper bound 0.05" in w for w in result.warnings)
    relaxed = analyse_psychometric(pd.DataFrame(rows), ["crs"], 0.1, lapse_max=0.3,
                                   n_bootstrap=0)
    assert relaxed.fits["crs"].lapse == pytest.approx(0.2, abs=0.03)
    assert not any("upper bound" in w for w in relaxed.warnings)
