"""Bench area ``analysis``: the whole report on a 40 participants x 400 trials dataset.

The dataset is synthetic (:mod:`crs_study.analysis.synthetic`, 2 conditions x 10 digits x 20
repetitions a participant, plus practice), analysed with the shipped plan
``analysis/digit_identification.toml`` (GLMM with crossed participant and digit intercepts,
2000 bootstrap resamples, every chart). Baseline, measured in the same run: loading and
checking the dataset alone. Figures: the full report (target <= 10 s: a reanalysis stays
interactive) and, for orientation, the primary GLMM test alone (full and reduced fits and every
profile interval), both as ratios to loading; without ``--quick`` also the full report on 100
participants x 400 trials with the BLAS threads as installed (target < 3 s: a dense 110 x 110
solve per step once took 8-35 s there on a busy two-core machine with multithreaded OpenBLAS).

``--quick`` checks that every figure runs: 10 participants x 100 trials, once, with the
plan's resampling counts cut to :data:`QUICK_RESAMPLES` (below 20 participants the primary p
is the parametric bootstrap, whose 1000 refits are nine tenths of the quick report's time).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

from crs_study.analysis.load import load_datasets, with_exclusions
from crs_study.analysis.plan import AnalysisPlan, default_plan_path, load_plan, order_conditions
from crs_study.analysis.primary import primary_test
from crs_study.analysis.report import analyze
from crs_study.analysis.synthetic import SyntheticSpec, write_dataset
from crs_study.benchmarks import Figure, median_seconds

AREA = "analysis"
DESCRIPTION = "full analysis report on 40 participants x 400 trials, against loading alone"

#: Budget for the full report on the 40 x 400 dataset (s): a reanalysis stays interactive.
TARGET_REPORT_S = 10.0
#: Budget for the full report on 100 participants x 400 trials (s): a large study too.
TARGET_LARGE_REPORT_S = 3.0
#: The quick form's bootstrap counts: the primary test's replicates (its plan minimum is
#: 19), the confusion matrix's and the psychometric fits' resamples.
QUICK_RESAMPLES = 50


def run(quick: bool) -> list[Figure]:
    participants, repetitions, repeat = (10, 5, 1) if quick else (40, 20, 3)
    label = f"{participants} x {2 * 10 * repetitions} trials"
    with tempfile.TemporaryDirectory() as folder:
        root = write_dataset(Path(folder) / "ds", SyntheticSpec(
            n_participants=participants, repetitions=repetitions, seed=2026))
        plan = load_plan(default_plan_path())
        if quick:
            plan = _quick_plan(plan)
        load = median_seconds(lambda: load_datasets([root]), repeat)
        counter = iter(range(1000))
        report = median_seconds(lambda: analyze([root], plan,
                                                Path(folder) / f"out{next(counter)}"), repeat)
        data = with_exclusions(load_datasets([root]), plan.exclusions)
        conditions, reference, _ = order_conditions(data.analysed, plan)
        glmm = median_seconds(lambda: primary_test(
            data.analysed, conditions, reference, plan.primary.random_effects,
            plan.primary.method, plan.primary.n_quadrature, plan.alpha), repeat)
    figures = [
        Figure(AREA, f"full report, {label}", report, "s", "loading alone", load,
               f"value <= {TARGET_REPORT_S:g} s", report <= TARGET_REPORT_S),
        Figure(AREA, f"primary GLMM test (2 fits, profiles), {label}", glmm, "s",
               "loading alone", load),
    ]
    if not quick:
        figures.append(_large_report(repeat))
    return figures


def _quick_plan(plan: AnalysisPlan) -> AnalysisPlan:
    """The plan with :data:`QUICK_RESAMPLES` bootstrap resamples everywhere (the sequential
    stop of the primary bootstrap no later than its last replicate)."""
    n = QUICK_RESAMPLES
    primary = dataclasses.replace(plan.primary, bootstrap_replicates=n,
                                  bootstrap_stop_after=min(plan.primary.bootstrap_stop_after, n))
    return dataclasses.replace(
        plan, primary=primary,
        confusion=dataclasses.replace(plan.confusion, bootstrap=n),
        psychometric=dataclasses.replace(plan.psychometric, bootstrap=n))


def _large_report(repeat: int) -> Figure:
    """``analyze`` of 100 participants x 400 trials, against loading it."""
    with tempfile.TemporaryDirectory() as folder:
        root = write_dataset(Path(folder) / "ds", SyntheticSpec(
            n_participants=100, repetitions=20, seed=2026))
        load = median_seconds(lambda: load_datasets([root]), repeat)
        counter = iter(range(1000))
        report = median_seconds(lambda: analyze([root], default_plan_path(),
                                                Path(folder) / f"out{next(counter)}"), repeat)
    return Figure(AREA, "full report, 100 x 400 trials", report, "s", "loading alone", load,
                  f"value < {TARGET_LARGE_REPORT_S:g} s", report < TARGET_LARGE_REPORT_S)
