"""The whole analysis: results.json, report, charts, headline, the command line, and a result
with a warning (never a crash, a silent NaN or a p of 0) in every degenerate case."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from analysis_fixtures import CHI2_PLAN, dataset, explicit_dataset, session_files, write_plan
from scipy import stats

from crs_study.analysis.headline import format_p, headline
from crs_study.analysis.report import analyze, analyze_dataset
from crs_study.cli import main
from crs_study.paths import data_dir

CONDITIONS = ("pixel-only", "crs")


def _no_bad_numbers(value, where="results"):
    """No NaN, no infinity and no p-value of exactly 0 anywhere in results.json."""
    if isinstance(value, dict):
        for key, item in value.items():
            if key.startswith("p_") and isinstance(item, float):
                assert item > 0, f"{where}.{key} is 0"
            _no_bad_numbers(item, f"{where}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _no_bad_numbers(item, f"{where}[{i}]")
    elif isinstance(value, float):
        assert math.isfinite(value), where


def _cells(n_participants, accuracy, repetitions=2, seed=0):
    rng = np.random.default_rng(seed)
    return {f"{p + 1:02d}": [(c, d, r, int(rng.random() < accuracy[c])) for c in accuracy
                            for d in range(10) for r in range(repetitions)]
            for p in range(n_participants)}


def _twenty_participants(path):
    """A dataset of 20 participants, one repetition each: the plan's rule ("auto", the
    parametric bootstrap below 20 participants) takes the chi2 p for it. The tests of where the
    analysis writes, which plan it reads, the HTML report, what the command prints and how it
    reports an edited trial file use it: with 3 participants the bootstrap's refits of the
    maximal GLMM cost seven times the analysis, for a p they do not read."""
    return dataset(path, n_participants=20, repetitions=1)


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    root = dataset(tmp / "ds", n_participants=8, repetitions=4)
    plan = write_plan(tmp / "plan.toml")
    return root, plan, analyze([root], plan, tmp / "out")


def test_results_json_holds_the_promised_keys(full_run):
    _, _, result = full_run
    saved = json.loads(result.results_path.read_text())
    assert saved == result.results
    for condition in CONDITIONS:
        row = saved["conditions"][condition]
        assert {"n_trials", "n_correct", "accuracy", "ci95", "p_vs_chance"} <= set(row)
        assert row["ci95"][0] < row["accuracy"] < row["ci95"][1]
    glmm = saved["comparisons"][0]
    assert glmm["method"].startswith("GLMM") and glmm["estimate"] > 1
    assert {"method", "estimate", "ci95", "p_value"} <= set(glmm)
    methods = [c["method"].split()[0] for c in saved["comparisons"]]
    assert methods == ["GLMM", "paired", "Wilcoxon", "McNemar"]
    assert set(saved["information_transfer"]) == set(CONDITIONS)
    assert saved["information_transfer"]["crs"]["ci95"] is not None
    assert isinstance(saved["warnings"], list) and saved["headline"] == result.headline
    assert saved["psychometric"]["skipped"] and saved["sessions"][0]["TrialsSha256"]
    _no_bad_numbers(saved)


def test_report_and_charts_are_written(full_run):
    _, _, result = full_run
    text = result.report_path.read_text()
    assert result.report_path.name == "report.md" and result.headline in text
    charts = result.results["charts"]
    assert {"figures/accuracy.png", "figures/speed_accuracy.png", "figures/caf.png"} <= \
        set(charts)
    assert sum(c.startswith("figures/confusion_") for c in charts) == 2
    assert result.chart("speed_accuracy") == result.results_path.parent / \
        "figures/speed_accuracy.png"
    for chart in charts:
        png = (result.results_path.parent / chart).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and f"]({chart})" in text


def test_headline_reads_like_the_paper(full_run):
    _, _, result = full_run
    crs = result.results["conditions"]["crs"]
    # the headline's interval accounts for participants (the pooled Wilson one
    # stays in the table): the mean of participant accuracies with its t interval
    shown = crs["headline"]
    assert shown["accuracy"] == pytest.approx(crs["between_participants"]["mean"])
    assert shown["ci95"] == pytest.approx(crs["between_participants"]["ci95"])
    low, high = shown["ci95"]
    assert result.headline.startswith(f"crs {100 * shown['accuracy']:.1f} % "
                                      f"[{100 * low:.1f}, {100 * high:.1f}]")
    assert " vs pixel-only " in result.headline and "; GLMM odds ratio " in result.headline
    n = result.results["n_participants"]
    assert f"(mean of {n} participants, 95 % t interval across participants); GLMM" in \
        result.headline
    assert "Wilson" not in result.headline and "penalised" not in result.headline


def test_headline_takes_the_kind_of_comparison_from_fields_not_from_method_labels(full_run):
    """headline() read its flags out of method labels ("no random effect estimable" in the
    label; a comparison counted as primary when its label began with GLMM or Fisher)."""
    _, _, result = full_run
    results = json.loads(json.dumps(result.results))  # as results.json holds them
    first = results["comparisons"][0]
    assert (first["primary"], first["test"], first["logistic_regression"]) == (
        True, "glmm", False)
    assert all(not c["primary"] for c in results["comparisons"][1:])
    first["method"] = "a label that says nothing"
    first["logistic_regression"] = True
    results["comparisons"][1]["method"] = "GLMM lookalike (a secondary test)"
    text = headline(results)
    assert "; GLMM odds ratio (logistic regression: no participant variance estimable) " in text
    assert text.count("odds ratio") == 1
    first["test"] = "fisher"
    assert "; odds ratio (Fisher) (logistic regression" in headline(results)


def test_pooled_and_between_participant_accuracy_intervals(full_run):
    _, _, result = full_run
    crs = result.results["conditions"]["crs"]
    assert crs["ci95_method"].startswith("Wilson score interval of the pooled trials")
    per = [r["accuracy"] for r in result.results["accuracy_by_participant"]
           if r["condition"] == "crs"]
    between = crs["between_participants"]
    low, high = stats.t.interval(0.95, len(per) - 1, loc=np.mean(per), scale=stats.sem(per))
    assert between["mean"] == pytest.approx(np.mean(per))
    assert between["ci95"] == pytest.approx([low, high])
    assert between["method"] == "t interval on participant accuracies"
    assert between["n_participants"] == len(per) == crs["n_participants"]
    # participants differ, so the between-participant interval is the wider one
    assert high - low > crs["ci95"][1] - crs["ci95"][0]
    text = result.report_path.read_text()
    assert "Pooled trials: `ci_low`, `ci_high` are the Wilson interval" in text
    assert "Between participants: the mean of the participants' accuracies" in text


def test_mcnemar_is_labelled_mid_p_with_the_exact_p_apart(full_run):
    _, _, result = full_run
    (mcnemar,) = [c for c in result.results["comparisons"] if "McNemar" in c["method"]]
    assert mcnemar["method"].startswith("McNemar mid-p test (p_value the mid-p; p_exact the "
                                        "exact conditional test)")
    assert mcnemar["p_value"] == mcnemar["p_mid"] <= mcnemar["p_exact"]


def test_reanalysis_gives_identical_results(full_run, tmp_path):
    root, plan, first = full_run
    second = analyze([root], plan, tmp_path / "again")
    a, b = dict(first.results), dict(second.results)
    a.pop("generated_at"), b.pop("generated_at")
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_default_output_is_a_bids_derivative_and_the_protocol_plan_is_used(tmp_path):
    root = _twenty_participants(tmp_path / "ds")
    result = analyze_dataset(root)
    out = root / "derivatives" / "crs-study"
    assert result.results_path == out / "results.json"
    description = json.loads((out / "dataset_description.json").read_text())
    assert description["DatasetType"] == "derivative"
    assert result.results["plan"]["path"].endswith("analysis/digit_identification.toml")


def test_the_shipped_plan_is_named_without_the_install_location(tmp_path, monkeypatch):
    # From a folder without analysis/, the shipped plan is used; it is named by its place in
    # the package, not the install location (which can name the user's home folder).
    root = _twenty_participants(tmp_path / "ds")
    monkeypatch.chdir(tmp_path)
    result = analyze_dataset(root)
    assert result.results["plan"]["path"] == "crs_study/data/analysis/digit_identification.toml"
    for written in (result.results_path, *result.results_path.parent.glob("report.*")):
        assert str(data_dir()) not in written.read_text()


def test_html_report(tmp_path):
    root = _twenty_participants(tmp_path / "ds")
    plan = write_plan(tmp_path / "p.toml", '[plan]\nname = "h"\n[report]\nformat = "html"\n'
                      'charts = ["accuracy"]\n[confusion]\nbootstrap = 50\n')
    result = analyze([root], plan, tmp_path / "out")
    assert result.report_path.name == "report.html"
    assert result.report_path.read_text().startswith("<!DOCTYPE html>")
    assert result.results["charts"] == ["figures/accuracy.png"]


def test_psychometric_functions_when_a_level_varies(tmp_path):
    root = dataset(tmp_path / "ds", n_participants=4, repetitions=6, level_column="digit_height",
                   levels=(0.4, 0.6, 0.8, 1.0, 1.2), level_threshold=0.8, level_slope=8.0)
    result = analyze([root], write_plan(tmp_path / "p.toml", CHI2_PLAN), tmp_path / "out")
    psychometric = result.results["psychometric"]
    assert psychometric["level_column"] == "digit_height" and not psychometric["skipped"]
    assert set(psychometric["fits"]) == set(CONDITIONS)
    assert "figures/psychometric.png" in result.results["charts"]


# --- degenerate data, one test each -------------------------------------------------------------

def _run(tmp_path, cells):
    root = explicit_dataset(tmp_path / "ds", cells)
    result = analyze([root], write_plan(tmp_path / "plan.toml"), tmp_path / "out")
    _no_bad_numbers({k: v for k, v in result.results.items()})
    return result


def test_separation_every_answer_right_in_one_condition(tmp_path):
    result = _run(tmp_path, _cells(8, {"pixel-only": 0.5, "crs": 1.0}))
    assert result.results["conditions"]["crs"]["accuracy"] == 1.0
    glmm = result.results["comparisons"][0]
    # separation: the ML odds ratio does not exist; the primary figure is the one-sided limit
    # of the unpenalised profile, the penalised fit is kept apart and labelled
    assert glmm["separated"] and glmm["estimate"] is None and glmm["p_wald"] is None
    low, high = glmm["ci95"]
    assert 1 < low < 1e6 and high is None
    assert glmm["ci_method"].startswith("one-sided profile-likelihood limit of the unpenalised")
    penalised = glmm["penalised"]
    assert penalised["odds_ratio"] > 1 and penalised["ci95_wald"][1] < 1e6   # finite
    assert "never the primary figure" in penalised["note"]
    assert f"; GLMM odds ratio > {low:.3g} (ML estimate infinite" in result.headline
    assert "upper limit infinite" in result.headline and "penalised" not in result.headline
    report = result.report_path.read_text()
    assert "Penalised fit, for orientation only" in report
    assert f"odds ratio {penalised['odds_ratio']:.4g}" in report
    # every participant at 100 %: the between-participant interval is the point 1
    between = result.results["conditions"]["crs"]["between_participants"]
    assert between["ci95"] == [1.0, 1.0] and "no spread" in between["method"]
    # ... so the headline shows the pooled interval there, and says why
    assert "every participant alike" in result.results["conditions"]["crs"]["headline"][
        "method"]
    assert any("separation" in w and "penalised by normal priors" in w
               for w in result.warnings)


def test_separation_every_answer_wrong_in_one_condition(tmp_path):
    result = _run(tmp_path, _cells(8, {"pixel-only": 0.0, "crs": 0.6}))
    assert result.results["conditions"]["pixel-only"]["ci95"][0] == 0.0
    assert any("is at 0 % correct" in w for w in result.warnings)
    # the reference at 0 %: crs's odds ratio is infinite too, one-sided from below
    glmm = result.results["comparisons"][0]
    assert glmm["separated"] and glmm["ci95"][1] is None and glmm["ci95"][0] > 1
    assert f"GLMM odds ratio > {glmm['ci95'][0]:.3g} (ML estimate infinite" in result.headline


def test_single_participant(tmp_path):
    result = _run(tmp_path, _cells(1, {"pixel-only": 0.4, "crs": 0.7}, repetitions=4))
    assert "GLMM odds ratio (logistic regression: no participant variance estimable)" in \
        result.headline
    between = result.results["conditions"]["crs"]["between_participants"]
    assert between["ci95"] == [None, None] and between["method"] == \
        "no interval: 1 participant(s)"
    assert any("a single participant" in w for w in result.warnings)
    assert any("random intercept was dropped" in w for w in result.warnings)
    t_test = result.results["comparisons"][1]
    assert t_test["p_value"] is None and "needs 2 or more participants" in t_test["note"]


def test_missing_condition(tmp_path):
    result = _run(tmp_path, _cells(4, {"crs": 0.7}))
    assert result.results["comparisons"] == []
    assert "no comparison of conditions" in result.headline
    assert any("missing condition(s) ['pixel-only']" in w for w in result.warnings)


def test_no_discordant_pairs(tmp_path):
    cells = {f"{p:02d}": [(c, d, r, int((d + r + p) % 2 == 0)) for c in CONDITIONS
                          for d in range(10) for r in range(2)] for p in range(6)}
    result = _run(tmp_path, cells)
    mcnemar = result.results["comparisons"][3]
    assert mcnemar["p_value"] == 1.0 and mcnemar["estimate"] is None
    assert any("no discordant pairs" in w and "reported p = 1" in w for w in result.warnings)


def test_random_effect_variance_at_zero(tmp_path):
    # every participant answers exactly alike: no variation between participants at all
    cells = {f"{p:02d}": [(c, d, r, int((d + r) % 10 < (6 if c == "crs" else 5)))
                          for c in CONDITIONS for d in range(10) for r in range(2)]
             for p in range(8)}
    result = _run(tmp_path, cells)
    variances = result.results["primary"]["model"]["variance_components"]
    assert variances == {"participant_id:Intercept": 0.0, "participant_id:condition[crs]": 0.0}
    assert any("estimated at 0" in w for w in result.warnings)
    assert any("with every participant variance at 0" in w and
               "logistic regression without that random term" in w for w in result.warnings)


def test_five_or_fewer_participants_warn_about_wilcoxon(tmp_path):
    result = _run(tmp_path, _cells(5, {"pixel-only": 0.3, "crs": 0.9}, seed=1))
    wilcoxon = result.results["comparisons"][2]
    assert wilcoxon["p_value"] == pytest.approx(0.0625)
    assert any("smallest attainable two-sided p is 0.0625" in w for w in result.warnings)


def test_every_answer_wrong_draws_charts_without_matplotlib_warnings(tmp_path):
    # No condition has a correct response, so the speed-accuracy chart has no condition mean
    # to label: matplotlib warned "No artists with labels found to put in legend" (pytest
    # runs with warnings as errors, so a warning fails this test).
    result = _run(tmp_path, _cells(3, {"pixel-only": 0.0, "crs": 0.0}))
    assert result.chart("speed_accuracy").exists() and result.chart("caf").exists()


def test_format_p_never_prints_zero():
    assert format_p(0.0) == "p < 1e-16" and format_p(0.04567) == "p = 0.0457"
    assert format_p(3.2e-7) == "p = 3.20e-07" and format_p(None) == "p n/a"


# --- the command line -------------------------------------------------------------------------

def test_cli_prints_headline_and_writes_files(tmp_path, capsys):
    root = _twenty_participants(tmp_path / "ds")
    plan = write_plan(tmp_path / "p.toml")
    assert main(["analyze", str(root), "--plan", str(plan), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "GLMM odds ratio" in out and "report:" in out
    assert main(["analyze", str(root), "--plan", str(plan), "--out", str(tmp_path / "j"),
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["conditions"]


def test_cli_tampering_is_loud_and_strict_fails(tmp_path, capsys):
    root = _twenty_participants(tmp_path / "ds")
    plan = write_plan(tmp_path / "p.toml")
    tsv, _ = session_files(root)[0]
    original = tsv.read_bytes()
    edited = original.replace(b"\t1.0\t", b"\t1.1\t", 1)      # the first onset, edited
    assert edited != original
    tsv.write_bytes(edited)
    assert main(["analyze", str(root), "--plan", str(plan), "--out", str(tmp_path / "o")]) == 0
    assert "WARNING: " in capsys.readouterr().err
    assert main(["analyze", str(root), "--plan", str(plan), "--out", str(tmp_path / "o"),
                 "--strict"]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "TAMPERED?" in err and len(err.strip().splitlines()) == 1


def test_cli_refuses_a_dataset_given_twice_in_one_line(tmp_path, capsys):
    root = dataset(tmp_path / "ds", n_participants=2, repetitions=1)
    plan = write_plan(tmp_path / "p.toml")
    assert main(["analyze", str(root), str(root) + "/", "--plan", str(plan),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "(given twice)" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "results.json").exists()


def test_cli_bad_plan_is_one_line(tmp_path, capsys):
    root = dataset(tmp_path / "ds", n_participants=2, repetitions=1)
    plan = write_plan(tmp_path / "p.toml", '[plan]\nname = "x"\nalpha = 2\n')
    assert main(["analyze", str(root), "--plan", str(plan)]) == 2
    assert "plan.alpha: expected a number <= 0.5, got 2" in capsys.readouterr().err


def test_conditions_outside_the_plan_are_analysed_after_the_planned_ones():
    import pandas as pd

    from crs_study.analysis.plan import AnalysisPlan, order_conditions

    plan = AnalysisPlan.from_dict({"plan": {"name": "x", "conditions": ["pixel-only", "crs"]}})
    trials = pd.DataFrame({"condition": ["zeta", "crs", "pixel-only", "alpha"]})
    ordered, reference, notes = order_conditions(trials, plan)
    assert ordered == ["pixel-only", "crs", "alpha", "zeta"] and reference == "pixel-only"
    assert "condition(s) ['alpha', 'zeta'] are not in the plan" in notes[0]


def test_cli_unwritable_output_is_one_line(tmp_path, capsys):
    """--out under a file used to end in a traceback of OSErrors, after the whole analysis:
    now it is one line before any work."""
    root = dataset(tmp_path / "ds", n_participants=2, repetitions=1)
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["analyze", str(root), "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "--out: " in err and "file/out cannot be made" in err and "nothing was computed" in err


def test_results_agree_with_scipy_and_statsmodels_from_the_raw_files(full_run):
    """results.json recomputed independently from the stored TSVs: practice, device faults,
    time-outs and anticipations (< 0.15 s) left out; Wilson intervals from statsmodels
    ``proportion_confint(method="wilson")``, tests against chance from scipy ``binomtest``,
    McNemar's mid-p (Fagerland et al. 2013: exact two-sided p minus the point probability)
    on trials paired by participant, digit and repetition from scipy's binomial."""
    import glob

    import pandas as pd
    from scipy import stats
    from statsmodels.stats.proportion import proportion_confint

    root, _, result = full_run
    files = sorted(glob.glob(str(root / "sub-*/ses-*/beh/*_beh.tsv")))
    raw = pd.concat([pd.read_csv(f, sep="\t", na_values=["n/a"]).assign(p=f) for f in files])
    kept = raw[(raw.trial_type == "test") & (raw.device_fault == 0) & (raw.timed_out == 0)
               & (raw.response_time >= 0.15)]
    assert (raw.trial_type == "practice").any() and len(kept) < len(raw)
    for condition, rows in kept.groupby("condition"):
        k, n = int(rows.correct.sum()), len(rows)
        stored = result.results["conditions"][condition]
        assert (stored["n_correct"], stored["n_trials"]) == (k, n)
        assert stored["accuracy"] == pytest.approx(k / n, abs=1e-12)
        assert stored["ci95"] == pytest.approx(proportion_confint(k, n, method="wilson"),
                                               abs=1e-12)
        assert stored["p_vs_chance"] == pytest.approx(stats.binomtest(k, n, 0.1).pvalue,
                                                      rel=1e-9)
    pairs = kept.pivot_table(index=["p", "digit", "repetition"], columns="condition",
                             values="correct").dropna()
    b = int(((pairs["crs"] == 1) & (pairs["pixel-only"] == 0)).sum())
    c = int(((pairs["crs"] == 0) & (pairs["pixel-only"] == 1)).sum())
    n, low = b + c, min(b, c)
    mid_p = min(1.0, 2 * stats.binom.cdf(low, n, 0.5)) - stats.binom.pmf(low, n, 0.5)
    mcnemar = next(x for x in result.results["comparisons"] if "McNemar" in x["method"])
    assert mcnemar["p_value"] == pytest.approx(mid_p, rel=1e-9)
    assert mcnemar["estimate"] == pytest.approx(b / c, rel=1e-12)
