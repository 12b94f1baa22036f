"""Secondary tests: McNemar mid-p against Fagerland et al., paired t and Wilcoxon against
scipy, effect sizes by hand, Holm against its definition."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from statsmodels.stats.multitest import multipletests

from crs_study.analysis.plan import CORRECTIONS
from crs_study.analysis.secondary import (
    adjusted_p_values,
    mcnemar_midp,
    mcnemar_test,
    paired_t,
    paired_table,
    participant_differences,
    per_symbol,
    secondary_tests,
    wilcoxon_signed_rank,
)


def test_mcnemar_matches_fagerland_2013_worked_example():
    # Fagerland MW, Lydersen S, Laake P (2013) BMC Med Res Methodol 13:91, Table 1: airway
    # hyper-responsiveness before/after stem cell transplantation in 21 children (Bentur et
    # al.), discordant pairs n12 = 1, n21 = 7; exact conditional p = 0.070, mid-p = 0.039.
    exact, mid = mcnemar_midp(1, 7)
    assert exact == pytest.approx(0.0703125, abs=1e-12)       # 2 * 9 / 256
    assert mid == pytest.approx(0.0390625, abs=1e-12)         # 2 * 9/256 - 8/256
    assert round(exact, 3) == 0.070 and round(mid, 3) == 0.039
    assert mcnemar_midp(7, 1) == (exact, mid)


def test_mcnemar_mid_p_with_equal_discordant_counts_follows_the_supplement():
    # Fagerland et al. 2013, supplement: if n12 = n21, mid-p = 1 - 0.5 binompdf(n12, n, 0.5)
    exact, mid = mcnemar_midp(3, 3)
    assert exact == 1.0
    assert mid == pytest.approx(1 - 0.5 * stats.binom.pmf(3, 6, 0.5))


def _pairs(table):
    a, b, c, d = table
    ref = [1] * a + [1] * b + [0] * c + [0] * d
    cond = [1] * a + [0] * b + [1] * c + [0] * d
    return pd.DataFrame({"ref": ref, "cond": cond})


def test_mcnemar_test_reports_the_conditional_odds_ratio():
    result = mcnemar_test(_pairs((1, 1, 7, 12)), "after", "before")
    assert result.estimate == 7.0 and result.p_value == pytest.approx(0.0390625)
    assert result.extra["p_exact"] == pytest.approx(0.0703125)
    # exact interval of c / (b + c) = 7/8, mapped by p / (1 - p)
    ci = stats.binomtest(7, 8).proportion_ci(0.95, method="exact")
    assert result.ci95 == pytest.approx((ci.low / (1 - ci.low), ci.high / (1 - ci.high)))
    assert result.ci95[0] < 7.0 < result.ci95[1]


def test_no_discordant_pairs_gives_p_one_and_says_so():
    result = mcnemar_test(_pairs((5, 0, 0, 5)), "crs", "pixel-only")
    assert result.p_value == 1.0 and result.estimate is None
    assert "no discordant pairs" in result.note


def test_one_sided_discordance_gives_a_finite_corrected_odds_ratio():
    result = mcnemar_test(_pairs((5, 0, 6, 5)), "crs", "pixel-only")
    assert result.estimate == pytest.approx(6.5 / 0.5) and np.isinf(result.ci95[1])
    assert "b = 0" in result.note and 0 < result.p_value < 0.05


def test_paired_t_matches_scipy_and_cohen_dz():
    diffs = pd.Series([0.1, 0.25, -0.05, 0.3, 0.2, 0.15])
    result = paired_t(diffs, "crs", "pixel-only")
    before = np.array([0.4, 0.5, 0.6, 0.45, 0.5, 0.55])
    reference = stats.ttest_rel(before + diffs.to_numpy(), before)
    assert result.p_value == pytest.approx(reference.pvalue)
    assert result.statistic == pytest.approx(reference.statistic)
    assert result.effect_size == pytest.approx(diffs.mean() / diffs.std(ddof=1))  # Lakens Eq.6
    assert result.ci95[0] < diffs.mean() < result.ci95[1]


def test_paired_t_without_spread_or_participants_explains_itself():
    flat = paired_t(pd.Series([0.1, 0.1, 0.1]), "crs", "pixel-only")
    assert flat.p_value is None and "no spread" in flat.note
    alone = paired_t(pd.Series([0.1]), "crs", "pixel-only")
    assert alone.p_value is None and "needs 2 or more participants" in alone.note


def test_wilcoxon_matches_scipy_and_rank_biserial_by_hand():
    diffs = pd.Series([0.12, -0.04, 0.2, 0.08, 0.3, 0.16, -0.1, 0.22])
    result = wilcoxon_signed_rank(diffs, "crs", "pixel-only")
    assert result.p_value == pytest.approx(stats.wilcoxon(diffs).pvalue)
    # ranks of |d|: .04->1 .08->2 .1->3 .12->4 .16->5 .2->6 .22->7 .3->8; T- = 1 + 3 = 4
    assert (result.extra["t_plus"], result.extra["t_minus"]) == (32.0, 4.0)
    assert result.effect_size == pytest.approx((32 - 4) / 36)        # Kerby 2014
    assert result.note == ""


def test_wilcoxon_treats_differences_equal_in_exact_arithmetic_as_ties():
    # Accuracies out of 10 trials (reference, condition). In floats 0.7 - 0.4 and 0.8 - 0.5
    # are 0.29999999999999993 and 0.30000000000000004, and 0.3 - 0.2 is 0.09999999999999998:
    # without rounding the tied |0.3| and |0.1| groups get distinct ranks (T = 12, p = 0.242).
    pairs = [(0.4, 0.7), (0.5, 0.8), (0.3, 0.0), (0.9, 0.8), (0.1, 0.2), (0.6, 0.7),
             (0.0, 0.3), (0.2, 0.6), (0.5, 0.3), (0.4, 0.4)]
    rows = [{"participant_id": f"p{i}", "condition": name, "accuracy": value}
            for i, pair in enumerate(pairs)
            for name, value in zip(("ref", "crs"), pair, strict=True)]
    diffs = participant_differences(pd.DataFrame(rows), "crs", "ref")
    assert len(set(diffs.abs())) == 5                       # 0, 0.1, 0.2, 0.3, 0.4
    result = wilcoxon_signed_rank(diffs, "crs", "ref")
    # the same test on the exact differences in tenths (integers, no rounding issue):
    # scipy.stats.wilcoxon([3, 3, -3, -1, 1, 1, 3, 4, -2]) -> statistic 12.5, p 0.265625
    exact = stats.wilcoxon([3, 3, -3, -1, 1, 1, 3, 4, -2])
    assert (exact.statistic, exact.pvalue) == (12.5, pytest.approx(0.265625))
    assert result.statistic == 12.5 and result.p_value == pytest.approx(exact.pvalue)
    # midranks: |1| x3 -> 2, |2| -> 4, |3| x4 -> 6.5, |4| -> 9; T- = 6.5 + 2 + 4 = 12.5
    assert (result.extra["t_plus"], result.extra["t_minus"]) == (32.5, 12.5)
    assert "1 zero difference(s) dropped" in result.note      # 0.4 - 0.4 is a zero


def test_wilcoxon_with_five_participants_warns_it_cannot_reject():
    result = wilcoxon_signed_rank(pd.Series([0.1, 0.2, 0.3, 0.4, 0.5]), "crs", "pixel-only")
    assert result.p_value == pytest.approx(0.0625)                    # 2 / 2^5, all positive
    assert "smallest attainable two-sided p is 0.0625" in result.note
    assert "cannot reject" in result.note


def test_per_digit_holm_matches_its_definition():
    rng = np.random.default_rng(4)
    rows = []
    for p in range(12):
        for d in range(4):
            for r in range(3):
                for c, acc in (("pixel-only", 0.4), ("crs", 0.4 + 0.15 * d)):
                    rows.append({"participant_id": f"p{p}", "session": "1", "digit": d,
                                 "repetition": r, "condition": c,
                                 "correct": float(rng.random() < acc)})
    table, _ = per_symbol(pd.DataFrame(rows), "crs", "pixel-only", "holm")
    p = table["p_value"].to_numpy()
    order = np.argsort(p)
    m = len(p)
    holm = np.maximum.accumulate([min(1.0, (m - i) * p[j]) for i, j in enumerate(order)])
    expected = np.empty(m)
    expected[order] = holm                                            # Holm 1979
    assert table["p_adjusted"].to_numpy() == pytest.approx(expected)
    assert (table["n_pairs"] == 36).all()


# p-values as the per-symbol tests give them: ties (symbols alike), ones, tiny values
P_VALUES = st.lists(st.sampled_from([1.0, 0.5, 0.25, 0.05, 1e-300]) | st.floats(0.0, 1.0),
                    max_size=30).map(lambda p: np.array(p, dtype=float))


@settings(max_examples=300, deadline=None)
@given(P_VALUES, st.sampled_from([c for c in CORRECTIONS if c != "none"]))
def test_adjusted_p_values_are_statsmodels_multipletests_bit_for_bit(p, correction):
    # outside reference: statsmodels' multipletests (Holm's is computed without it)
    # statsmodels' Holm branch runs gc.collect() (a tenth of a second in a test worker),
    # which changes no number: held off here, 300 examples would take 20 s
    with np.errstate(divide="ignore"), mock.patch("gc.collect"):
        reference = multipletests(p, alpha=0.05, method=correction)[1]
    assert np.array_equal(adjusted_p_values(p, 0.05, correction), reference)
    assert np.array_equal(adjusted_p_values(p, 0.05, "none"), p)


def test_secondary_tests_run_every_planned_test():
    rows = []
    rng = np.random.default_rng(5)
    for p in range(8):
        for d in range(10):
            for c, acc in (("pixel-only", 0.5), ("crs", 0.7)):
                rows.append({"participant_id": f"p{p}", "session": "1", "digit": d,
                             "repetition": 0, "condition": c,
                             "correct": float(rng.random() < acc)})
    trials = pd.DataFrame(rows)
    by_participant = trials.groupby(["participant_id", "condition"])["correct"].mean() \
        .rename("accuracy").reset_index()
    result = secondary_tests(trials, by_participant, ["pixel-only", "crs"], "pixel-only",
                             ("paired_t", "wilcoxon", "mcnemar", "per_digit"))
    assert [t.method.split()[0] for t in result.tests] == ["paired", "Wilcoxon", "McNemar"]
    assert set(result.per_symbol) == {"crs"} and len(result.to_frame()) == 3


def test_pairs_keep_every_level_of_a_level_protocol():
    """A psychometric protocol repeats (digit, repetition) at each level; a pair must match the
    level too, or three quarters of these trials would be dropped as duplicates."""
    rows = [{"participant_id": "p1", "session": 1, "digit": d, "repetition": 0,
             "digit_height": h, "condition": c, "correct": float((d + h * 10 + (c == "crs")) % 2)}
            for d in range(3) for h in (0.5, 0.8, 1.2, 1.6) for c in ("pixel-only", "crs")]
    pairs = paired_table(pd.DataFrame(rows), "crs", "pixel-only")
    assert len(pairs) == 12
    assert sorted(set(pairs["digit_height"])) == [0.5, 0.8, 1.2, 1.6]
