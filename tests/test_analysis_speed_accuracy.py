"""Speed against accuracy: summaries, conditional accuracy functions, IES, RCS and BIS by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

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
    result = analyse_speed_accuracy(_trials(cells), ["x", "y"])
    summary = result.efficiency_summary.set_index("condition")
    per = result.efficiency.loc[result.efficiency["condition"] == "y", "ies"]
    assert summary.loc["y", "ies"] == pytest.approx(per.mean())
    assert summary.loc["y", "ies_ci_low"] < per.mean() < summary.loc["y", "ies_ci_high"]
    assert summary.loc["y", "accuracy"] > summary.loc["x", "accuracy"]
    assert summary.loc["y", "n_participants"] == 8 and not result.warnings
