"""Tests for ``crs-study quality``: JSON rows, chart and tables, cache, one-line errors."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import pytest

from crs_study.cli import main
from crs_study.quality import sweep as sweep_module
from crs_study.quality.sweep import DEFAULT_D_OVER_L

FAST = ["--models", "nearest", "linear", "--layouts", "1d", "hex", "--jobs", "1"]


def test_json_rows_include_the_required_d_over_l(tmp_path, capsys):
    code = main(["quality", "--json", *FAST, "--cache-dir", str(tmp_path / "cache"),
                 "--d-over-l", "0.1", "0.2", "0.3", str(1 / 3)])
    assert code == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert all(set(r) == {"layout", "model", "d_over_l", "D_P", "D_S"} for r in rows)
    assert len(rows) == 2 * 2 * 4
    for layout in ("1d", "hex"):
        xs = sorted(r["d_over_l"] for r in rows
                    if r["layout"] == layout and r["model"] == "nearest")
        assert xs == pytest.approx([0.1, 0.2, 0.3, 1 / 3])
    one = next(r for r in rows if r["layout"] == "1d" and r["model"] == "nearest"
               and r["d_over_l"] == 0.2)
    assert one["D_P"] == pytest.approx(0.05)  # paper: 0.25 d/l
    assert not (tmp_path / "quality").exists()  # --json writes no files unless --out is given


def test_default_sweep_has_the_papers_points():
    for x in (0.1, 0.2, 0.3, 1 / 3):
        assert any(math.isclose(x, d) for d in DEFAULT_D_OVER_L)


def test_out_writes_chart_and_tables(tmp_path, capsys):
    out = tmp_path / "report"
    code = main(["quality", *FAST, "--no-cache", "--out", str(out),
                 "--d-over-l", "0.2", str(1 / 3)])
    assert code == 0
    text = capsys.readouterr().out
    assert "hex    nearest   d/l=1/3  D_P=0.1170" in text
    assert (out / "quality.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((out / "quality.csv").read_text().splitlines()))
    assert len(rows) == 8
    hexagonal = next(r for r in rows if r["layout"] == "hex" and r["model"] == "nearest"
                     and float(r["d_over_l"]) == 0.2)
    assert float(hexagonal["D_P_paper"]) == pytest.approx(0.3510 * 0.2)
    linear = next(r for r in rows if r["layout"] == "hex" and r["model"] == "linear")
    assert linear["D_S_paper"] == ""  # the paper gives no 2D linear line
    assert (out / "quality.md").read_text().startswith("| layout | model | d/l |")


def test_second_run_reads_the_cache(tmp_path, capsys, monkeypatch):
    args = ["quality", "--json", *FAST, "--cache-dir", str(tmp_path), "--d-over-l", "0.25"]
    assert main(args) == 0
    first = capsys.readouterr().out

    def refuse(*a, **k):
        raise AssertionError("recomputed a cached point")

    monkeypatch.setattr(sweep_module, "compute_point", refuse)
    assert main(args) == 0
    assert capsys.readouterr().out == first


def test_points_a_model_cannot_compute_are_reported(tmp_path, capsys):
    # d/l = 0.8 is within the hexagonal lattice's range but beyond the square one's
    code = main(["quality", "--json", "--models", "nearest", "--layouts", "square", "hex",
                 "--d-over-l", "0.8", "--no-cache", "--jobs", "1"])
    assert code == 0
    captured = capsys.readouterr()
    assert [json.loads(line)["layout"] for line in captured.out.splitlines()] == ["hex"]
    assert ("quality: square nearest   n/a at d/l = 0.8: d/l = 0.8 is outside [0.02, 0.7071]"
            in captured.err)
    assert len(captured.err.splitlines()) == 1  # one line per distinct failure, not per point


@pytest.mark.parametrize(("argv", "message"), [
    (["--models", "nearst"], "--models: unknown display model 'nearst'; known: "),
    (["--d-over-l", "3"], "--d-over-l: expected values in [0.02, "),
    (["--order", "1"], "--order: expected a whole number in 2..32, got 1"),
    # resolution 100000 was killed out of memory; jobs 0 was taken silently
    (["--resolution", "100000"], "--resolution: expected a whole number in 4..96, got 100000"),
    (["--jobs", "0"], "--jobs: expected a whole number in 1..64, got 0"),
    # refused before the sweep (it was refused after a minute of surfaces)
    (["--out", "/proc/crs-study-nope"], "--out: cannot write in /proc"),
    (["--speed-accuracy", "--out", "/proc/crs-study-nope"], "--out: cannot write in /proc"),
    (["--device", "crs1d", "--layouts", "hex"], "the device 'crs1d' is a 1d lattice"),
    (["--device", "no-such-device"], "no-such-device"),
])
def test_bad_arguments_are_one_line_errors(argv, message, capsys):
    assert main(["quality", "--json", "--no-cache", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert len(err.strip().splitlines()) == 1


def test_speed_accuracy_writes_chart_table_and_rows(tmp_path, capsys, monkeypatch):
    """``--speed-accuracy``: the bench's rows (time per surface, error vs the reference),
    speed_accuracy.png and .md in --out; the compressed beam is far closer to the reference
    than the models without the CRS feed."""
    from crs_study.benchmarks import display as bench

    monkeypatch.setattr(bench, "MODELS", ("nearest", "spline", "beam"))
    out = tmp_path / "q"
    assert main(["quality", "--speed-accuracy", "--json", "--out", str(out)]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert {(r["layout"], r["model"]) for r in rows} == {
        (lay, m) for lay in ("1d", "2d") for m in ("nearest", "spline", "beam")}
    assert (out / "speed_accuracy.png").stat().st_size > 1000
    table = (out / "speed_accuracy.md").read_text()
    assert table.startswith("| layout | model | ms/surface |") and "| 2d | beam |" in table
    for layout in ("1d", "2d"):
        error = {r["model"]: r["rms_error_mm"] for r in rows if r["layout"] == layout}
        assert error["beam"] < 0.05 * min(error["spline"], error["nearest"])
        assert all(r["seconds_per_surface"] > 0 for r in rows)


def test_parallel_sweep_equals_the_serial_one_and_restores_the_environment(monkeypatch):
    import os

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    args = (["nearest", "linear"], ["1d"], [0.2, 0.3])
    parallel = sweep_module.sweep(*args, jobs=2)
    assert parallel == sweep_module.sweep(*args, jobs=1)
    assert "OPENBLAS_NUM_THREADS" not in os.environ


def test_device_option_computes_that_devices_lattice_with_its_section(tmp_path, capsys):
    """A device file by path: its lattice alone, its pitch and beam (a thicker beam changes
    the CRS numbers, never the pixel-only ones, which are scale-free in d/l)."""
    import tomllib

    from crs_study.geometry.layout import device_file_path

    text = device_file_path("crs1d").read_text()
    thick = tmp_path / "thick1d.toml"
    assert "thickness_mm = 0.1" in text
    thick.write_text(text.replace("thickness_mm = 0.1", "thickness_mm = 0.3"))
    tomllib.loads(thick.read_text())

    def rows(device):
        argv = ["quality", "--json", "--no-cache", "--models", "nearest", "beam",
                "--d-over-l", "0.3", "--device", device]
        assert main(argv) == 0, capsys.readouterr().err
        return {r["model"]: r for r in map(json.loads, capsys.readouterr().out.splitlines())}

    shipped, custom = rows("crs1d"), rows(str(thick))
    assert {r["layout"] for r in [*shipped.values(), *custom.values()]} == {"1d"}
    assert custom["nearest"] == shipped["nearest"]
    assert custom["beam"]["D_S"] != shipped["beam"]["D_S"]


def test_chart_marks_collapse_and_missing_models_and_labels_every_panel():
    import matplotlib.pyplot as plt

    from crs_study.quality.report import plot_quality
    from crs_study.quality.sweep import Point

    points = [Point("hex", "nearest", x, 0.351 * x, 1.3 * x, 1) for x in (0.1, 0.3)]
    points += [Point("hex", "beam", 0.1, 0.01, 0.007, 1),
               Point("hex", "beam", 0.3, note="beam 1: ... the beam collapses; reduce ...")]
    points += [Point("square", "nearest", 0.1, 0.038, 0.15, 1),
               Point("square", "beam", 0.1, note="beam: lattice 'square' not supported")]
    before = plt.get_fignums()
    axes = plot_quality(points)
    assert plt.get_fignums() == before        # drawn without pyplot: nothing left behind
    for shown in (axes, axes[1, 1]):        # a notebook's picture, the grid or one panel
        assert shown._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    for ax in axes.ravel():
        assert ax.get_legend() is not None
    hex_labels = [line.get_label() for line in axes[0, 1].get_lines()]
    assert "beam: collapses (uncapped feed)" in hex_labels
    assert "paper nearest: 0.351 (d/l)" in hex_labels
    square = axes[0, 0]
    assert [t.get_text() for t in square.texts] == ["no beam model on this lattice"]
    assert not any("collapses" in line.get_label() for line in square.get_lines())


def test_a_module_that_can_draw_starts_without_matplotlib():
    """matplotlib (half a second) is imported with the first chart, not with the modules that
    can draw one: the quality command, a measurement session and its report."""
    modules = ("crs_study.commands.quality", "crs_study.session.measurement",
               "crs_study.quality.measured_report")
    code = (f"import sys\nfor name in {modules!r}: __import__(name)\n"
            "print('matplotlib' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "False", done.stderr


def test_a_chart_pickles_and_still_displays():
    import pickle

    from crs_study._figure import ChartFigure, new_axes

    ax = new_axes()
    ax.plot([0, 1], [1, 0])
    figure = pickle.loads(pickle.dumps(ax.figure))
    assert isinstance(figure, ChartFigure)
    assert figure._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
