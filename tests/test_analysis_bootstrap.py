"""The parametric bootstrap of the primary LR test (crs_study.analysis.bootstrap).

Outside reference: R's pbkrtest (Halekoh & Hojsgaard 2014, J. Stat. Softw. 59(9)),
``PBmodcomp`` on three small datasets of the random-slopes corpus
(``tests/fixtures/bootstrap/pbkrtest_results.json``, made by ``pbkrtest.R`` beside it, 500
simulations each with glmer's refits). The random numbers differ, so the comparison is of
distributions: our simulated LR statistics and pbkrtest's are one distribution by the
two-sample Kolmogorov-Smirnov test, and the two p-values agree within their Monte Carlo
error. The rest: the p's formula and interval, failures counted, the same answer however the
replicates are cut into units of work, and the null model's random effects drawn with the
null fit's covariance.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from crs_study.analysis import bootstrap
from crs_study.analysis.bootstrap import StudyRows, simulate_null
from crs_study.analysis.glmm_simulate import simulate_cells, slope_covariance
from crs_study.analysis.glmm_terms import RandomTerm
from crs_study.analysis.primary import design, fit_primary, primary_test

FIXTURES = Path(__file__).parent / "fixtures"
CONDITIONS = ["pixel-only", "crs"]
#: Our replicates of each pbkrtest dataset: enough for the two-sample test to see a shift of
#: a fifth of the statistic's spread.
OUR_REPLICATES = 200


def _cells(seed: int = 3, effect: float = 0.3):
    return simulate_cells(np.random.default_rng(seed), 10, 10, 5, [0.0, effect],
                          slope_covariance(0.6, 0.6, 0.0), slope_covariance(0.3, 0.0),
                          conditions=CONDITIONS)


@pytest.fixture(scope="module")
def fits():
    return fit_primary(_cells(), CONDITIONS, "pixel-only", ("participant", "digit"))


def test_the_p_is_one_plus_the_exceedances_over_one_plus_b(fits):
    result, why = fits.bootstrap(fits.tests[0], 60, 11)
    assert why is None and result.used == 60 and result.failed == 0
    assert result.pvalue == pytest.approx((1 + result.exceed) / 61)
    ci = stats.binomtest(result.exceed, 60).proportion_ci(0.95, method="exact")
    assert result.ci95 == pytest.approx((ci.low, ci.high))
    assert result.statistic == pytest.approx(fits.tests[0].test.statistic)


def test_units_of_work_and_their_order_do_not_change_the_answer(fits, monkeypatch):
    alone, _ = fits.bootstrap(fits.tests[0], 120, 5)
    monkeypatch.setattr(bootstrap, "REPLICATES_PER_TASK", 7)
    reversed_order = fits.bootstrap(fits.tests[0], 120, 5,
                                    lambda f, tasks: [f(t) for t in reversed(tasks)])[0]
    assert reversed_order.exceed == alone.exceed and reversed_order.pvalue == alone.pvalue


def test_the_sequential_test_stops_at_the_hth_exceedance_whatever_the_units(fits,
                                                                          monkeypatch):
    """Besag & Clifford (1991): stop at the replicate L where h of them reached the observed
    LR, p = h / L; the same L and p whatever the size of the units of work and their
    order (the replicates computed past L are not used)."""
    test = fits.tests[0]
    statistics = _statistics(fits, test, 100, 8, full=True)
    h = 3
    reached = np.flatnonzero(statistics >= test.test.statistic - 1e-6)
    assert len(reached) >= h, "the fixture must reach the observed LR a few times"
    expected = int(reached[h - 1]) + 1
    sequential, _ = fits.bootstrap(test, 400, 8, stop_after=h)
    assert sequential.stopped and sequential.exceed == h
    assert sequential.used == expected and sequential.pvalue == pytest.approx(h / expected)
    monkeypatch.setattr(bootstrap, "REPLICATES_PER_TASK", 7)
    cut, _ = fits.bootstrap(test, 400, 8, lambda f, tasks: [f(t) for t in reversed(tasks)],
                            stop_after=h)
    assert (cut.used, cut.pvalue) == (sequential.used, sequential.pvalue)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(0, 10), st.just(float("nan"))), min_size=1, max_size=60),
       st.floats(0, 10), st.integers(0, 8))
def test_the_sequential_count_reads_the_statistics_in_order(values, statistic, h):
    values = np.asarray(values)
    outcome = bootstrap.sequential_count(values, statistic, h)
    reached = np.isfinite(values) & (np.nan_to_num(values, nan=-1) >= statistic - 1e-6)
    if h and reached.sum() < h:
        assert outcome is None
        return
    drawn, used, exceed, stopped = outcome
    assert stopped == bool(h)
    assert reached[:drawn].sum() == exceed and used == np.isfinite(values[:drawn]).sum()
    if h:
        assert exceed == h and reached[drawn - 1]
    else:
        assert drawn == len(values)


def test_replicates_that_cannot_be_fitted_are_counted_not_dropped(fits, monkeypatch):
    real = bootstrap.run_bootstrap_task

    def some_fail(task):
        chunk = real(task)
        statistics = chunk.statistics.copy()
        statistics[::10] = np.nan                      # as _reference_statistic gives them
        return bootstrap.BootstrapChunk(chunk.replicates, statistics, chunk.reference_fits)

    monkeypatch.setattr(bootstrap, "run_bootstrap_task", some_fail)
    result, _ = fits.bootstrap(fits.tests[0], 50, 3)
    assert result.failed == 5 and result.used == 45
    assert result.pvalue == pytest.approx((1 + result.exceed) / 46)


def test_the_null_draws_have_the_null_fits_covariance():
    """Many replicates: a participant's drawn (intercept, slope) on the linear predictor
    have the covariance T T' of the null theta, and mean the null's fixed intercept."""
    cells = simulate_cells(np.random.default_rng(1), 3, 1, 1, [0.0, 0.0],
                           slope_covariance(0.5, 0.5, 0.0), conditions=CONDITIONS)
    full_design = design(cells, CONDITIONS, "pixel-only")
    term = RandomTerm("participant_id", tuple(full_design.columns))
    rows = StudyRows.of(cells, full_design, [term], trials="n_trials")
    theta = np.array([0.3, 0.8, -0.4, 0.6])           # intercept, then T's entries
    eta = np.array([e for _, e in bootstrap.null_linear_predictors(
        rows, "condition[crs]", theta, 9, range(20000))])
    pixel, crs = eta[:, rows.X[:, 1] == 0], eta[:, rows.X[:, 1] == 1]
    effects = np.stack([pixel[:, 0] - 0.3, crs[:, 0] - pixel[:, 0]], axis=1)
    T = np.array([[0.8, 0.0], [-0.4, 0.6]])
    np.testing.assert_allclose(np.cov(effects.T), T @ T.T, atol=0.03)
    Y = simulate_null(rows, "condition[crs]", theta, 9, range(50))
    assert Y.shape == (50, len(rows.trials)) and np.all((Y >= 0) & (Y <= rows.trials))


def test_the_bootstrap_distribution_is_pbkrtests():
    """pbkrtest's PBmodcomp (tests/fixtures/bootstrap/pbkrtest.R, 500 glmer refits a
    dataset) and ours draw the LR statistic from the same distribution (two-sample
    Kolmogorov-Smirnov test), and the two bootstrap p's agree within their Monte Carlo
    error (ours ``OUR_REPLICATES``, a test's time; theirs took 10 and 32 minutes)."""
    reference = json.loads((FIXTURES / "bootstrap" / "pbkrtest_results.json").read_text())
    corpus = pd.read_csv(FIXTURES / "lme4_slopes" / "corpus.csv",
                         dtype={"participant": str, "dataset": str, "digit": str})
    assert len(reference["datasets"]) >= 2
    for name, theirs in reference["datasets"].items():
        rows = corpus.loc[corpus["dataset"] == name]
        trials = pd.DataFrame({"participant_id": rows["participant"].to_numpy(),
                               "digit": rows["digit"].to_numpy(),
                               "condition": rows["condition"].to_numpy(),
                               "correct": rows["successes"].to_numpy(float),
                               "n_trials": rows["trials"].to_numpy(float)})
        fits = fit_primary(trials, CONDITIONS, "pixel-only", ("participant", "digit"))
        test = fits.tests[0]
        assert test.test.statistic == pytest.approx(theirs["statistic"], abs=2e-3)
        nsim = int(theirs["nsim"])
        ours = _statistics(fits, test, OUR_REPLICATES, 2026)
        assert stats.ks_2samp(ours, np.asarray(theirs["reference"])).pvalue > 0.001, name
        # the two p's, each a binomial proportion, within their joint Monte Carlo error
        p = (1 + np.sum(ours >= test.test.statistic - 1e-6)) / (1 + len(ours))
        se = np.sqrt(p * (1 - p) * (1 / len(ours) + 1 / nsim))
        assert abs(p - theirs["p_bootstrap"]) < 4 * se + 0.004, name


def _statistics(fits, test, replicates: int, seed: int, full: bool = False) -> np.ndarray:
    """The simulated LR statistics themselves (the bootstrap keeps only their count); NaN
    for a failed refit kept in place with ``full``."""
    whole = fits.full
    rows = StudyRows.of(fits.data, fits.design, whole.terms, "correct", "n_trials")
    chunks = [bootstrap.run_bootstrap_task(bootstrap.BootstrapTask(
        rows, test.column, np.r_[test.reduced.params.to_numpy(), test.reduced.theta],
        np.r_[whole.params.to_numpy(), whole.theta], seed, (start, min(start + 100,
                                                                      replicates))))
        for start in range(0, replicates, 100)]
    values = np.concatenate([c.statistics for c in chunks])
    return values if full else values[np.isfinite(values)]


def test_the_plan_chooses_the_bootstrap_below_a_number_of_participants():
    cells = _cells(4, 0.0)
    few = primary_test(cells, CONDITIONS, "pixel-only", ("participant", "digit"),
                       p_value="auto", bootstrap_below=20, bootstrap_replicates=50, seed=1)
    comparison = few.comparisons[0]
    assert comparison.p_method == "bootstrap" and comparison.bootstrap["used"] == 50
    assert comparison.p_lr is not None and comparison.p_value != comparison.p_lr
    assert "parametric bootstrap, B = 50" in comparison.method
    assert few.model["p_value_rule"]["used"] == "bootstrap"
    many = primary_test(cells, CONDITIONS, "pixel-only", ("participant", "digit"),
                        p_value="auto", bootstrap_below=5, seed=1)
    assert many.comparisons[0].p_method == "chi2" and many.comparisons[0].bootstrap is None
    assert many.comparisons[0].p_value == many.comparisons[0].p_lr
