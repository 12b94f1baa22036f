"""Confusions and information transfer: hand-computed matrices, Miller & Nicely's definition,
the Miller-Madow correction, seeded bootstrap intervals."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from crs_study.analysis.confusion import (
    analyse_confusions,
    confusion_counts,
    information_transfer,
)


def test_hand_computed_two_by_two():
    # N = [[3, 1], [1, 3]]: p = 3/8 on the diagonal, 1/8 off it, marginals 1/2. By hand:
    # T = 2 (3/8) log2(1.5) + 2 (1/8) log2(0.5) = 0.75 * 0.5849625 - 0.25 = 0.1887219
    # (= 1 - H(1/4), a binary symmetric channel with error 1/4).
    counts = np.array([[3, 1], [1, 3]])
    assert information_transfer(counts, "none") == pytest.approx(0.1887219, abs=1e-7)
    # Miller-Madow: m_SR - m_S - m_R + 1 = 4 - 2 - 2 + 1 = 1, so subtract 1 / (2 * 8 * ln 2)
    assert information_transfer(counts) == pytest.approx(0.1887219 - 1 / (16 * np.log(2)),
                                                         abs=1e-7)


def test_perfect_and_independent_transmission():
    assert information_transfer(np.eye(4) * 25, "none") == pytest.approx(2.0)
    independent = np.outer([10, 20, 30], [1, 2, 3, 4])
    assert information_transfer(independent, "none") == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 40), min_size=9, max_size=9).filter(lambda v: sum(v) > 0))
def test_matches_miller_nicely_definition_and_shannon_entropies(cells):
    counts = np.array(cells, dtype=float).reshape(3, 3)
    p = counts / counts.sum()
    pi, pj = p.sum(1, keepdims=True), p.sum(0, keepdims=True)
    # Miller & Nicely 1955, Eq. 1: T(x; y) = -sum_ij p_ij log2(p_i p_j / p_ij)
    mask = p > 0
    direct = -np.sum(p[mask] * np.log2((pi * pj)[mask] / p[mask]))
    shannon = (stats.entropy(counts.sum(1), base=2) + stats.entropy(counts.sum(0), base=2)
               - stats.entropy(counts.ravel(), base=2))
    value = information_transfer(counts, "none")
    assert value == pytest.approx(direct, abs=1e-10)
    assert value == pytest.approx(shannon, abs=1e-10)
    assert -1e-12 <= value <= min(stats.entropy(counts.sum(1), base=2),
                                  stats.entropy(counts.sum(0), base=2)) + 1e-12


def test_bias_correction_brings_independent_samples_near_zero():
    rng = np.random.default_rng(1)
    samples = np.array([np.bincount(rng.integers(0, 100, 200), minlength=100).reshape(10, 10)
                        for _ in range(300)])
    plugin = information_transfer(samples, "none").mean()
    corrected = information_transfer(samples).mean()
    assert plugin > 0.2                  # the plug-in estimate is badly biased at N = 200
    assert abs(corrected) < plugin / 2   # Miller-Madow removes most of it


def _trials(seed=0, n_participants=6, accuracy=0.7):
    rng = np.random.default_rng(seed)
    rows = []
    for p in range(n_participants):
        for c in ("pixel-only", "crs"):
            for d in range(10):
                for _ in range(4):
                    right = rng.random() < (accuracy if c == "crs" else accuracy - 0.2)
                    rows.append({"participant_id": f"p{p}", "condition": c, "digit": d,
                                 "response": d if right else int(rng.integers(10))})
    trials = pd.DataFrame(rows)
    trials["response"] = trials["response"].astype("Int64")
    return trials


def test_counts_proportions_and_seeded_interval():
    trials = _trials()
    trials.loc[0, "response"] = pd.NA                              # a time-out
    results, warnings = analyse_confusions(trials, ["pixel-only", "crs"], n_bootstrap=300,
                                           seed=3)
    assert not warnings
    crs = results["crs"]
    assert crs.counts.shape == (10, 10) and crs.counts.to_numpy().sum() == crs.n_trials
    assert crs.proportions.sum(axis=1).to_numpy() == pytest.approx(np.ones(10))
    assert results["pixel-only"].n_no_response == 1
    assert crs.ci95[0] < crs.bits < crs.ci95[1]
    assert crs.bits > results["pixel-only"].bits
    again, _ = analyse_confusions(trials, ["pixel-only", "crs"], n_bootstrap=300, seed=3)
    assert again["crs"].ci95 == crs.ci95
    direct = confusion_counts(trials.loc[trials["condition"] == "crs"], list(range(10)))
    assert (direct.to_numpy() == crs.counts.to_numpy()).all()


def test_single_participant_resamples_trials_and_says_so():
    results, warnings = analyse_confusions(_trials(n_participants=1), ["crs"], n_bootstrap=100)
    assert results["crs"].bootstrap["unit"] == "trial"
    assert any("resampled trials instead of participants" in w for w in warnings)
