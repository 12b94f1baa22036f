"""Bench area ``analysis``: figures are ratios against loading measured in the same run."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_quick_bench_reports_report_time_against_loading():
    from crs_study.benchmarks import analysis

    figures = analysis.run(quick=True)
    report, glmm = figures
    assert report.area == "analysis" and report.baseline_name == "loading alone"
    assert report.baseline > 0 and report.value > report.baseline
    # the target is judged and printed by the bench, never asserted: speed depends on the load
    assert report.passed in (True, False) and report.target == "value <= 10 s"
    assert glmm.passed is None and glmm.value > 0
