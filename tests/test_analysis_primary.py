"""The primary test: GLMM odds ratios with Wald and likelihood-ratio p-values, fallbacks."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from crs_study.analysis import glmm, primary_fit
from crs_study.analysis.glmm import MAX_QUADRATURE, GlmmFitError
from crs_study.analysis.plan import AnalysisPlan
from crs_study.analysis.primary import design, primary_test
from crs_study.errors import AnalysisError, PlanError


def _trials(n_participants=12, n_per_cell=40, accuracy=None, seed=0, sd=0.5):
    accuracy = accuracy or {"pixel-only": 0.5, "crs": 0.68}
    rng = np.random.default_rng(seed)
    rows = []
    for p in range(n_participants):
        u = rng.normal(0, sd)
        for condition, acc in accuracy.items():
            eta = np.log(acc / (1 - acc)) + u
            for i in range(n_per_cell):
                rows.append({"participant_id": f"p{p:02d}", "condition": condition,
                             "digit": i % 10,
                             "correct": float(rng.random() < 1 / (1 + np.exp(-eta)))})
    return pd.DataFrame(rows)


def test_design_is_treatment_coded_against_the_reference():
    trials = pd.DataFrame({"condition": ["crs", "pixel-only", "x"]})
    matrix = design(trials, ["pixel-only", "crs", "x"], "pixel-only")
    assert list(matrix.columns) == ["Intercept", "condition[crs]", "condition[x]"]
    assert matrix.to_numpy().tolist() == [[1, 1, 0], [1, 0, 0], [1, 0, 1]]


def test_odds_ratio_interval_and_both_p_values():
    trials = _trials(n_participants=20, n_per_cell=60, seed=1)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    (comparison,) = result.comparisons
    true_or = (0.68 / 0.32) / (0.5 / 0.5)                       # 2.125, conditional on u
    assert comparison.ci95[0] < true_or < comparison.ci95[1]
    assert comparison.estimate == pytest.approx(np.exp(comparison.log_odds))
    assert comparison.p_value == comparison.p_lr and comparison.p_wald < 1e-6
    assert comparison.method.startswith(
        "GLMM correct ~ condition + (1 + condition | participant)")
    assert result.model["variance_components"]["participant_id:Intercept"] > 0
    # the truth has no slope variance: the maximal fit is singular, kept, and said so
    assert result.omnibus is None and all("singular" in w for w in result.warnings)


def test_three_conditions_get_an_omnibus_test():
    trials = _trials(n_participants=10, n_per_cell=30, seed=2,
                     accuracy={"pixel-only": 0.5, "crs": 0.7, "crs-opt": 0.75})
    result = primary_test(trials, ["pixel-only", "crs", "crs-opt"], "pixel-only")
    assert [c.condition for c in result.comparisons] == ["crs", "crs-opt"]
    assert result.omnibus["df"] == 2 and 0 < result.omnibus["p_value"] < 0.05


def test_a_single_condition_gives_no_comparison_but_a_warning():
    trials = _trials()
    result = primary_test(trials.loc[trials["condition"] == "crs"], ["crs"], "crs")
    assert result.comparisons == () and "primary test not run" in result.warnings[0]


def test_a_failing_model_falls_back_to_fisher_with_a_warning(monkeypatch):
    def broken(*args, **kwargs):
        raise GlmmFitError("singular design")

    monkeypatch.setattr(primary_fit, "fit_model", broken)
    trials = _trials(seed=3)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    (comparison,) = result.comparisons
    assert comparison.method.startswith("Fisher's exact test")
    assert "could not be fitted (singular design)" in result.warnings[0]
    counts = trials.groupby("condition")["correct"].agg(["sum", "size"])
    a, n1 = counts.loc["crs"]
    c, n0 = counts.loc["pixel-only"]
    assert comparison.estimate == pytest.approx(a * (n0 - c) / ((n1 - a) * c))
    assert 0 < comparison.p_value < 1
    # a zero cell (crs always right): Haldane-Anscombe +0.5 on every cell, Woolf interval
    # by hand: OR = (n1 + .5)(n0 - c + .5) / (.5 (c + .5)), se = sqrt(sum 1 / cell)
    trials.loc[trials["condition"] == "crs", "correct"] = 1.0
    (comparison,) = primary_test(trials, ["pixel-only", "crs"], "pixel-only").comparisons
    cells = np.array([n1 + 0.5, 0.5, c + 0.5, n0 - c + 0.5])
    log_or = np.log(cells[0] * cells[3] / (cells[1] * cells[2]))
    se = np.sqrt((1 / cells).sum())
    assert comparison.estimate == pytest.approx(np.exp(log_or))
    assert comparison.ci95 == pytest.approx((np.exp(log_or - 1.959964 * se),
                                             np.exp(log_or + 1.959964 * se)), rel=1e-6)


def test_crossed_digit_effect_is_fitted_when_planned():
    trials = _trials(n_participants=8, n_per_cell=30, seed=4)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only",
                          random_effects=("participant", "digit"), structure="intercepts")
    assert set(result.model["variance_components"]) == {"participant_id", "digit"}
    assert "(1 | digit)" in result.comparisons[0].method
    maximal = primary_test(trials, ["pixel-only", "crs"], "pixel-only",
                           random_effects=("participant", "digit"))
    assert "(1 + condition | participant) + (1 + condition | digit)" in \
        maximal.comparisons[0].method


def test_adaptive_quadrature_when_planned():
    trials = _trials(n_participants=10, n_per_cell=30, seed=5)
    laplace = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    agq = primary_test(trials, ["pixel-only", "crs"], "pixel-only", method="agq",
                       structure="intercepts",
                       n_quadrature=15)
    assert "AGQ 15 points" in agq.comparisons[0].method
    # same data, close estimates (Laplace and AGQ differ by the integral's approximation only)
    assert agq.comparisons[0].log_odds == pytest.approx(laplace.comparisons[0].log_odds,
                                                        abs=0.02)


def test_agq_with_crossed_effects_falls_back_to_laplace_with_a_warning():
    trials = _trials(n_participants=6, n_per_cell=20, seed=6)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only",
                          random_effects=("participant", "digit"), method="agq")
    assert "(Laplace" in result.comparisons[0].method
    assert "fitted with the Laplace approximation instead" in result.warnings[0]


def test_a_numerical_failure_inside_the_fit_reaches_the_fisher_fallback(monkeypatch):
    def singular(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(glmm, "optimise", singular)
    trials = _trials(seed=3)
    with pytest.raises(GlmmFitError, match=r"numerical failure .*LinAlgError: Singular matrix"):
        glmm.fit_glmm(trials, "correct", "C(condition)", "participant_id")
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    assert result.comparisons[0].method.startswith("Fisher's exact test")
    assert "LinAlgError: Singular matrix" in result.warnings[0]


@pytest.mark.parametrize("n_quadrature", [0, MAX_QUADRATURE + 1])
def test_a_configuration_error_surfaces_instead_of_the_fisher_fallback(n_quadrature):
    trials = _trials(n_participants=6, n_per_cell=10, seed=3)
    with pytest.raises(AnalysisError, match=rf"n_quadrature must be an integer in "
                       rf"1\.\.{MAX_QUADRATURE}, got {n_quadrature}$") as info:
        primary_test(trials, ["pixel-only", "crs"], "pixel-only", method="agq",
                     n_quadrature=n_quadrature)
    assert not isinstance(info.value, GlmmFitError)


def test_the_plan_and_the_glmm_share_one_quadrature_limit():
    plan = AnalysisPlan.from_dict({"plan": {"name": "x"}, "primary": {
        "method": "agq", "n_quadrature": MAX_QUADRATURE, "structure": "intercepts"}},
        "p.toml")
    assert plan.primary.n_quadrature == MAX_QUADRATURE
    with pytest.raises(PlanError, match=rf"primary\.n_quadrature: expected .*{MAX_QUADRATURE}"
                       ) as info:
        AnalysisPlan.from_dict({"plan": {"name": "x"}, "primary": {
            "method": "agq", "n_quadrature": MAX_QUADRATURE + 1,
            "structure": "intercepts"}}, "p.toml")
    assert "\n" not in str(info.value)
    # what the plan accepts, the fit accepts: the largest rule runs (and agrees with 25 points)
    trials = _trials(n_participants=6, n_per_cell=10, seed=3)
    top = primary_test(trials, ["pixel-only", "crs"], "pixel-only", method="agq",
                       n_quadrature=MAX_QUADRATURE, structure="intercepts")
    usual = primary_test(trials, ["pixel-only", "crs"], "pixel-only", method="agq",
                         structure="intercepts")
    assert top.comparisons[0].log_odds == pytest.approx(usual.comparisons[0].log_odds, abs=1e-6)


def _statsmodels_profile_interval(y, x, level=0.95):
    """Profile-likelihood interval of the slope of ``logit P(y) = a + b x``, computed apart
    from our optimiser: statsmodels' GLM (IRLS) maximises over the intercept at each fixed b
    (as an offset), Brent's method finds where 2 (l_max - l_prof(b)) = chi2_1(level)."""
    import statsmodels.api as sm
    from scipy import optimize, stats

    ones = np.ones((len(y), 1))
    full = sm.GLM(y, np.column_stack([ones, x]), family=sm.families.Binomial()).fit()
    b_hat, se = full.params[1], full.bse[1]
    cutoff = stats.chi2.ppf(level, 1)

    def excess(b):
        fit = sm.GLM(y, ones, family=sm.families.Binomial(), offset=b * x).fit()
        return 2.0 * (full.llf - fit.llf) - cutoff

    return (optimize.brentq(excess, b_hat - 5 * se, b_hat, xtol=1e-10),
            optimize.brentq(excess, b_hat, b_hat + 5 * se, xtol=1e-10))


