"""``crs-study validate``: the plan summary in text and JSON, one-line errors."""

from __future__ import annotations

import json

import pytest

from crs_study.cli import main
from crs_study.paths import shipped_file
from crs_study.protocol import load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.stimuli.stimulus import make_stimulus

FULL = str(shipped_file("protocols/digit_identification.toml"))
PILOT = str(shipped_file("protocols/pilot.toml"))


def test_text_summary(capsys):
    assert main(["validate", FULL]) == 0
    out = capsys.readouterr().out
    assert "valid (digitid 1.0.0, device crs2d" in out
    assert "trials: 120 (20 practice, 100 test) in 2 blocks" in out
    assert "pixel-only: 10 practice, 50 test" in out
    # which participant gets which order: by counterbalance index k (order of arrival)
    assert "block orders (alternate) by counterbalance index k" in out
    assert "  k mod 2 = 0 (k = 0, 2, 4, ...): pixel-only crs\n" in out
    assert "  k mod 2 = 1 (k = 1, 3, 5, ...): crs pixel-only\n" in out
    assert "frames per trial:" in out and "expected duration:" in out
    assert "wire, full frames: 125 bytes/frame" in out  # 3*19+7 + 3*18+7 (docs/device.md)
    assert "ok  no collapse" in out


def test_json_summary_is_consistent_with_the_plan(capsys):
    assert main(["validate", PILOT, "--json", "--participant", "p01"]) == 0
    summary = json.loads(capsys.readouterr().out)
    protocol = load_protocol(PILOT)
    plan = make_plan(protocol, "p01", 1, 0)
    assert summary["trials"]["total"] == len(plan) == 26
    assert summary["trials"]["per_condition"]["crs"] == {"practice": 3, "test": 10}
    assert summary["example_plan"]["seed"] == plan.seed
    layout = protocol.layout()
    expected = sum(make_stimulus(protocol, layout, t.symbol).duration_s + 2.0 + 1.0
                   for t in plan.trials)
    assert summary["expected_duration_s"] == pytest.approx(expected)
    assert 2 * 60 < expected < 5 * 60  # "a few minutes"
    frames = summary["frames_per_trial"]
    assert frames["per_digit"]["1"] == make_stimulus(protocol, layout, 1).n_frames
    wire = summary["wire"]
    # Full frame on the busier controller: 19 servos, 64 bytes, 66.7 ms at 9600 baud 8N1.
    assert wire["full_frame_busiest_controller_ms"] == pytest.approx(64 * 10 / 9600 * 1e3)
    assert wire["full_frame_budget_percent"] == pytest.approx(100.0)
    for condition in ("pixel-only", "crs"):
        changed = wire["changed_only"][condition]
        assert 0 < changed["mean_bytes_per_frame"] < wire["full_frame_bytes"]
        assert changed["max_rate_hz"] >= protocol.frame_rate_hz
    assert summary["checks"] == list(protocol.checks)


def test_block_orders_by_counterbalance_index_match_the_plans(tmp_path, capsys):
    """The orders validate lists are those make_plan gives each counterbalance index."""
    text = shipped_file("protocols/pilot.toml").read_text()
    path = tmp_path / "abba.toml"
    path.write_text(text.replace('counterbalancing = "alternate"', 'counterbalancing = "abba"')
                    .replace("repetitions = 1", "repetitions = 2"))
    assert main(["validate", str(path), "--json"]) == 0
    orders = json.loads(capsys.readouterr().out)["block_orders"]
    assert orders["counterbalancing"] == "abba" and orders["cycle"] == 2
    protocol = load_protocol(path)
    for k in range(6):
        row = orders["by_counterbalance"][k % 2]
        assert row["k_mod_cycle"] == k % 2
        assert tuple(row["order"]) == make_plan(protocol, "p01", 1, k).block_conditions
    assert main(["validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "  k mod 2 = 1 (k = 1, 3, 5, ...): crs pixel-only pixel-only crs\n" in out


def test_list_prints_every_trial(capsys):
    assert main(["validate", PILOT, "--list"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line[:5].strip().isdigit()]
    assert len(rows) == 26


def test_bad_protocol_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(shipped_file("protocols/pilot.toml").read_text()
                    .replace("frame_rate_hz = 15.0", "frame_rate_hz = 30.0"))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1
    assert "bad.toml:" in err[0] and "stimulus.frame_rate_hz: expected at most 15.00" in err[0]


def test_warnings_are_listed_in_text_and_json(tmp_path, capsys):
    path = tmp_path / "odd.toml"
    path.write_text(shipped_file("protocols/pilot.toml").read_text()
                    .replace("inter_trial_interval_s = 1.0", "inter_trial_interval_s = 0.0")
                    .replace("time_limit_s = 10.0", "time_limit_s = 300.0"))
    assert main(["validate", str(path)]) == 0  # odd, not wrong
    out = capsys.readouterr().out
    assert "\nwarnings (odd but legal values" in out
    lines = [line for line in out.splitlines() if line.startswith("  warning  ")]
    assert len(lines) == 2
    assert any(f"{path}:" in line and "responses.time_limit_s: 300.0 s is a long time limit"
               in line for line in lines)
    assert any("design.inter_trial_interval_s: 0.0 s" in line for line in lines)
    assert main(["validate", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert [w.split(": ", 2)[1] for w in summary["warnings"]] == \
        ["responses.time_limit_s", "design.inter_trial_interval_s"]
    assert main(["validate", PILOT]) == 0
    assert "warning" not in capsys.readouterr().out
