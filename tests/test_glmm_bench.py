"""Bench area ``glmm``: the bootstrap figure in its quick form (a check that it runs, against
its baseline; the real figure comes from ``crs-study bench glmm``)."""

from __future__ import annotations

import shutil

import pytest

from crs_study.benchmarks import glmm as bench


@pytest.mark.slow
def test_the_bootstrap_figure_is_set_against_one_lme4_fit_pair():
    """The quick bootstrap (a small B, target printed, not judged) on a small version of the
    bench's data, against lme4's fit pair on the same rows when R with lme4 is installed,
    else against our own observed fit pair."""
    data = bench.trials_with_slopes(20, 100)     # 4,000 rows: lme4's pair in seconds
    lme4 = bench.lme4_seconds(data, profile=False)
    if shutil.which("Rscript"):
        assert set(lme4) == {"pair"} and lme4["pair"] > 0
    figure = bench.bootstrap_figure(data, bench.BOOTSTRAP_REPLICATES[0], lme4.get("pair"),
                                    judged=False)
    assert figure.area == "glmm" and figure.unit == "s" and figure.value > 0
    assert figure.name.startswith(f"bootstrap p, B = {bench.BOOTSTRAP_REPLICATES[0]}, "
                                  "20 x 200 trials, maximal model, ")
    assert figure.target == "value <= 30 s at B = 1000" and figure.passed is None
    assert figure.baseline > 0
    if "pair" in lme4:
        assert figure.baseline_name == "lme4 glmer fit pair (full + reduced)"
        assert figure.name.endswith("lme4 fit pairs")
    else:
        assert figure.baseline_name == "our fit pair (full + reduced)"
        assert "lme4 not timed (no Rscript with lme4)" in figure.name
