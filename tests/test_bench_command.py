"""``crs-study bench`` prints each figure when its area yields it: an area of minutes (the
power curve and point, the glmm figures, the validity grid) interrupted part-way keeps on the
screen, and in a log, every figure it has measured."""

from __future__ import annotations

import inspect
import types

import pytest

from crs_study.benchmarks import Figure
from crs_study.cli import main
from crs_study.commands import bench as bench_command


def test_a_figure_is_printed_before_the_next_is_measured(monkeypatch, capsys):
    measured = []

    def run(quick: bool):
        measured.append("first")
        yield Figure("slow", "first figure", 1.0, "s", "baseline", 2.0)
        raise KeyboardInterrupt          # Ctrl-C while the next figure is measured

    area = types.SimpleNamespace(AREA="slow", DESCRIPTION="a slow area", run=run)
    monkeypatch.setattr(bench_command, "_areas", lambda: {"slow": area})
    status = main(["bench", "slow", "--quick"])
    out, err = capsys.readouterr()
    assert measured == ["first"]
    assert "slow      first figure" in out and "ratio        0.5 vs baseline (2)" in out, out
    assert status == 130 and "interrupted" in err


@pytest.mark.parametrize("area", ["power", "glmm", "validity"])
def test_the_long_areas_yield_their_figures_one_by_one(area):
    """The areas whose full form takes a quarter of an hour or more produce each figure as
    it is measured, not a list at the end (a timeout or Ctrl-C lost every figure)."""
    module = bench_command._areas()[area]
    assert inspect.isgeneratorfunction(module.run), area
