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
