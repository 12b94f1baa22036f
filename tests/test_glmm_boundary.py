"""The GLMM reaches its maximum: the boundary check, restarts, profiles that free every
variance, the Schur-complement core and separation's one-sided limit."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.special import expit

from crs_study.analysis.glmm import fit_glmm, profile_conf_int
from crs_study.analysis.glmm_core import BinomialData, CrossedTerms
from crs_study.analysis.glmm_optimise import maximise, variance_slope
from crs_study.analysis.glmm_reference import load_cbpp
from crs_study.analysis.glmm_simulate import simulate_trials
from crs_study.analysis.glmm_terms import RandomTerm
from crs_study.analysis.primary import fit_primary


@pytest.fixture(scope="module")
def cbpp_fit():
    return fit_glmm(load_cbpp(), "incidence", "C(period)", "herd", trials="size")


def test_a_start_on_the_boundary_is_left_when_moving_inward_raises_the_likelihood(cbpp_fit):
    # The trap: the objective is even in sigma, so at sigma = 0 its gradient is exactly 0
    # and a first-order optimiser started (or clipped) there never moves (a bounded TNC
    # stayed at 0 here). The boundary check sees d l / dv > 0 and moves inward.
    problem, theta_hat = cbpp_fit._model.problem, cbpp_fit._model.theta
    start = theta_hat.copy()
    start[-1] = 0.0
    assert problem.objective(start)[1][-1] == 0.0       # no first-order signal at sigma = 0
    assert variance_slope(problem, start, 4) > 1.0
    opt = maximise(problem, start)
    assert not opt.at_zero
    assert opt.theta[-1] == pytest.approx(theta_hat[-1], abs=1e-4)     # lme4: sd 0.6423
    assert opt.value == pytest.approx(problem.objective(theta_hat, grad=False), abs=1e-8)


def test_variance_slope_is_the_derivative_on_the_variance_scale(cbpp_fit):
    # (l(v = d) - l(0)) / d with the other parameters fixed, by plain differences of values
    problem, theta_hat = cbpp_fit._model.problem, cbpp_fit._model.theta
    base = theta_hat.copy()
    base[-1] = 0.0
    slope = variance_slope(problem, base, 4)
    for d in (1e-4, 1e-5):
        shifted = base.copy()
        shifted[-1] = np.sqrt(d)
        numeric = (problem.objective(shifted, grad=False)
                   - problem.objective(base, grad=False)) / d
        assert slope == pytest.approx(numeric, rel=2e-3)


def test_a_boundary_estimate_is_a_true_statement():
    # Every participant answers alike: the participant variance's ML estimate is 0, and the
    # warning's slope is what a refit says: held just inside 0, the best likelihood is lower.
    rows = [{"participant": f"p{p}", "condition": c, "correct": int(i < k)}
            for p in range(8) for c, k in (("a", 9), ("b", 14)) for i in range(20)]
    fit = fit_glmm(pd.DataFrame(rows), "correct", "condition", "participant")
    assert fit.boundary == ("participant",) and fit.converged
    (note,) = [w for w in fit.warnings if "estimated at 0" in w]
    slope = float(note.split("d loglik / d variance = ")[1].split(" ")[0])
    assert slope < 0
    problem, theta = fit._model.problem, fit._model.theta
    inside = maximise(problem, np.r_[theta[:2], 0.2], {2: 0.2})
    assert inside.value < problem.objective(theta, grad=False)
    assert "no variation" not in note                    # the earlier, overstated wording


def test_profile_intervals_free_every_variance():
    # Few trials per cell (our earlier 1.066-8.88 where lme4 gives 1.053-9.72). The digit
    # variance is 0 at the estimate but moves inward towards the upper end; holding it at 0
    # (our earlier profiles; glmmTMB's log-SD profile, 1.68534 on these data) ends too soon.
    # Each end is where the best likelihood with every other parameter free (an independent
    # maximisation from several starts) drops by chi2_1(0.95).
    data = simulate_trials(np.random.default_rng(4011), 12, 6, [0.0, 0.8], 0.49,
                           digit_variance=0.09)     # the corpus' sim-12p-6t-psd0.7-dsd0.3-11
    fit = fit_glmm(data, "correct", "condition", ["participant", "digit"])
    assert fit.boundary == ("digit",)
    low, high = profile_conf_int(fit).loc["condition[T.c1]"]
    problem, theta_hat = fit._model.problem, fit._model.theta
    top = problem.objective(theta_hat, grad=False)
    cutoff = stats.chi2.ppf(0.95, 1)
    for end in (low, high):
        best = max(maximise(problem, np.r_[theta_hat[0], end, s, s], {1: end}).value
                   for s in (0.0, 0.5, 1.5))
        assert 2 * (top - best) == pytest.approx(cutoff, abs=2e-3)
    at_end = maximise(problem, np.r_[theta_hat[0], high, theta_hat[2], 0.3], {1: high})
    assert at_end.theta[3] > 0.05                      # the digit SD moved inward
    held = maximise(problem, np.r_[theta_hat[0], 1.68534, theta_hat[2], 0.0],
                    {1: 1.68534, 3: 0.0})
    assert 2 * (top - held.value) == pytest.approx(cutoff, abs=2e-3) and high > 1.69



def _intercepts(data: BinomialData) -> CrossedTerms:
    """Crossed random intercepts, one per grouping factor of ``data``."""
    return CrossedTerms(data, [RandomTerm(f"g{k}") for k in range(len(data.group_codes))])


@settings(max_examples=10, deadline=None)
@given(sizes=st.permutations([3, 7, 4]), theta=st.lists(st.floats(-1.0, 1.0), min_size=5,
                                                           max_size=5))
def test_schur_core_equals_the_dense_laplace_whichever_factor_is_largest(sizes, theta):
    """Value against a dense Newton solve and slogdet written apart; gradient against central
    differences; the factor with most levels may be any of the three."""
    rng = np.random.default_rng(11)
    n = 90
    X = np.column_stack([np.ones(n), rng.integers(0, 2, n)])
    codes = tuple(rng.permutation(np.arange(n) % k) for k in sizes)
    m = rng.integers(1, 5, n).astype(float)
    y = rng.binomial(m.astype(int), 0.55).astype(float)
    theta = np.asarray(theta)
    theta[2:] = np.abs(theta[2:]) + 0.1
    model = _intercepts(BinomialData(X, y, m, codes, tuple(sizes)))
    Z = np.zeros((n, sum(sizes)))
    offsets = np.cumsum([0, *sizes])
    for k, c in enumerate(codes):
        Z[np.arange(n), offsets[k] + c] = theta[2 + k]
    u = np.zeros(Z.shape[1])
    for _ in range(60):
        p = expit(X @ theta[:2] + Z @ u)
        H = Z.T @ (Z * (m * p * (1 - p))[:, None]) + np.eye(len(u))
        u = u + np.linalg.solve(H, Z.T @ (y - m * p) - u)
    eta = X @ theta[:2] + Z @ u
    p = expit(eta)
    H = Z.T @ (Z * (m * p * (1 - p))[:, None]) + np.eye(len(u))
    dense = np.sum(y * eta - m * np.logaddexp(0, eta)) - u @ u / 2 - np.linalg.slogdet(H)[1] / 2
    value, grad = model.loglik(theta)
    assert value == pytest.approx(dense, abs=1e-9)
    h = 1e-6
    numeric = [(model.loglik(theta + h * e, False) - model.loglik(theta - h * e, False)) / (2 * h)
               for e in np.eye(5)]
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-5)


def test_separation_limit_is_where_the_unpenalised_profile_meets_the_cutoff():
    # Every 'c1' trial correct: the supremum is the fit of the 'c0' trials alone, and at the
    # one-sided limit the best unpenalised likelihood with the effect held there (refitted
    # here from several starts) lies chi2_1(0.95) / 2 below it.
    data = simulate_trials(np.random.default_rng(5000), 8, 30, [0.0, 0.7], 0.49)
    data.loc[data["condition"] == "c1", "correct"] = 1
    fit = fit_glmm(data, "correct", "condition", "participant")
    separation = fit.separation
    assert separation.coefficients == ("condition[T.c1]",) and separation.directions == (1,)
    alone = fit_glmm(data.loc[data["condition"] == "c0"], "correct", "1", "participant")
    assert separation.sup_loglike == pytest.approx(alone.loglike, abs=1e-8)
    low, high = profile_conf_int(fit).loc["condition[T.c1]"]
    assert high == np.inf and 0 < low < fit.params["condition[T.c1]"] + 5
    problem = separation.problem
    best = max(maximise(problem, np.r_[0.0, low, s], {1: low}).value for s in (0.3, 1.0))
    assert 2 * (separation.sup_loglike - problem.user_constant - best) == pytest.approx(
        stats.chi2.ppf(0.95, 1), abs=1e-4)


def test_fit_primary_on_aggregated_counts_equals_trial_rows():
    # The API for power simulations: the same LR test from 0/1 rows or from counts
    data = simulate_trials(np.random.default_rng(3), 10, 40, [0.0, 0.6], 0.3, digit_variance=0.1)
    trials = data.rename(columns={"participant": "participant_id"})
    trials["condition"] = trials["condition"].astype(str)
    counts = (trials.groupby(["participant_id", "digit", "condition"])["correct"]
              .agg(correct="sum", n_trials="size").reset_index())
    by_row = fit_primary(trials, ["c0", "c1"], "c0", ("participant", "digit"))
    by_count = fit_primary(counts, ["c0", "c1"], "c0", ("participant", "digit"))
    (a,), (b,) = by_row.tests, by_count.tests
    assert a.log_odds == pytest.approx(b.log_odds, abs=1e-6)
    assert a.p_value == pytest.approx(b.p_value, rel=1e-6)
    assert a.test.statistic == pytest.approx(b.test.statistic, abs=1e-6)
    row = by_count.to_frame().iloc[0]
    assert row["condition"] == "c1" and row["df"] == 1 and row["converged"]
    assert not row["separated"] and row["error"] is None


def test_a_condition_at_zero_percent_has_an_upper_limit_only():
    from crs_study.analysis.headline import _separated_text

    data = simulate_trials(np.random.default_rng(5001), 8, 30, [0.0, -0.7], 0.25)
    data.loc[data["condition"] == "c1", "correct"] = 0
    fit = fit_glmm(data, "correct", "condition", "participant")
    assert fit.separation.directions == (-1,)
    low, high = profile_conf_int(fit).loc["condition[T.c1]"]
    assert low == -np.inf and fit.params["condition[T.c1]"] - 5 < high < 0
    text = _separated_text({"ci95": [None, float(np.exp(high))]}, "95 %")
    assert text.startswith(f"< {np.exp(high):.3g} (ML estimate infinite") and "lower limit 0" \
        in text
