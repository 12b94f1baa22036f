"""Prediction (crs_study/live/predict.py) and the position error at landing
(crs_study/live/landing.py, simulate.py): the 1€ filter against its authors' own
implementation, and the simulated link's errors, which are deterministic and asserted here
(their figures are ``crs-study bench live``'s)."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from OneEuroFilter import OneEuroFilter  # the authors' reference implementation (PyPI)

from crs_study.live import LiveError
from crs_study.live.predict import OneEuro, PredictConfig
from crs_study.live.simulate import simulate
from crs_study.live.trace import digit_trace, stroke_trace


@pytest.mark.parametrize("min_cutoff, beta, d_cutoff", [(1.0, 0.0, 1.0), (1.0, 0.5, 15.0),
                                                        (0.3, 0.007, 2.0)])
def test_one_euro_is_the_reference_implementation(rng, min_cutoff, beta, d_cutoff):
    # Casiez, Roussel & Vogel (2012), their Python implementation: a noisy sine sampled with
    # jittered timestamps (from 1 s: the reference ignores the first timestamp when it is 0)
    t = 1.0 + np.cumsum(rng.uniform(0.005, 0.02, 400))
    x = np.sin(t * 3.0) * 40.0 + rng.normal(0.0, 0.5, t.size)
    reference = OneEuroFilter(freq=72.0, mincutoff=min_cutoff, beta=beta, dcutoff=d_cutoff)
    ours = OneEuro(min_cutoff, beta, d_cutoff)
    expected = [reference(v, ts) for ts, v in zip(t, x, strict=True)]
    got = [ours.filter(ts, v) for ts, v in zip(t, x, strict=True)]
    # the reference's first step uses its nominal freq (72 Hz), ours the real time step: from
    # the second sample on both run on timestamps
    assert np.allclose(got[2:], expected[2:], atol=0.05)
    assert np.max(np.abs(np.array(got[100:]) - expected[100:])) < 1e-9


def test_the_simulation_is_deterministic():
    trace = digit_trace(5, speed_mm_s=100.0, profile="minimum-jerk")
    a, b = simulate(trace).errors, simulate(trace).errors
    assert np.array_equal(a.errors_mm, b.errors_mm) and np.array_equal(a.leads_s, b.leads_s)


def test_prediction_more_than_halves_the_error_at_natural_speed():
    on, off = [], []
    for digit in (2, 5, 9):
        trace = digit_trace(digit, speed_mm_s=100.0, profile="minimum-jerk")
        on.append(np.median(simulate(trace).errors.errors_mm))
        off.append(np.median(simulate(trace, PredictConfig(method="off")).errors.errors_mm))
    # without prediction a finger at 100 mm/s is ~4 mm past the bump (~40 ms at the wire)
    assert 3.0 < np.median(off) < 5.0
    assert np.median(on) < 0.5 * np.median(off)


@pytest.mark.parametrize("cap", [2.0, 6.0])
def test_overshoot_at_a_sudden_stop_is_bounded_by_the_step_cap(cap):
    trace = stroke_trace((-50.0, 0.0), (50.0, 0.0), speed_mm_s=150.0)
    errors = simulate(trace, PredictConfig(max_extrapolation_mm=cap)).errors
    off = simulate(trace, PredictConfig(method="off")).errors
    assert errors.overshoot_mm.size == 1 and 0.0 < errors.overshoot_mm[0] <= cap + 0.2
    assert off.overshoot_mm[0] < 0.2  # without prediction the bump trails, never overshoots
    assert np.median(errors.errors_mm) < np.median(off.errors_mm)


@pytest.mark.parametrize("options, message", [
    (dict(method="kalman"), "expected 'one-euro' or 'off'"),
    (dict(beta=-1.0), "predict beta"),
    (dict(max_extrapolation_mm=float("nan")), "max_extrapolation_mm"),
])
def test_bad_predictor_settings(options, message):
    with pytest.raises(LiveError, match=message):
        PredictConfig(**options)


def test_the_recording_states_the_predictor_and_each_frame_its_prediction(tmp_path):
    record = tmp_path / "r.jsonl"
    cli = [sys.executable, "-m", "crs_study"]
    live = subprocess.Popen(cli + ["live", "--device", "sim://", "--listen", "127.0.0.1:0",
                                   "--max-packets", "60", "--json", "--record", str(record)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = int(re.search(r"127\.0\.0\.1:(\d+)", live.stderr.readline()).group(1))
        subprocess.run(cli + ["live-send", "--to", f"127.0.0.1:{port}", "--stroke",
                              "--speed-mm-s", "100"], check=True, timeout=60,
                       capture_output=True)
        out, err = live.communicate(timeout=60)
    finally:
        live.kill()
    assert live.returncode == 0, err
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    assert lines[0]["config"]["predict"]["method"] == "one-euro"
    assert lines[0]["predictor"].startswith("1€ filter (min cutoff 1 Hz, beta 0.5")
    frames = [x["frame"] for x in lines if "frame" in x and x["frame"]["kind"] == "finger"]
    assert frames and all(len(f["shown"]) == 3 and f["for"] is not None for f in frames)
    result = json.loads(out)
    assert result["config"]["predict"]["max_extrapolation_mm"] == 6.0
    assert result["position_error_mm"]["n"] >= 1
