"""Speed against accuracy: summaries, conditional accuracy functions, IES, RCS and BIS by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from statsmodels.stats.proportion import proportion_confint

from crs_study.analysis.speed_accuracy import (
    analyse_speed_accuracy,
    conditional_accuracy,
    efficiency_scores,
    rt_summary,
)


def _trials(cells):
    rows = [{"participant_id": p, "condition": c, "correct": float(k), "response_time": rt}
            for p, c, k, rt in cells]
    return pd.DataFrame(rows)


HAND = _trials([
    ("a", "x", 1, 1.0), ("a", "x", 1, 2.0), ("a", "x", 0, 3.0), ("a", "x", 1, 2.0),
    ("b", "x", 1, 2.0), ("b", "x", 0, 2.0),
])


def test_inverse_efficiency_rate_correct_and_balanced_integration_by_hand():
    table, warnings = efficiency_scores(HAND, "response_time", ["x"])
    a, b = table.iloc[0], table.iloc[1]
    # participant a: PC = 3/4, mean correct RT = (1 + 2 + 2) / 3 = 5/3 s
    assert a["accuracy"] == 0.75 and a["mean_correct_rt"] == pytest.approx(5 / 3)
    assert a["ies"] == pytest.approx((5 / 3) / 0.75)            # Townsend & Ashby: RT / PC
    assert a["rcs"] == pytest.approx(3 / 8.0)                   # Woltz & Was: correct / sum RT
    assert b["ies"] == pytest.approx(2.0 / 0.5) and b["rcs"] == pytest.approx(1 / 4.0)
    # Liesefeld & Janczyk 2019: z across all cells (population sd); two cells -> z = +-1
    assert a["bis"] == pytest.approx(1 - (-1)) and b["bis"] == pytest.approx(-1 - 1)
    assert not warnings


def test_no_correct_response_leaves_ies_undefined_with_a_warning():
    trials = _trials([("a", "x", 0, 1.0), ("a", "x", 0, 2.0), ("b", "x", 1, 1.0)])
    table, warnings = efficiency_scores(trials, "response_time", ["x"])
    assert table.loc[0, "ies"] is None or pd.isna(table.loc[0, "ies"])
    assert any("no correct response" in w for w in warnings)


def test_rt_summary_median_and_quartiles():
    summary = rt_summary(HAND, "response_time", ["x"]).set_index("outcome")
    values = np.array([1.0, 2.0, 3.0, 2.0, 2.0, 2.0])
    assert summary.loc["all", "median"] == np.median(values)
    assert summary.loc["all", "q1"] == np.quantile(values, 0.25)
    assert summary.loc["error", "mean"] == pytest.approx(2.5)
    assert summary.loc["correct", "n"] == 4


def test_caf_bins_split_each_participant_equally():
    rng = np.random.default_rng(2)
    cells = [(f"p{p}", c, float(rng.random() < 0.8 - 0.1 * (rt > 2)), rt)
             for p in range(5) for c in ("x", "y") for rt in rng.uniform(1, 3, 20)]
    caf = conditional_accuracy(_trials(cells), "response_time", ["x", "y"], bins=4)
    assert list(caf["bin"].unique()) == [0, 1, 2, 3]
    assert (caf["n_trials"] == 25).all()                        # 5 participants x 20 / 4
    means = caf.loc[caf["condition"] == "x", "mean_rt"].to_numpy()
    assert (np.diff(means) > 0).all()                           # bins ordered by speed
    assert ((caf["ci_low"] <= caf["accuracy"]) & (caf["accuracy"] <= caf["ci_high"])).all()


def test_summary_means_and_intervals_per_condition():
    rng = np.random.default_rng(3)
    cells = [(f"p{p}", c, float(rng.random() < (0.7 if c == "y" else 0.5)),
              rng.lognormal(0.7, 0.2)) for p in range(8) for c in ("x", "y") for _ in range(30)]
    trials = _trials(cells)
    result = analyse_speed_accuracy(trials, ["x", "y"])
    summary = result.efficiency_summary.set_index("condition")
    per = result.efficiency.loc[result.efficiency["condition"] == "y", "ies"].astype(float)
    # IES is positive and skewed: geometric mean, t interval of the mean log (scipy), exp
    logs = np.log(per.to_numpy())
    low, high = stats.t.interval(0.95, 7, loc=logs.mean(), scale=stats.sem(logs))
    assert summary.loc["y", "ies"] == pytest.approx(np.exp(logs.mean()))
    assert (summary.loc["y", "ies_ci_low"], summary.loc["y", "ies_ci_high"]) == \
        pytest.approx((np.exp(low), np.exp(high)))
    assert summary.loc["y", "ies_method"] == "geometric mean, t interval on the log scale"
    # accuracy is the pooled proportion with its Wilson interval (statsmodels)
    y = trials.loc[trials["condition"] == "y", "correct"]
    wilson = proportion_confint(int(y.sum()), len(y), method="wilson")
    assert summary.loc["y", "accuracy"] == pytest.approx(y.mean())
    assert (summary.loc["y", "accuracy_ci_low"], summary.loc["y", "accuracy_ci_high"]) == \
        pytest.approx(wilson)
    assert summary.loc["y", "accuracy"] > summary.loc["x", "accuracy"]
    # BIS is unbounded: the plain mean with a t interval
    bis = result.efficiency.loc[result.efficiency["condition"] == "y", "bis"].astype(float)
    assert summary.loc["y", "bis"] == pytest.approx(bis.mean())
    assert summary.loc["y", "bis_ci_low"] == pytest.approx(
        stats.t.interval(0.95, 7, loc=bis.mean(), scale=stats.sem(bis))[0])
    assert summary.loc["y", "n_participants"] == 8 and not result.warnings


def test_summary_intervals_stay_in_range_with_two_extreme_participants():
    # Two participants, 19/20 and 20/20 correct, one ten times slower: the t intervals of
    # the arithmetic means went to 1.29 for accuracy and below 0 for RT, IES and RCS.
    cells = [(p, "x", float(i < k), rt * (1 + 0.1 * (i % 3)))
             for p, k, rt in (("a", 19, 0.4), ("b", 20, 4.0)) for i in range(20)]
    row = analyse_speed_accuracy(_trials(cells), ["x"]).efficiency_summary.iloc[0]
    assert 0 < row["accuracy_ci_low"] < row["accuracy"] < row["accuracy_ci_high"] < 1
    for measure in ("mean_correct_rt", "ies", "rcs"):
        assert 0 < row[f"{measure}_ci_low"] < row[measure] < row[f"{measure}_ci_high"]


def test_summary_of_all_correct_and_all_wrong_conditions():
    cells = [(f"p{p}", c, float(c == "easy"), 1.0 + 0.1 * p + 0.01 * i)
             for p in range(4) for c in ("easy", "hard") for i in range(10)]
    summary = analyse_speed_accuracy(_trials(cells), ["easy", "hard"]).efficiency_summary
    easy, hard = summary.iloc[0], summary.iloc[1]
    assert easy["accuracy"] == 1.0 and easy["accuracy_ci_high"] == 1.0
    assert 0.9 < easy["accuracy_ci_low"] < 1.0                 # Wilson: 40/40 -> [0.912, 1]
    assert hard["accuracy"] == 0.0 and hard["accuracy_ci_low"] == 0.0
    assert 0.0 < hard["accuracy_ci_high"] < 0.1
    assert hard["ies"] is None or pd.isna(hard["ies"])          # no correct response at all


def test_caf_edges_all_correct_and_all_wrong_bins():
    # fast responses always right, slow always wrong: the first bin is 100 %, the last 0 %
    cells = [(f"p{p}", "x", float(rt < 2.0), rt) for p in range(3)
             for rt in np.linspace(1.0, 3.0, 20)]
    caf = conditional_accuracy(_trials(cells), "response_time", ["x"], bins=4)
    first, last = caf.iloc[0], caf.iloc[-1]
    assert first["accuracy"] == 1.0 and first["ci_high"] == 1.0 and first["ci_low"] < 1.0
    assert last["accuracy"] == 0.0 and last["ci_low"] == 0.0 and last["ci_high"] > 0.0
    assert ((caf["ci_low"] >= 0) & (caf["ci_high"] <= 1)).all()
    low, high = proportion_confint(15, 15, method="wilson")      # 3 participants x 5 trials
    assert (first["ci_low"], first["n_trials"]) == (pytest.approx(low), 15)


def test_response_times_from_offset_can_be_negative_and_use_plain_means():
    cells = [(f"p{p}", "x", 1.0, -0.2 + 0.1 * p + 0.05 * i) for p in range(4) for i in range(5)]
    trials = _trials(cells).rename(columns={"response_time": "response_time_from_offset"})
    row = analyse_speed_accuracy(trials, ["x"], rt="response_time_from_offset"
                                 ).efficiency_summary.iloc[0]
    assert row["mean_correct_rt_method"] == "mean, t interval"
    assert row["mean_correct_rt"] == pytest.approx(np.mean([-0.2 + 0.1 * p + 0.1
                                                            for p in range(4)]))
