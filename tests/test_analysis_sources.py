"""Simulated and human sessions are not pooled silently; every session is listed by who
answered and on what device; a participant left with no analysed trial
is named."""

from __future__ import annotations

import pytest
from analysis_fixtures import dataset, edit_sidecar, explicit_dataset, session_files, write_plan

from crs_study.analysis.report import analyze
from crs_study.cli import main
from crs_study.errors import DatasetError


def _make_human(root, how_many: int) -> None:
    """The first ``how_many`` sessions become people at the keypad on the real device."""
    for _, sidecar in session_files(root)[:how_many]:
        edit_sidecar(sidecar, Responder="keypad", DeviceURL="serial:///dev/ttyUSB0,/dev/ttyUSB1")


@pytest.fixture
def mixed(tmp_path):
    root = dataset(tmp_path / "ds", n_participants=6, repetitions=2)
    _make_human(root, 2)
    return root


def test_a_mixture_is_refused_in_one_line(mixed, tmp_path):
    plan = write_plan(tmp_path / "p.toml")
    with pytest.raises(DatasetError, match="simulated and human sessions together") as info:
        analyze([mixed], plan, tmp_path / "out")
    message = str(info.value)
    assert "\n" not in message and "--include-simulated" in message
    assert "2 human (keypad on serial://" in message and "4 simulated (observer on sim://)" \
        in message


def test_the_cli_says_so_and_exits_2(mixed, tmp_path, capsys):
    plan = write_plan(tmp_path / "p.toml")
    assert main(["analyze", str(mixed), "--plan", str(plan), "--out", str(tmp_path / "o")]) == 2
    assert "simulated and human sessions together" in capsys.readouterr().err


def test_pooling_on_request_warns_and_lists_the_sessions(mixed, tmp_path):
    result = analyze([mixed], write_plan(tmp_path / "p.toml"), tmp_path / "out",
                     include_simulated=True)
    assert result.results["sources"]["kind"] == "mixed"
    assert result.results["n_participants"] == 6
    assert any("pooled on request" in w for w in result.warnings)
    counts = {(r["kind"], r["responder"]): r["sessions"]
              for r in result.results["sources"]["sessions"]}
    assert counts == {("human", "keypad"): 2, ("simulated", "observer"): 4}
    assert {s["Responder"] for s in result.results["sessions"]} == {"keypad", "observer"}
    text = result.report_path.read_text()
    assert "Sessions by who answered and on what device" in text and "| keypad |" in text


def test_a_responder_filter_keeps_one_kind(mixed, tmp_path):
    result = analyze([mixed], write_plan(tmp_path / "p.toml"), tmp_path / "out",
                     responders=["keypad"])
    assert result.results["n_participants"] == 2
    assert result.results["sources"]["kind"] == "human"
    assert "4 session(s) left out by the responder filter ['keypad']" in \
        result.results["sources"]["notes"]
    with pytest.raises(DatasetError, match="no session has responder \\['people'\\]"):
        analyze([mixed], write_plan(tmp_path / "p.toml"), tmp_path / "o2", responders=["people"])


def test_all_simulated_is_analysed_and_says_so(tmp_path):
    # what the demo and every dry-run produce: no flag needed
    root = dataset(tmp_path / "ds", n_participants=3, repetitions=2)
    result = analyze([root], write_plan(tmp_path / "p.toml"), tmp_path / "out")
    assert result.results["sources"]["kind"] == "simulated"
    note = "every session is simulated"
    assert any(note in n for n in result.results["sources"]["notes"])
    assert note in result.report_path.read_text()


def test_a_participant_with_every_trial_excluded_is_named(tmp_path):
    cells = {f"{p:02d}": [(c, d, 0, int((d + p) % 3 > 0)) for c in ("pixel-only", "crs")
                          for d in range(10)] for p in range(4)}
    cells["gone"] = [(c, d, 0, None) for c in ("pixel-only", "crs") for d in range(10)]
    root = explicit_dataset(tmp_path / "ds", cells)
    result = analyze([root], write_plan(tmp_path / "p.toml"), tmp_path / "out")
    (warning,) = [w for w in result.warnings if "has no analysed trial" in w]
    assert warning.startswith("participant 'gone' has no analysed trial (all 20 excluded: "
                              "timeout 20)")
    assert result.results["n_participants"] == 4
