"""Bench area ``power``: every figure against a baseline of the same run (the quick form
here; the real figures come from ``crs-study bench power``)."""

from __future__ import annotations

import shutil

import pytest

from crs_study.benchmarks import power as bench


@pytest.mark.slow
def test_the_figures_and_their_baselines(monkeypatch):
    """The bench's quick form (``crs-study bench power --quick``) with half its studies:
    every figure runs and is set against its baseline. The figures' sizes and the studies'
    split into units of work are the quick form's; what is checked is that each figure is
    measured and named, which needs studies, not many."""
    for name in ("CURVE_STUDIES", "PER_STUDY_STUDIES", "POINT_STUDIES", "WARM_STUDIES",
                 "DASK_STUDIES"):
        quick, full = getattr(bench, name)
        monkeypatch.setattr(bench, name, (max(2, quick // 2), full))   # power: >= 2
    figures = list(bench.run(quick=True))
    curve, per_study, *rest = figures
    assert curve.name.startswith(f"default curve, 2 sizes x {bench.CURVE_STUDIES[0]} studies, ")
    assert curve.baseline_name == "fit_primary loop (extrapolated)" and curve.baseline > 0
    assert curve.passed is None                         # quick: no target judged
    assert per_study.baseline_name == "ours" and per_study.baseline > 0
    if shutil.which("Rscript"):
        assert per_study.name.endswith("lme4 refit loop (0/1 rows, as simr) / ours")
        assert per_study.value > 0                       # timed (which is faster: the bench)
    dask, busy = rest[-2:]
    assert dask.baseline_name == "1 worker" and dask.target == "ratio >= 1.6"
    assert 0 < busy.value <= 2.2 and busy.baseline == 2.0


@pytest.mark.slow
def test_the_point_with_the_plans_test_is_set_against_the_same_point_with_chi2():
    """Figure 3 in its quick form (a few studies, target printed, not judged): at 12
    participants the shipped plan's test is the bootstrap-calibrated one, its baseline the
    same point with the chi2 test."""
    point = bench.point_figure(quick=True)
    assert point.name.startswith(f"one point, N = 12 x {bench.POINT_STUDIES[0]} studies, "
                                 "the plan's test (p_value = 'auto': bootstrap-calibrated")
    assert point.baseline_name == "the same point, p_value = 'chi2'"
    assert point.value > 0 and point.baseline > 0
    assert point.target == "value <= 30 s at 1000 studies" and point.passed is None