def test_odds_ratio_interval_is_the_profile_likelihood_one_checked_at_variance_zero():
    # Eight participants with identical results (14/20 correct with crs, 9/20 without): no
    # variation between participants, so the participant variance is estimated at exactly 0
    # and the model is the logistic regression; its profile interval must then equal the
    # logistic regression's profile interval, computed here with statsmodels' GLM.
    rows = []
    for p in range(8):
        for condition, k in (("pixel-only", 9), ("crs", 14)):
            rows += [{"participant_id": f"p{p}", "condition": condition, "digit": i % 10,
                      "correct": float(i < k)} for i in range(20)]
    trials = pd.DataFrame(rows)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only",
                          structure="intercepts")
    (comparison,) = result.comparisons
    assert result.model["variance_components"]["participant_id"] == 0.0
    y = trials["correct"].to_numpy()
    x = (trials["condition"] == "crs").to_numpy(dtype=float)
    low, high = _statsmodels_profile_interval(y, x)
    assert np.log(comparison.ci95) == pytest.approx((low, high), abs=2e-5)
    assert comparison.ci_method.startswith("profile likelihood")
    # the Wald interval is kept, labelled, and differs: the profile is not symmetric in b
    b, se = comparison.log_odds, comparison.std_error
    assert np.log(comparison.ci95_wald) == pytest.approx((b - 1.959964 * se,
                                                         b + 1.959964 * se), abs=1e-6)
    assert abs((high - b) - (b - low)) > 1e-3
    as_json = comparison.to_dict()
    assert as_json["ci95"] == list(comparison.ci95)
    assert as_json["ci95_wald"] == list(comparison.ci95_wald)
    # the participant SD: estimate 0, profile interval from 0
    sd = result.model["random_effects"]["participant"]
    assert sd["sd"] == 0.0 and sd["sd_ci95"][0] == 0.0 and sd["sd_ci95"][1] > 0


