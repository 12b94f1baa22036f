"""Adaptive thresholds in the analysis: per participant and condition, paired comparison,
charts, report; on the default observer the CRS threshold is below the pixel-only one.

Outside references: the paired comparison against scipy.stats.ttest_rel on the same log
thresholds; the fit threshold against the logistic it was drawn from (recovery); Levitt
1971 for a fixed rule's target rate.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
from _power_helpers import chi2_plan
from _session_helpers import adaptive_protocol
from scipy import special, stats

import crs_study
from crs_study.analysis.thresholds import (
    AdaptiveDesign,
    analyse_thresholds,
    design_from_protocol,
    fit_threshold,
    rule_target,
)


def test_rule_targets_are_levitts():
    assert rule_target("1-up-2-down") == pytest.approx(0.7071, abs=1e-4)
    assert rule_target("1-up-3-down") == pytest.approx(0.7937, abs=1e-4)
    assert rule_target("weighted") is None


def test_design_from_a_protocol_text(tmp_path):
    text = adaptive_protocol(tmp_path, procedure="staircase").read_text()
    design = design_from_protocol(text)
    assert design == AdaptiveDesign("staircase", "digit_height", "log", 0.5 ** 0.5, 1)
    assert design_from_protocol("[study]\nid = 'x'\n") is None


def test_fit_threshold_recovers_the_generating_logistic():
    """Trials drawn from psi(u) = 0.1 + 0.88 logistic(6 (u + 0.2)): the level at 50 % is
    recovered without bias over 12 datasets, and the bootstrap interval holds the estimate."""
    truth = -0.2 + special.logit((0.5 - 0.1) / 0.88) / 6.0
    u = np.repeat(np.linspace(-0.6, 0.2, 9), 60)
    p = 0.1 + 0.88 * special.expit(6.0 * (u + 0.2))
    estimates = []
    for seed in range(12):
        correct = (np.random.default_rng(seed).random(len(u)) < p).astype(float)
        estimates.append(fit_threshold(u, correct, 0.1, 0.5, 0.1, 0,
                                       np.random.default_rng(1))["fit_threshold"])
    se = np.std(estimates, ddof=1) / np.sqrt(len(estimates))
    assert abs(np.mean(estimates) - truth) < 2.5 * se
    out = fit_threshold(u, correct, 0.1, 0.5, 0.1, 100, np.random.default_rng(1))
    assert out["fit_ci_low"] < out["fit_threshold"] < out["fit_ci_high"]
    assert out["fit_ci_high"] - out["fit_ci_low"] < 0.3


def synthetic(n=6, ratio=0.7, seed=3):
    """Stored tracks of n participants: CRS thresholds ``ratio`` times pixel-only."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n):
        base = 0.8 * 10 ** rng.normal(0, 0.05)
        for block, (condition, threshold) in enumerate((("pixel-only", base),
                                                        ("crs", base * ratio * 10 ** rng.normal(
                                                            0, 0.03)))):
            for t in range(30):
                level = float(np.round(threshold * 10 ** rng.normal(0, 0.15), 6))
                u = np.log10(level / threshold)
                correct = float(rng.random() < 0.1 + 0.88 * special.expit(8 * u + 0.9))
                rows.append({"participant_id": f"p{k}", "session": 1, "condition": condition,
                             "trial_type": "test", "trial_index": 100 * block + t,
                             "digit_height": level, "correct": correct,
                             "adaptive_estimate": threshold, "adaptive_ci_low": threshold * 0.9,
                             "adaptive_ci_high": threshold * 1.1,
                             "adaptive_reversal": float(t % 5 == 0),
                             "adaptive_reversals": t // 5})
    trials = pd.DataFrame(rows)
    protocol = ('[adaptive]\nparameter = "digit_height_pitch"\nprocedure = "quest-plus"\n'
                'scale = "log"\ntarget_rate = 0.5\n')
    return trials, pd.DataFrame({"Protocol": [protocol]})


def test_paired_comparison_is_scipys_paired_t_on_log_thresholds():
    trials, sessions = synthetic()
    result = analyse_thresholds(trials, trials, sessions, ["pixel-only", "crs"], "pixel-only",
                                0.1, n_bootstrap=0)
    assert not result.skipped and len(result.thresholds) == 12
    procedure = next(c for c in result.comparisons if c.method == "procedure")
    wide = result.thresholds.pivot(index="participant_id", columns="condition",
                                   values="procedure_threshold")
    reference = stats.ttest_rel(np.log10(wide["crs"]), np.log10(wide["pixel-only"]))
    assert procedure.t == pytest.approx(reference.statistic)
    assert procedure.pvalue == pytest.approx(reference.pvalue)
    assert procedure.ratio_ci95[0] < procedure.ratio < procedure.ratio_ci95[1] < 1.0
    assert procedure.ratio == pytest.approx(0.7, abs=0.05)
    assert "crs threshold (procedure) is 0." in procedure.sentence("digit_height")


def test_fixed_level_data_skip_thresholds():
    trials, sessions = synthetic()
    plain = trials.drop(columns=[c for c in trials if c.startswith("adaptive_")])
    assert analyse_thresholds(plain, plain, sessions, ["pixel-only", "crs"], "pixel-only",
                              0.1).skipped


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    """Six simulated participants of the default observer on a short QUEST+ protocol,
    analysed by the protocol's plan with two of its costs these tests never read cut: the
    GLMM's p against chi2 (the plan's rule draws up to 1000 refits below 20 participants for
    it) and 20 draws, not 200, for the fitted thresholds' intervals. The thresholds, their
    paired comparison, the charts and the report come out of the same code either way."""
    folder = tmp_path_factory.mktemp("adaptive")
    protocol = adaptive_protocol(folder, procedure="quest-plus", trials=24, levels=6,
                                 digits=(0, 1, 2, 3, 4, 5, 6, 7, 8, 9), practice=0)
    text = protocol.read_text().replace("min = 0.4", "min = 0.25").replace("max = 1.2",
                                                                           "max = 1.5")
    protocol.write_text(text)
    result = crs_study.dry_run(protocol, participants=6, out=folder / "ds")
    assert result.finished
    plan = chi2_plan(protocol)
    plan = dataclasses.replace(plan, psychometric=dataclasses.replace(plan.psychometric,
                                                                      bootstrap=20))
    return crs_study.analyze(folder / "ds", plan, write=True)


def test_on_the_default_observer_crs_thresholds_are_below_pixel_only(dry_run):
    thresholds = dry_run.thresholds
    assert not thresholds.skipped
    procedure = next(c for c in thresholds.comparisons if c.method == "procedure")
    assert procedure.condition == "crs" and procedure.reference == "pixel-only"
    assert procedure.ratio < 1.0 and procedure.n_pairs == 6
    report = dry_run.files.report.read_text()
    assert "## Adaptive thresholds" in report and "times the pixel-only threshold" in report
    assert dry_run.to_dict()["thresholds"]["procedure"] == "quest-plus"


def test_charts_of_tracks_and_fitted_functions(dry_run):
    names = {p.name for p in dry_run.files.charts}
    assert {"tracks.png", "thresholds.png"} <= names
    ax = dry_run.plot("tracks")
    assert ax.get_yscale() == "log" and len(ax.lines) >= 12
    ax = dry_run.plot("thresholds")
    assert ax.get_xscale() == "log"


def test_an_adaptive_study_is_headlined_by_its_thresholds(dry_run):
    """The procedure steers accuracy towards its target: the headline is the threshold
    comparison, the accuracy GLMM a secondary result (in results.json and the report)."""
    procedure = next(c for c in dry_run.thresholds.comparisons if c.method == "procedure")
    headline = dry_run.headline
    assert headline.startswith(f"crs threshold {procedure.ratio:.3g} x pixel-only")
    assert f"paired t({procedure.n_pairs - 1})" in headline
    assert "accuracy steered by the procedure" in headline and "GLMM" not in headline
    glmm = [c for c in dry_run.to_dict()["comparisons"] if c.get("test") == "glmm"]
    assert glmm and not any(c["primary"] for c in glmm)
    assert all("adaptive procedure" in c["secondary_because"] for c in glmm)
    report = dry_run.files.report.read_text()
    assert "## Accuracy model (secondary: the thresholds answer an adaptive study)" in report
