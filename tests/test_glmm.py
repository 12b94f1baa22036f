"""The GLMM against lme4 (cbpp), against scipy quadrature, and where maximum likelihood fails."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats
from scipy.special import expit

from crs_study.analysis.glmm import (
    PRIOR_SD_COEFFICIENT,
    fit_glmm,
    format_pvalue,
    lrt,
    profile_conf_int,
    profile_sd_conf_int,
)
from crs_study.analysis.glmm_core import BinomialData, CrossedTerms, SingleFactor
from crs_study.analysis.glmm_reference import load_cbpp
from crs_study.analysis.glmm_simulate import simulate_trials
from crs_study.analysis.glmm_terms import RandomTerm
from crs_study.errors import AnalysisError

#: lme4's data(cbpp) and lme4's own fits of it, written by make_cbpp.R there (README.md).
CBPP_FIXTURE = Path(__file__).parent / "fixtures" / "cbpp"
PERIOD = ["Intercept", "C(period)[T.2]", "C(period)[T.3]", "C(period)[T.4]"]


@pytest.fixture(scope="module")
def cbpp() -> pd.DataFrame:
    return load_cbpp()


def test_embedded_cbpp_is_the_reference_file():
    reference = pd.read_csv(CBPP_FIXTURE / "cbpp.csv")
    assert load_cbpp().equals(reference[["herd", "incidence", "size", "period"]])


@pytest.fixture(scope="module")
def cbpp_laplace(cbpp):
    return fit_glmm(cbpp, "incidence", "C(period)", "herd", trials="size")


@pytest.fixture(scope="module")
def cbpp_trials(cbpp) -> pd.DataFrame:
    """cbpp expanded to one 0/1 row per animal (842 rows)."""
    rows = cbpp.loc[cbpp.index.repeat(cbpp["size"])].reset_index(drop=True)
    rank = rows.groupby(["herd", "period"]).cumcount()
    rows["sick"] = (rank < rows["incidence"]).astype(int)
    return rows


@pytest.fixture(scope="module")
def two_conditions() -> pd.DataFrame:
    return simulate_trials(np.random.default_rng(7), 20, 60, [0.2, 0.9], 0.5)


# ------------------------------------------------------------------------- lme4's cbpp example
def test_cbpp_laplace_matches_lme4(cbpp_laplace):
    # lme4: glmer(cbind(incidence, size - incidence) ~ period + (1 | herd), cbpp, binomial)
    # (lme4's documentation; tests/fixtures/cbpp/README.md): -1.39855, -0.99234, -1.12868,
    # -1.58030; herd variance 0.412455; logLik -92.0266; summary prints AIC 194.1, BIC 204.2,
    # deviance 184.1.
    r = cbpp_laplace
    assert list(r.params.index) == PERIOD
    np.testing.assert_allclose(r.params, [-1.39855, -0.99234, -1.12868, -1.58030], atol=1e-3)
    assert r.variance_components["herd"] == pytest.approx(0.412455, rel=0.01)
    # logLik: ours -92.02628, lme4's -92.0266 (-92.02656639 as lme4 2.0.1 prints it): within
    # 1e-3, but not a rounding of ours. The gap is not in the optimum (our Laplace value at
    # lme4's own estimates is -92.026282 at the published ones and -92.026286 at 2.0.1's)
    # nor in the binomial constant (185.4757, the same for both): it is lme4's evaluation of
    # the Laplace approximation, lower by 3e-4. Independent implementations of the same
    # Laplace likelihood agree with ours; see test_cbpp_laplace_matches_mixedmodels_jl.
    assert r.loglike == pytest.approx(-92.0266, abs=1e-3)
    assert (round(r.aic, 1), round(r.bic, 1), round(r.deviance, 1)) == (194.1, 204.2, 184.1)
    assert r.converged and r.method == "laplace" and r.warnings == ()
    assert r.n_groups == {"herd": 15} and r.nobs == 56


def test_cbpp_matches_lme4_as_run_by_the_fixture_script(cbpp_laplace):
    # lme4 1.1.31's own Laplace fit (tests/fixtures/cbpp/make_cbpp.R, lme4_cbpp.json).
    lme4 = json.loads((CBPP_FIXTURE / "lme4_cbpp.json").read_text(encoding="utf-8"))["laplace"]
    np.testing.assert_allclose(cbpp_laplace.params, lme4["fixef"], atol=1e-3)
    assert cbpp_laplace.variance_components["herd"] == pytest.approx(lme4["herd_variance"],
                                                                     rel=0.01)
    assert cbpp_laplace.loglike == pytest.approx(lme4["loglik"], abs=1e-3)


def test_cbpp_laplace_matches_mixedmodels_jl(cbpp_laplace):
    # Julia's MixedModels.jl (D. Bates, lme4's first author), test/pirls.jl, testset "cbpp":
    # the same model fitted by its PIRLS Laplace: loglikelihood -92.02628186840045 and its
    # parts, deviance(gm2, true) = 100.09585619892968 = sum(devresid) 73.47174762237978 +
    # sum(abs2, u) 9.723054788538546 + logdet 16.90105378801136 (deviance relative to the
    # saturated model; drmTMB 0.7.1's TMB Laplace gives -92.02628186 too). lme4 reports
    # -92.0266: its own evaluation differs by 3e-4 (see test_cbpp_laplace_matches_lme4).
    r = cbpp_laplace
    assert r.loglike == pytest.approx(-92.02628186840045, abs=1e-6)
    problem, theta = r._model.problem, r._model.theta
    model = problem.model
    model.loglik(theta, grad=False)                       # modes u at the optimum
    sigma = theta[-1]
    eta = model.X @ theta[:-1] + sigma * model.u[model.codes]
    mu = model.m * expit(eta)
    y, m = model.y, model.m
    with np.errstate(divide="ignore", invalid="ignore"):
        devresid = 2 * (np.where(y > 0, y * np.log(y / mu), 0.0)
                        + np.where(m > y, (m - y) * np.log((m - y) / (m - mu)), 0.0))
    weights = np.add.reduceat(m * expit(eta) * (1 - expit(eta)), model.starts)
    logdet = np.log(1 + sigma**2 * weights).sum()
    assert devresid.sum() == pytest.approx(73.47174762237978, abs=1e-3)
    assert model.u @ model.u == pytest.approx(9.723054788538546, abs=1e-3)
    assert logdet == pytest.approx(16.90105378801136, abs=1e-3)
    assert devresid.sum() + model.u @ model.u + logdet == pytest.approx(100.09585619892968,
                                                                       abs=1e-5)


def test_cbpp_standard_errors_match_lme4(cbpp_laplace):
    # lme4's vcov(use.hessian = TRUE) (inverse Hessian of the deviance, beta block), as recorded
    # by a third-party lme4 cross-check ("se_hessian" of cbpp, nAGQ = 1; summary prints
    # 0.2325, 0.3066, 0.3266, 0.4274): 0.2324733, 0.3066413, 0.3266372, 0.4274372.
    np.testing.assert_allclose(cbpp_laplace.bse, [0.2324733, 0.3066413, 0.3266372, 0.4274372],
                               rtol=0.01)
    # The beta-conditional SEs (MixedModels.jl, lme4 use.hessian = FALSE): 0.227891, 0.305385,
    # 0.326049, 0.428795 -- the variance's uncertainty moves them by at most ~2 %.
    np.testing.assert_allclose(cbpp_laplace.bse, [0.227891, 0.305385, 0.326049, 0.428795],
                               rtol=0.03)
    # lme4 summary: z -6.016, -3.236, -3.455, -3.697; p 1.79e-09, 0.001212, 0.000549, 0.000218
    np.testing.assert_allclose(cbpp_laplace.zvalues, [-6.016, -3.236, -3.455, -3.697], atol=0.01)
    np.testing.assert_allclose(cbpp_laplace.pvalues, [1.79e-09, 0.001212, 0.000549, 0.000218],
                               rtol=0.03)


def test_cbpp_agq25_matches_lme4(cbpp):
    # lme4 glmer(..., nAGQ = 25) (tests/fixtures/cbpp/README.md): -1.39923, -0.99141,
    # -1.12782, -1.57947.
    r = fit_glmm(cbpp, "incidence", "C(period)", "herd", trials="size", method="agq")
    np.testing.assert_allclose(r.params, [-1.39923, -0.99141, -1.12782, -1.57947], atol=1e-3)
    assert r.method == "agq" and r.n_quadrature == 25 and r.converged


def test_cbpp_agq7_matches_lme4(cbpp):
    # lme4 nAGQ = 7, as recorded by a third-party cross-check: beta -1.3992298, -0.9913961,
    # -1.1278329, -1.5794439; herd sd 0.6475178; se 0.2335116, 0.3067674, 0.3267698, 0.4275907.
    r = fit_glmm(cbpp, "incidence", "C(period)", "herd", trials="size", method="agq",
                 n_quadrature=7)
    np.testing.assert_allclose(r.params, [-1.3992298, -0.9913961, -1.1278329, -1.5794439],
                               atol=1e-4)
    assert math.sqrt(r.variance_components["herd"]) == pytest.approx(0.6475178, rel=1e-3)
    np.testing.assert_allclose(r.bse, [0.2335116, 0.3067674, 0.3267698, 0.4275907], rtol=0.01)


def test_cbpp_as_zero_one_trials(cbpp_laplace, cbpp_trials):
    # README: the same fit on the 842 expanded 0/1 trials has a log-likelihood lower by the
    # binomial constants, 185.4757; the estimates are the same.
    r = fit_glmm(cbpp_trials, "sick", "C(period)", "herd")
    assert len(cbpp_trials) == 842 and r.nobs == 842
    np.testing.assert_allclose(r.params, cbpp_laplace.params, atol=1e-6)
    assert cbpp_laplace.loglike - r.loglike == pytest.approx(185.4757, abs=1e-3)


# ------------------------------------------------------------------------ the numerical core
def _intercepts(data: BinomialData) -> CrossedTerms:
    """Crossed random intercepts, one per grouping factor of ``data``."""
    return CrossedTerms(data, [RandomTerm(f"g{k}") for k in range(len(data.group_codes))])


def _cbpp_data(cbpp) -> BinomialData:
    X = np.column_stack([np.ones(len(cbpp))] + [(cbpp["period"] == k).to_numpy(float)
                                                for k in (2, 3, 4)])
    codes = (cbpp["herd"].to_numpy() - 1).astype(np.intp)
    return BinomialData(X, cbpp["incidence"].to_numpy(float), cbpp["size"].to_numpy(float),
                        (codes,), (15,))


@settings(max_examples=15, deadline=None)
@given(theta=st.lists(st.floats(-2.0, 2.0), min_size=5, max_size=5),
       n_quadrature=st.sampled_from([1, 2, 5, 11]))
def test_gradient_is_exact(cbpp, theta, n_quadrature):
    """The implicit-derivative gradient equals central differences of the objective."""
    model = SingleFactor(_cbpp_data(cbpp), n_quadrature)
    theta = np.asarray(theta)
    theta[-1] = abs(theta[-1]) + 0.05
    _, g = model.loglik(theta)
    h = 1e-6
    numeric = [(model.loglik(theta + h * e, False) - model.loglik(theta - h * e, False)) / (2 * h)
               for e in np.eye(5)]
    np.testing.assert_allclose(g, numeric, rtol=1e-5, atol=1e-5)


def test_agq_equals_scipy_quadrature(cbpp):
    """AGQ with 25 points = the marginal likelihood integrated by scipy.integrate.quad."""
    data = _cbpp_data(cbpp)
    theta = np.array([-1.4, -1.0, -1.1, -1.6, 0.9])
    eta_fixed = data.X @ theta[:4]
    exact = 0.0
    for j in range(15):
        rows = data.group_codes[0] == j
        y, m, off = data.successes[rows], data.trials[rows], eta_fixed[rows]

        def density(u, y=y, m=m, off=off):
            eta = off + theta[4] * u
            return np.exp(np.sum(y * eta - m * np.logaddexp(0, eta))) * stats.norm.pdf(u)

        exact += math.log(integrate.quad(density, -12, 12, epsabs=0, epsrel=1e-12)[0])
    assert SingleFactor(data, 25).loglik(theta, False) == pytest.approx(exact, abs=1e-8)
    # Laplace is the one-point rule, and off by a little on these small herds
    laplace = SingleFactor(data, 1).loglik(theta, False)
    assert laplace == SingleFactor(data, 1).loglik(theta, False)
    assert 1e-4 < abs(laplace - exact) < 0.5


def test_crossed_laplace_reduces_to_single_factor(cbpp):
    data = _cbpp_data(cbpp)
    crossed = BinomialData(data.X, data.successes, data.trials,
                           (data.group_codes[0], np.arange(56) % 3), (15, 3))
    theta = np.array([-1.4, -1.0, -1.1, -1.6, 0.7])
    single = SingleFactor(data, 1).loglik(theta, False)
    assert _intercepts(crossed).loglik(np.r_[theta, 0.0], False) == pytest.approx(single,
                                                                                     abs=1e-9)


def test_crossed_laplace_against_dense_computation(rng):
    """The Schur-complement Laplace value = a dense Newton solve + slogdet, written apart."""
    n, J1, J2 = 120, 6, 4
    X = np.column_stack([np.ones(n), rng.integers(0, 2, n)])
    g1, g2 = rng.integers(0, J1, n), rng.integers(0, J2, n)
    m = rng.integers(1, 6, n).astype(float)
    y = rng.binomial(m.astype(int), 0.6).astype(float)
    theta = np.array([0.3, 0.5, 0.8, 0.6])
    Z = np.zeros((n, J1 + J2))
    Z[np.arange(n), g1] = theta[2]
    Z[np.arange(n), J1 + g2] = theta[3]
    u = np.zeros(J1 + J2)
    for _ in range(50):
        p = expit(X @ theta[:2] + Z @ u)
        H = Z.T @ (Z * (m * p * (1 - p))[:, None]) + np.eye(J1 + J2)
        u = u + np.linalg.solve(H, Z.T @ (y - m * p) - u)
    eta = X @ theta[:2] + Z @ u
    p = expit(eta)
    H = Z.T @ (Z * (m * p * (1 - p))[:, None]) + np.eye(J1 + J2)
    dense = np.sum(y * eta - m * np.log1p(np.exp(eta))) - u @ u / 2 - np.linalg.slogdet(H)[1] / 2
    data = BinomialData(X, y, m, (g1, g2), (J1, J2))
    assert _intercepts(data).loglik(theta, False) == pytest.approx(dense, abs=1e-9)


@settings(max_examples=10, deadline=None)
@given(theta=st.lists(st.floats(-1.5, 1.5), min_size=6, max_size=6))
def test_crossed_gradient_is_exact(theta):
    """Implicit differentiation through u* and tr(H^-1 dH) = central differences."""
    rng = np.random.default_rng(3)
    n = 150
    X = np.column_stack([np.ones(n), rng.integers(0, 2, n), rng.normal(size=n)])
    codes = (rng.integers(0, 6, n), rng.integers(0, 4, n), rng.integers(0, 3, n))
    m = rng.integers(1, 6, n).astype(float)
    y = rng.binomial(m.astype(int), 0.6).astype(float)
    model = _intercepts(BinomialData(X, y, m, codes, (6, 4, 3)))
    theta = np.asarray(theta)
    theta[3:] = np.abs(theta[3:])
    _, g = model.loglik(theta)
    h = 1e-6
    numeric = [(model.loglik(theta + h * e, False) - model.loglik(theta - h * e, False)) / (2 * h)
               for e in np.eye(6)]
    np.testing.assert_allclose(g, numeric, rtol=1e-5, atol=1e-5)


def test_pooling_rows_changes_nothing(two_conditions):
    pooled = fit_glmm(two_conditions, "correct", "condition", "participant")
    raw = fit_glmm(two_conditions, "correct", "condition", "participant", aggregate=False)
    np.testing.assert_allclose(pooled.params, raw.params, atol=1e-6)
    np.testing.assert_allclose(pooled.bse, raw.bse, rtol=1e-4)
    assert pooled.loglike == pytest.approx(raw.loglike, abs=1e-6)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_row_order_and_design_form_do_not_matter(two_conditions, seed):
    """Shuffled rows, or the design given as a matrix instead of a formula: the same fit."""
    reference = fit_glmm(two_conditions, "correct", "condition", "participant")
    shuffled = two_conditions.sample(frac=1.0, random_state=seed % 2**31)
    design = pd.DataFrame({"Intercept": 1.0,
                           "condition[T.c1]": (shuffled["condition"] == "c1").astype(float)},
                          index=shuffled.index)
    r = fit_glmm(shuffled, "correct", design, "participant")
    np.testing.assert_allclose(r.params, reference.params, atol=1e-6)
    np.testing.assert_allclose(r.bse, reference.bse, rtol=1e-4)
    assert r.loglike == pytest.approx(reference.loglike, abs=1e-7)
    with pytest.raises(AnalysisError, match="same index"):
        fit_glmm(shuffled, "correct", design.reset_index(drop=True), "participant")


def test_three_conditions_and_reference_level(rng):
    df = simulate_trials(rng, 15, 80, [0.0, 0.5, 1.2], 0.4)
    r = fit_glmm(df, "correct", "condition", "participant")
    assert list(r.params.index) == ["Intercept", "condition[T.c1]", "condition[T.c2]"]
    other = fit_glmm(df, "correct", "C(condition, Treatment('c2'))", "participant")
    # the c0-vs-c2 contrast flips sign with the reference level; the fit is the same model
    assert other.params.iloc[1] == pytest.approx(-r.params.iloc[2], abs=1e-4)
    assert other.loglike == pytest.approx(r.loglike, abs=1e-6)


def test_crossed_participant_and_digit(rng):
    df = simulate_trials(rng, 20, 100, [0.0, 0.8], 0.5, digit_variance=0.4)
    r = fit_glmm(df, "correct", "condition", ["participant", "digit"])
    assert r.n_groups == {"participant": 20, "digit": 10} and r.converged
    assert set(r.variance_components.index) == {"participant", "digit"}
    single = fit_glmm(df, "correct", "condition", "participant")
    test = lrt(r, single)
    assert test.distribution == "0.5 chi2(0) + 0.5 chi2(1)" and test.statistic > 0
    with pytest.raises(AnalysisError, match="single random intercept"):
        fit_glmm(df, "correct", "condition", ["participant", "digit"], method="agq")


# ---------------------------------------------------------------------- result and inference
def test_result_object(cbpp_laplace):
    r = cbpp_laplace
    frame = r.to_frame()
    assert list(frame.columns) == ["estimate", "std_error", "z", "p_value", "ci_low", "ci_high",
                                   "odds_ratio", "or_ci_low", "or_ci_high"]
    np.testing.assert_allclose(frame["ci_high"] - frame["estimate"], 1.959964 * r.bse,
                               rtol=1e-6)
    np.testing.assert_allclose(r.odds_ratios()["odds_ratio"], np.exp(r.params))
    np.testing.assert_allclose(r.odds_ratios(0.9)["ci_low"], np.exp(r.conf_int(0.9)["ci_low"]))
    json.dumps(r.to_dict())
    text = r.summary()
    assert "Laplace" in text and "C(period)[T.4]" in text and "0.4125" in text


def test_lrt_of_period(cbpp, cbpp_laplace):
    reduced = fit_glmm(cbpp, "incidence", "1", "herd", trials="size")
    test = lrt(cbpp_laplace, reduced)
    assert test.df == 3 and test.distribution == "chi2(3)"
    assert test.statistic == pytest.approx(2 * (cbpp_laplace.loglike - reduced.loglike))
    assert test.pvalue == pytest.approx(stats.chi2.sf(test.statistic, 3))
    with pytest.raises(AnalysisError, match="more parameters"):
        lrt(reduced, cbpp_laplace)
    with pytest.raises(AnalysisError, match="same data"):
        lrt(cbpp_laplace, fit_glmm(cbpp.iloc[:40], "incidence", "1", "herd", trials="size"))


def test_profile_interval_brackets_the_estimate(cbpp_laplace):
    prof = profile_conf_int(cbpp_laplace, terms=["C(period)[T.2]"])
    wald = cbpp_laplace.conf_int().loc["C(period)[T.2]"]
    low, high = prof.loc["C(period)[T.2]"]
    assert low < cbpp_laplace.params["C(period)[T.2]"] < high
    assert low == pytest.approx(wald["ci_low"], abs=0.1)
    assert high == pytest.approx(wald["ci_high"], abs=0.1)
    with pytest.raises(AnalysisError, match="unknown term 'period'"):
        profile_conf_int(cbpp_laplace, terms=["period"])


def test_sd_profile_interval_on_cbpp(cbpp, cbpp_laplace):
    # The herd SD (0.6423) with its profile interval: the ends are where the deviance of the
    # model refitted at that SD exceeds the optimum's by chi2_1(0.95) = 3.8415, every other
    # parameter re-maximised (checked here by refitting with the SD held, apart from the
    # profiler's own search); 0 lies outside because the herd variance's likelihood-ratio
    # statistic against the logistic regression (statsmodels GLM, sigma = 0) exceeds 3.8415.
    table = profile_sd_conf_int(cbpp_laplace)
    sd, low, high = table.loc["herd"]
    assert sd == pytest.approx(np.sqrt(cbpp_laplace.variance_components["herd"]))
    assert 0.2 < low < sd < high < 1.5
    problem, theta_hat = cbpp_laplace._model.problem, cbpp_laplace._model.theta
    from crs_study.analysis.glmm_fit import _minimise

    for end in (low, high):
        start = theta_hat.copy()
        start[-1] = end
        theta, _, _ = _minimise(problem, start, {4: end})
        deviance = 2 * (problem.objective(theta_hat, grad=False)
                        - problem.objective(theta, grad=False))
        assert deviance == pytest.approx(stats.chi2.ppf(0.95, 1), abs=1e-3)
    no_herd = fit_glmm(cbpp, "incidence", "C(period)", trials="size")     # statsmodels GLM
    assert 2 * (cbpp_laplace.loglike - no_herd.loglike) > stats.chi2.ppf(0.95, 1)


def test_sd_profile_lower_end_is_zero_within_the_cutoff():
    # A small random-intercept variance: the profile at sigma = 0 (the logistic regression,
    # by statsmodels) is within the cutoff, so the lower end is 0, not a root of the profile.
    df = simulate_trials(np.random.default_rng(4), 10, 20, [0.0, 0.8], 0.05)
    full = fit_glmm(df, "correct", "condition", "participant")
    glm = fit_glmm(df, "correct", "condition")
    statistic = 2 * (full.loglike - glm.loglike)
    assert full.variance_components.iloc[0] > 0 and statistic < stats.chi2.ppf(0.95, 1)
    sd, low, high = profile_sd_conf_int(full).iloc[0]
    assert low == 0.0 and high > sd
    # an estimate on the boundary: 0 with an interval [0, upper]
    identical = pd.concat([pd.DataFrame({"participant": f"p{p}", "condition": "c1",
                                         "correct": [1] * 7 + [0] * 3}) for p in range(6)])
    boundary = fit_glmm(identical.reset_index(drop=True), "correct", "1", "participant")
    assert boundary.boundary == ("participant",)
    sd, low, high = profile_sd_conf_int(boundary).iloc[0]
    assert sd == low == 0.0 and 0 < high < np.inf
    # no random effect: no rows
    assert profile_sd_conf_int(glm).empty


@pytest.mark.parametrize(("p", "text"), [(0.0312, "0.0312"), (3e-17, "< 1e-16"),
                                         (float("nan"), "n/a")])
def test_format_pvalue(p, text):
    assert format_pvalue(p) == text


# ------------------------------------------------------------ where maximum likelihood fails
@pytest.mark.parametrize("outcome", [1, 0], ids=["all-correct", "all-wrong"])
def test_separation_gives_finite_penalised_estimates(two_conditions, outcome):
    df = two_conditions.copy()
    df.loc[df["condition"] == "c1", "correct"] = outcome
    r = fit_glmm(df, "correct", "condition", "participant")
    assert r.penalty is not None and "separation" in r.warnings[0]
    assert "condition[T.c1]" in r.warnings[0]
    assert np.all(np.isfinite(r.params)) and np.all(np.isfinite(r.bse))
    assert np.sign(r.params["condition[T.c1]"]) == (1 if outcome else -1)
    assert abs(r.params["condition[T.c1]"]) < 5 * PRIOR_SD_COEFFICIENT
    assert np.all(r.pvalues > 0)


def test_everything_correct(two_conditions):
    df = two_conditions.assign(correct=1)
    r = fit_glmm(df, "correct", "condition", "participant")
    assert "['Intercept', 'condition[T.c1]']" in r.warnings[0]
    assert np.all(np.isfinite(r.params)) and np.all(np.isfinite(r.bse))


def test_variance_at_zero(rng):
    df = simulate_trials(rng, 20, 40, [0.0, 0.7], 0.0)
    r = fit_glmm(df, "correct", "condition", "participant")
    assert r.variance_components["participant"] == 0.0 and r.boundary == ("participant",)
    assert any("estimated at 0" in w and "mixture" in w for w in r.warnings)
    glm = fit_glmm(df, "correct", "condition", [])
    np.testing.assert_allclose(r.params, glm.params, atol=1e-5)
    np.testing.assert_allclose(r.bse, glm.bse, rtol=1e-4)
    test = lrt(r, glm)
    assert test.statistic == pytest.approx(0.0, abs=1e-6) and test.pvalue == 1.0


def test_single_participant_falls_back_to_glm(two_conditions):
    import statsmodels.api as sm

    one = two_conditions[two_conditions["participant"] == "p000"]
    r = fit_glmm(one, "correct", "condition", "participant")
    assert r.method == "glm" and "single level" in r.warnings[0]
    X = np.column_stack([np.ones(len(one)), (one["condition"] == "c1").to_numpy(float)])
    reference = sm.Logit(one["correct"].to_numpy(float), X).fit(disp=0)
    np.testing.assert_allclose(r.params, reference.params, atol=1e-6)
    np.testing.assert_allclose(r.bse, reference.bse, rtol=1e-6)
    assert r.loglike == pytest.approx(reference.llf, abs=1e-8)


def test_single_participant_with_separation(two_conditions):
    one = two_conditions[two_conditions["participant"] == "p001"].copy()
    one.loc[one["condition"] == "c1", "correct"] = 1
    r = fit_glmm(one, "correct", "condition", "participant")
    assert r.method == "glm" and r.penalty is not None
    assert any("single level" in w for w in r.warnings)
    assert any("separation" in w for w in r.warnings)
    assert np.all(np.isfinite(r.params)) and np.all(np.isfinite(r.bse))
    assert profile_conf_int(r, terms=["Intercept"]).notna().all().all()


def test_missing_condition_level_is_dropped(rng):
    df = simulate_trials(rng, 12, 30, [0.0, 0.5, 1.0], 0.3)
    df = df[df["condition"] != "c1"]
    r = fit_glmm(df, "correct", "condition", "participant")
    assert list(r.params.index) == ["Intercept", "condition[T.c2]"]
    assert "['c1']" in r.warnings[0]
    explicit = fit_glmm(df.assign(condition=df["condition"].astype(str)), "correct",
                        "C(condition, levels=['c0', 'c1', 'c2'])", "participant")
    assert "aliased" in explicit.warnings[0] and len(explicit.params) == 2


def test_p_value_is_never_zero(rng):
    df = simulate_trials(rng, 30, 400, [-2.0, 3.0], 0.2)
    r = fit_glmm(df, "correct", "condition", "participant")
    assert r.zvalues.iloc[1] > 40
    assert r.pvalues.iloc[1] > 0.0 and format_pvalue(r.pvalues.iloc[1]) == "< 1e-16"


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"response": "answer"}, "response column 'answer' is not in the data"),
    ({"groups": "subject"}, "group column 'subject'"),
    ({"fixed": "correct ~ condition"}, "right-hand side"),
    ({"fixed": "nonsense_column"}, "fixed-effects formula 'nonsense_column'"),
    ({"method": "pql"}, "method must be 'laplace' or 'agq', got 'pql'"),
    ({"method": "agq", "n_quadrature": 0}, "n_quadrature must be an integer"),
    ({"response": "digit"}, "must be 0/1 per trial"),
    ({"trials": "digit"}, "integers between 0 and 'digit'"),
])
def test_bad_input(two_conditions, kwargs, match):
    args = {"response": "correct", "fixed": "condition", "groups": "participant", **kwargs}
    with pytest.raises(AnalysisError, match=match):
        fit_glmm(two_conditions, **args)


def test_missing_values_are_errors(two_conditions):
    df = two_conditions.copy()
    df["correct"] = df["correct"].astype(float)
    df.loc[3, "correct"] = np.nan
    with pytest.raises(AnalysisError, match="1 missing or non-numeric"):
        fit_glmm(df, "correct", "condition", "participant")
    df = two_conditions.copy()
    df["participant"] = df["participant"].astype(object)
    df.loc[5, "participant"] = None
    with pytest.raises(AnalysisError, match="group column 'participant' has 1 missing"):
        fit_glmm(df, "correct", "condition", "participant")


def test_unbalanced_real_dataset_shape_against_statsmodels():
    """What a real dataset brings at once: 1 to 120 trials per participant (one with a single
    trial), a participant 100 % correct, three conditions with 'pixel-only' as reference.
    The all-correct participant is not separation of a fixed effect (its intercept is a random
    effect), so no penalty; the LRT of condition has df 2, of the variance the 50:50 mixture;
    the variance-0 fit is statsmodels' GLM (estimates and standard errors); the profile
    interval holds the estimate and is within 25 % of the Wald width."""
    import statsmodels.api as sm
    import statsmodels.formula.api as smf

    rng = np.random.default_rng(7)
    rows = []
    for p in range(12):
        u = rng.normal(0.0, 0.8)
        for t in range([1, 5, 40, 80, 120][p % 5]):
            c = ("pixel-only", "crs", "crs-fast")[t % 3]
            eta = 0.2 + {"pixel-only": 0.0, "crs": 0.8, "crs-fast": 0.4}[c] + u
            rows.append((f"p{p}", c, int(rng.random() < expit(eta))))
    rows += [("all", c, 1) for c in ("pixel-only", "crs", "crs-fast") * 10]
    data = pd.DataFrame(rows, columns=["participant", "condition", "correct"])
    formula = "C(condition, Treatment('pixel-only'))"
    full = fit_glmm(data, "correct", formula, "participant")
    assert full.penalty is None and not full.warnings
    assert full.params.index[1].endswith("[T.crs]")
    by_condition = lrt(full, fit_glmm(data, "correct", "1", "participant"))
    assert by_condition.df == 2 and by_condition.distribution == "chi2(2)"
    no_variance = fit_glmm(data, "correct", formula)
    by_variance = lrt(full, no_variance)
    assert by_variance.df == 1 and by_variance.distribution == "0.5 chi2(0) + 0.5 chi2(1)"
    assert 0.0 < by_variance.pvalue < 1e-10 and (full.pvalues > 0).all()
    glm = smf.glm(f"correct ~ {formula}", data, family=sm.families.Binomial()).fit()
    np.testing.assert_allclose(no_variance.params.to_numpy(), glm.params.to_numpy(), atol=1e-6)
    np.testing.assert_allclose(no_variance.bse.to_numpy(), glm.bse.to_numpy(), rtol=1e-4)
    wald = full.conf_int()
    profile = profile_conf_int(full)
    assert (profile["ci_low"] < full.params).all() and (full.params < profile["ci_high"]).all()
    ratio = (profile["ci_high"] - profile["ci_low"]) / (wald["ci_low"].rsub(wald["ci_high"]))
    assert ratio.between(0.95, 1.25).all()