def test_profile_interval_without_random_effects_matches_statsmodels():
    # a single participant: no variance is estimable, the model is the logistic regression
    trials = _trials(n_participants=1, n_per_cell=60, seed=8)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    (comparison,) = result.comparisons
    y = trials["correct"].to_numpy()
    x = (trials["condition"] == "crs").to_numpy(dtype=float)
    assert np.log(comparison.ci95) == pytest.approx(_statsmodels_profile_interval(y, x),
                                                    abs=2e-5)
    assert result.model["random_effects"] == {}


def test_a_profile_that_never_leaves_the_cutoff_gives_null_ends_not_overflow(monkeypatch):
    # Seen on a 2-participant, 4-trial privacy-test dataset: the profile search ended at
    # -/+2359 log-odds and exp() overflowed (a RuntimeWarning, an error under pytest). Either
    # open end, even alone, is null with a warning.
    import json

    columns_seen = []

    def flat(full, level, columns):
        columns_seen.extend(columns)
        return pd.DataFrame({"ci_low": -2359.47, "ci_high": 2359.47}, index=columns)

    monkeypatch.setattr(glmm, "profile_conf_int", flat)
    trials = _trials(n_participants=6, n_per_cell=10, seed=3)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    (comparison,) = result.comparisons
    assert columns_seen == ["condition[crs]"]
    assert comparison.ci95 == (None, None)
    assert any("stays within the cutoff" in w for w in result.warnings)
    json.dumps(comparison.to_dict(), allow_nan=False)

    def open_below(full, level, columns):
        return pd.DataFrame({"ci_low": -np.inf, "ci_high": 1.0}, index=columns)

    monkeypatch.setattr(glmm, "profile_conf_int", open_below)
    result = primary_test(trials, ["pixel-only", "crs"], "pixel-only")
    (comparison,) = result.comparisons
    assert comparison.ci95 == (None, pytest.approx(np.e))
    assert any("stays within the cutoff" in w for w in result.warnings)
