"""``crs-study quality measure`` and ``crs-study quality analyze``: the lab workflow on the
simulated device end to end (protocol -> captures from the DIC stand-in -> import -> D_P, D_S
against the model and the paper's lines), and what a person sees when something is wrong."""

from __future__ import annotations

import io
import json

import pytest
from dic_synthetic import Rig, fill_measurement
from test_quality_measure_session import small_protocol

from crs_study.cli import main
from crs_study.geometry.layout import load_layout


def test_measure_on_the_simulated_device_end_to_end(tmp_path, capsys):
    protocol = small_protocol(tmp_path, shapes=6)
    out = tmp_path / "meas"
    code = main(["quality", "measure", str(protocol), "--out", str(out),
                 "--capture", "synthetic?servo=A:3:0.4&noise_mm=0.01"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "measurement complete: 14/14 captures shown" in captured.out
    assert "residual map: A:3 (pixel 2): offset +0.4" in captured.out \
        or "residual map: A:3 (pixel 2): offset +0.3" in captured.out
    assert "pixel-only: as predicted" in captured.out
    assert "shape-0001 (2/14): pixel-only, l = 90 mm" in captured.err  # progress
    for name in ("report.md", "results.json", "shapes.csv", "figures/measured_quality.png",
                 "figures/residual_map.png"):
        assert (out / "derivatives" / name).is_file(), name
    corrected = tmp_path / "corrected.toml"
    code = main(["quality", "analyze", str(out), "--write-calibration", str(corrected),
                 "--out", str(tmp_path / "again")])
    captured = capsys.readouterr()
    assert code == 0
    assert f"wrote {corrected}: A:3: zero_us = 95" in captured.out  # 0.4 mm lower
    layout = load_layout(corrected)  # a device file device calibrate can start from
    channel = next(a for a in layout.actuators if (a.controller, a.channel) == ("A", 3))
    assert channel.calibration.zero_us == pytest.approx(1000 - 0.4 * 1000 / 9, abs=8)
    assert code == 0 and main(["quality", "analyze", str(out), "--write-calibration",
                               str(corrected)]) == 2
    assert "already exists; choose another file or --overwrite" in capsys.readouterr().err


def test_json_output(tmp_path, capsys):
    protocol = small_protocol(tmp_path, shapes=3)
    out = tmp_path / "meas"
    assert main(["quality", "measure", str(protocol), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["measurement"]["status"] == "complete"
    assert {r["condition"] for r in report["results"]["rows"]} == {"pixel-only", "crs"}
    assert main(["quality", "analyze", str(out), "--json"]) == 0
    results = json.loads(capsys.readouterr().out)
    assert results["tolerance"] == {"D_P": 0.01, "D_S": 0.02}
    assert len(results["shapes"]) == 6


def test_a_lab_saves_the_exports_then_analyses(tmp_path, capsys, monkeypatch):
    """Timed captures (the lab's DIC records): the experimenter is prompted at each block;
    the exports are saved later and analysed."""
    protocol = small_protocol(tmp_path, shapes=3, settle=0.0, hold=0.05)
    out = tmp_path / "meas"
    monkeypatch.setattr("sys.stdin", io.StringIO("\n" * 10))
    assert main(["quality", "measure", str(protocol), "--out", str(out), "--capture",
                 "timed"]) == 0
    captured = capsys.readouterr()
    assert "block crs: mount the skeleton" in captured.err
    assert "6 capture(s) have no export yet" in captured.out
    fill_measurement(out, Rig(), "gom", seed=8)
    assert main(["quality", "analyze", str(out)]) == 0
    assert "crs: as predicted" in capsys.readouterr().out


def test_end_of_input_at_a_prompt_pauses_the_measurement(tmp_path, capsys, monkeypatch):
    protocol = small_protocol(tmp_path, shapes=3, settle=0.0, hold=0.01)
    monkeypatch.setattr("sys.stdin", io.StringIO("\n\n"))
    code = main(["quality", "measure", str(protocol), "--out", str(tmp_path / "m"),
                 "--capture", "prompt"])
    assert code == 130
    assert "interrupted after 1/8 captures: run the same command to resume" in \
        capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [
    (["quality", "analyze", "{tmp}/nowhere"], "no such measurement record"),
    (["quality", "measure", "{tmp}/none.toml", "--out", "{tmp}/m"],
     "cannot read the measurement protocol"),
    (["quality", "measure", "crs3d", "--out", "{tmp}/m"], "not a shipped measurement protocol"),
    (["quality", "measure", "crs1d", "--out", "{tmp}/m", "--device", "serial:///dev/null",
      "--capture", "synthetic"], "the stand-in reads the simulated device"),
    (["quality", "measure", "crs1d", "--out", "{tmp}/m", "--capture",
      "synthetic?rotation_deg=x"], "rotation_deg: expected a number, got 'x'"),
])
def test_known_errors_are_one_line(tmp_path, capsys, argv, message):
    code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
