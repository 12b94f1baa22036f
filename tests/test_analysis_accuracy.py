"""Accuracy tables: Wilson intervals against published values, binomial tests against scipy."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from crs_study.analysis.accuracy import (
    P_FLOOR,
    accuracy_table,
    analyse_accuracy,
    chance_level,
    floor_p,
    headline_accuracy,
    wilson_interval,
)
from crs_study.errors import AnalysisError


@pytest.mark.parametrize(("k", "n", "low", "high"), [
    # Newcombe RG (1998) Two-sided confidence intervals for the single proportion: comparison
    # of seven methods. Stat Med 17:857, Table I, method 3 (Wilson score, no continuity
    # correction); the same as R's prop.test(k, n, correct = FALSE)$conf.int.
    pytest.param(81, 263, 0.2553, 0.3662, id="81/263"),
    pytest.param(15, 148, 0.0624, 0.1605, id="15/148"),
    pytest.param(0, 20, 0.0000, 0.1611, id="0/20"),
    pytest.param(1, 29, 0.0061, 0.1718, id="1/29"),
])
def test_wilson_interval_matches_newcombe_1998(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert float(lo) == pytest.approx(low, abs=5e-5)
    assert float(hi) == pytest.approx(high, abs=5e-5)


@settings(max_examples=80, deadline=None)
@given(st.integers(1, 2000).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))),
       st.sampled_from([0.01, 0.05, 0.1]))
def test_wilson_interval_is_the_closed_form(kn, alpha):
    # Wilson 1927 / Brown, Cai & DasGupta 2001 Eq. 4, written out independently.
    k, n = kn
    z = stats.norm.ppf(1 - alpha / 2)
    p = k / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z / (1 + z**2 / n) * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    lo, hi = wilson_interval(k, n, alpha)
    assert float(lo) == pytest.approx(max(0.0, centre - half), abs=1e-12)
    assert float(hi) == pytest.approx(min(1.0, centre + half), abs=1e-12)
    assert 0.0 <= lo <= p <= hi <= 1.0


def _trials(rows):
    return pd.DataFrame(rows, columns=["participant_id", "condition", "digit", "correct"])


def test_table_counts_and_tests_against_chance():
    rng = np.random.default_rng(3)
    trials = _trials([(f"p{i % 4}", c, d, float(rng.random() < (0.6 if c == "crs" else 0.4)))
                      for i in range(400) for c in ("pixel-only", "crs") for d in [i % 10]])
    table = accuracy_table(trials, ["condition"], 0.1)
    for _, row in table.iterrows():
        subset = trials.loc[trials["condition"] == row["condition"], "correct"]
        assert row["n_trials"] == len(subset) and row["n_correct"] == subset.sum()
        assert row["p_vs_chance"] == floor_p(stats.binomtest(int(subset.sum()), len(subset),
                                                             0.1).pvalue)


def test_timed_out_trials_are_not_counted():
    trials = _trials([("a", "crs", 1, 1.0), ("a", "crs", 2, np.nan), ("a", "crs", 3, 0.0)])
    row = accuracy_table(trials, ["condition"], 0.1).iloc[0]
    assert (row["n_trials"], row["n_correct"]) == (2, 1)


def test_analyse_orders_conditions_and_makes_every_table():
    trials = _trials([("a", c, d, float(d % 2)) for c in ("crs", "pixel-only")
                      for d in range(10)] + [("b", "crs", 1, 1.0)])
    result = analyse_accuracy(trials, ("pixel-only", "crs"), 0.1)
    assert list(result.by_condition["condition"]) == ["pixel-only", "crs"]
    assert len(result.by_participant) == 3 and len(result.by_symbol) == 20
    assert result.condition_row("crs")["n_trials"] == 11
    with pytest.raises(AnalysisError, match=r"no accuracy for condition 'x'"):
        result.condition_row("x")


def test_p_values_never_reach_zero():
    # 5000 of 5000 correct against chance 0.1: the exact p underflows to 0 in double precision
    assert stats.binomtest(5000, 5000, 0.1).pvalue == 0.0
    trials = _trials([("a", "crs", 1, 1.0)] * 5000)
    assert accuracy_table(trials, ["condition"], 0.1)["p_vs_chance"].iloc[0] == P_FLOOR


def test_chance_level_is_one_over_the_digits_shown():
    trials = _trials([("a", "crs", d, 1.0) for d in (0, 1, 2, 3)])
    assert chance_level(trials) == 0.25
    assert chance_level(trials, 0.5) == 0.5
    with pytest.raises(AnalysisError, match=r"chance level undefined: the trials show 1 digit"):
        chance_level(trials.iloc[:1])


def test_between_participant_interval_is_scipy_t_and_stays_in_range():
    from crs_study.analysis.accuracy import between_participant_table

    table = pd.DataFrame({"participant_id": ["a", "b", "c", "a", "b", "c"],
                          "condition": ["x"] * 3 + ["y"] * 3,
                          "accuracy": [0.4, 0.5, 0.6, 0.9, 1.0, 1.0]})
    out = between_participant_table(table, ("x", "y")).set_index("condition")
    low, high = stats.t.interval(0.95, 2, loc=0.5, scale=stats.sem([0.4, 0.5, 0.6]))
    assert (out.loc["x", "ci_low"], out.loc["x", "ci_high"]) == pytest.approx((low, high))
    assert out.loc["x", "method"] == "t interval on participant accuracies"
    # 0.9, 1, 1: the t interval reaches 1.11; reported up to 1, and said so
    assert out.loc["y", "ci_high"] == 1.0 and out.loc["y", "ci_low"] < out.loc["y", "mean"]
    assert out.loc["y", "method"].endswith("clipped to [0, 1]")


def _participants(correct_by_participant: dict[str, int], n: int = 50) -> pd.DataFrame:
    rows = [{"participant_id": p, "condition": "crs", "digit": i % 10, "correct": float(i < k)}
            for p, k in correct_by_participant.items() for i in range(n)]
    return pd.DataFrame(rows)


def test_the_headline_interval_accounts_for_participants():
    # Three participants at 30, 50 and 76 % (50 trials each): the pooled Wilson interval
    # (trial level) is far narrower than the t interval across participants, which the
    # headline shows ([42.0, 58.0] against [22.8, 76.8] on such data).
    result = analyse_accuracy(_participants({"a": 15, "b": 25, "c": 38}), ("crs",), 0.1)
    (row,) = headline_accuracy(result).to_dict("records")
    per = np.array([0.30, 0.50, 0.76])
    low, high = stats.t.interval(0.95, 2, loc=per.mean(), scale=stats.sem(per))
    assert row["method"] == "mean of participant accuracies, t interval across participants"
    assert (row["accuracy"], row["ci_low"], row["ci_high"]) == pytest.approx(
        (per.mean(), max(low, 0.0), min(high, 1.0)))
    pooled = result.by_condition.iloc[0]
    assert row["ci_high"] - row["ci_low"] > 3 * (pooled["ci_high"] - pooled["ci_low"])


@pytest.mark.parametrize(("counts", "why"), [({"a": 20}, "one participant"),
                                             ({"a": 20, "b": 20}, "every participant alike")])
def test_the_headline_falls_back_to_the_pooled_interval_and_says_why(counts, why):
    result = analyse_accuracy(_participants(counts), ("crs",), 0.1)
    (row,) = headline_accuracy(result).to_dict("records")
    pooled = result.by_condition.iloc[0]
    assert (row["ci_low"], row["ci_high"]) == (pooled["ci_low"], pooled["ci_high"])
    assert row["method"] == (f"Wilson interval of the pooled trials; {why}, so no "
                             "participant-level interval")
