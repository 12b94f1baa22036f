"""Bench area ``device``: the wire figures, each against a same-run baseline.

The least we accept: frame rate >= 95 % of the wire bound with every channel changing;
software time per frame <= 1 % of the frame's wire time; median wire latency of the moving-bump
digits on the 2D device <= 45 ms (the paper's device: 75 ms), shown against sending everything.
The wire bound: a 19-servo SERVO_MOVE is 64 bytes, 66.7 ms at 9600 baud (docs/device.md).
"""

from __future__ import annotations

import json
import math

import pytest

from crs_study.cli import main


@pytest.fixture(scope="module")
def figures():
    """The figures as ``crs-study bench device --quick --json`` prints them (one JSON line
    each), and the command's exit status (1 when a target is missed)."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(["bench", "device", "--quick", "--json"])
    return status, [json.loads(line) for line in out.getvalue().splitlines()]


def test_the_bench_reports_the_wire_figures_against_their_baselines(figures):
    status, figs = figures
    assert len(figs) == 6
    for fig in figs:
        assert fig["area"] == "device"
        assert math.isfinite(fig["value"]) and fig["value"] > 0
        assert math.isfinite(fig["baseline"]) and fig["baseline"] > 0
        assert fig["ratio"] == pytest.approx(fig["value"] / fig["baseline"])
    rate, software, latency, *_ = figs
    assert rate["baseline"] == pytest.approx(9600 / 10 / 64)  # 15 frames/s: the wire bound
    assert software["baseline"] == pytest.approx(64 * 10 / 9600)  # one full frame's wire time
    assert latency["baseline"] == pytest.approx(64 * 10 / 9600)  # sending every channel
    assert {f["target"] for f in figs if f["target"]} == {"ratio >= 0.95", "ratio <= 0.01",
                                                          "value <= 45 ms"}
    assert status == int(any(f["passed"] is False for f in figs))  # 1: a target missed


def test_frames_leave_back_to_back_near_the_wire_bound(figures):
    # SerialDevice on two paced ports, every channel changing: frames leave back to back
    _, (rate, *_) = figures
    assert rate["target"] == "ratio >= 0.95"
    # the bench's target, 0.95 of the bound, is reported (a busy machine's late wake-ups may
    # miss it); back to back is far above 0.8 (0.98 measured beside the full suite)
    assert rate["ratio"] >= 0.8, rate
    assert rate["passed"] == (rate["ratio"] >= 0.95)


def test_software_time_per_frame_is_reported_against_its_wire_time(figures):
    _, (_, software, *_) = figures
    # measured CPU time: the bench judges the target; a busy machine may miss it
    assert software["target"] == "ratio <= 0.01"
    assert software["ratio"] > 0 and software["passed"] in (True, False)


def test_the_median_latency_of_the_digits_meets_45_ms_and_beats_sending_everything(figures):
    # the wire arithmetic (not the machine's speed) decides the latency figure
    _, (_, _, latency, lopsided_changed, lopsided_full, _) = figures
    assert latency["target"] == "value <= 45 ms"
    assert latency["value"] <= 0.045 and latency["passed"] is True
    assert latency["ratio"] < 1  # changed-only beats sending everything
    # balancing: the lopsided 24/13 map is slower than the shipped 19/18 either way
    assert lopsided_changed["ratio"] > 1 and lopsided_full["ratio"] > 1
