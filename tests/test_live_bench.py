"""``crs-study bench live``: the figures are measured (the boards' own record, this run's wire
time as the baseline) and named with their targets."""

from __future__ import annotations

import contextlib
import io
import json
import math

from crs_study.cli import main


def test_bench_live_quick():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(["bench", "live", "--quick", "--json"])
    figures = [json.loads(line) for line in out.getvalue().splitlines()]
    assert status in (0, 1)  # 1: a target missed on this (shared, noisy) machine
    names = {f["name"]: f for f in figures}
    for device in ("sim", "pty"):
        median = names[f"{device}: arrival->last byte, median"]
        assert median["target"] == "<= 40 ms" and median["unit"] == "ms"
        wire = median["baseline"]  # the median frame's wire time, measured in this run
        assert 10.4 <= wire <= 66.7  # between one servo's frame and every channel's
        assert median["value"] > wire  # a packet waits for its frame, then the wire
        assert names[f"{device}: arrival->last byte, p99"]["value"] >= median["value"]
        in_place = names[f"{device}: arrival->servos in place, median"]
        assert in_place["value"] >= median["value"] and in_place["target"] == "<= 75 ms"
        software = names[f"{device}: software per packet (CPU), median"]
        assert software["value"] > 0 and software["target"] == "ratio < 0.01"
        assert all(math.isfinite(f["value"]) for f in figures)
    # CPU times and the host model's error are figures (the bench prints them against their
    # targets), not asserted: a loaded machine inflates them for no fault of the code
    assert math.isfinite(names["pty: host model error, median |landed - predicted|"]["value"])
    assert names["software per packet, warm loop (CPU)"]["value"] > 0
    for what in ("render one frame", "an empty call"):
        for when in ("after a frame's pause", "back to back"):
            assert names[f"{what} {when} (CPU), median"]["value"] >= 0

def test_bench_live_reports_position_error_with_and_without_prediction():
    from crs_study.benchmarks import _live_landing

    figures = {f.name: f for f in _live_landing.run(quick=True)}
    natural = figures["position error at landing, natural: median"]
    # deterministic (virtual time): prediction against no prediction in the same run
    assert natural.target == "<= 1.5 mm and ratio <= 0.5" and natural.passed is not None
    assert natural.value < 0.5 * natural.baseline and 3.0 < natural.baseline < 5.0
    for speed in ("slow", "natural", "fast"):
        median = figures[f"position error at landing, {speed}: median"]
        assert 0 < median.value < median.baseline
        assert median.value <= figures[f"position error at landing, {speed}: p95"].value
    lead = figures["bump leads the finger, largest (any frame)"]
    assert lead.target == "<= 15 ms" and lead.baseline <= 0.0  # without prediction: lags only
    overshoot = figures["overshoot at stroke ends, digits: p95"]
    assert overshoot.target == "<= 3 mm" and 0 <= overshoot.value <= 6.0  # the step cap


def test_a_recording_given_with_trace_is_measured_too(tmp_path):
    from crs_study.benchmarks import _live_landing
    from crs_study.live.predict import PredictConfig
    from crs_study.live.trace import digit_trace

    trace = digit_trace(3, speed_mm_s=100.0, profile="minimum-jerk")
    path = tmp_path / "finger.jsonl"
    lines = [{"format": "crs-study live recording", "version": 1}] + [
        {"packet": {"t": 10.0 + t, "status": "accepted", "x": x, "y": y, "z": z}}
        for t, (x, y, z) in zip(trace.times.tolist(), trace.xyz.tolist(), strict=True)]
    path.write_text("\n".join(json.dumps(x) for x in lines) + "\n", encoding="utf-8")
    group = _live_landing.groups(quick=True, traces=[str(path)])["recording finger.jsonl"]
    on = _live_landing.measure(group, PredictConfig())
    off = _live_landing.measure(group, PredictConfig(method="off"))
    assert 0 < on["median"] < 0.5 * off["median"]  # as the digit it was made from
