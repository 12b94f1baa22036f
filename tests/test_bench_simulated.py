"""Bench area ``simulated`` runs and reports every figure against a same-run baseline."""

from __future__ import annotations

import math


def test_quick_bench_reports_each_figure_against_its_baseline():
    from crs_study.benchmarks import simulated

    figures = {f.name: f for f in simulated.run(quick=True)}
    assert len(figures) == 6
    for figure in figures.values():
        assert figure.area == "simulated"
        assert math.isfinite(figure.value) and figure.value > 0
        assert math.isfinite(figure.baseline) and figure.baseline > 0
    targeted = [f for f in figures.values() if f.target]
    assert {f.target for f in targeted} == {"<= 60 us", "<= 150 us", "ratio >= 100"}
    assert all(f.passed in (True, False) for f in targeted)
