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
        assert 0 < software["value"] < wire and software["target"] == "ratio < 0.01"
        assert all(math.isfinite(f["value"]) for f in figures)
    assert abs(names["pty: host model error, median |landed - predicted|"]["value"]) < 10
    assert 0 < names["software per packet, warm loop (CPU)"]["value"] < 1.0  # ms
    paused = names["render one frame after a frame's pause (CPU), median"]
    warm = names["render one frame back to back (CPU), median"]
    assert 0 < warm["value"] < 1.0 and 0 < paused["value"] < 5.0  # ms, this run's cold cost
    empty_paused = names["an empty call after a frame's pause (CPU), median"]
    empty_warm = names["an empty call back to back (CPU), median"]
    # the machine's floor: timing nothing costs less than rendering a frame, either way
    assert 0 <= empty_warm["value"] < warm["value"]
    assert 0 <= empty_paused["value"] < paused["value"]
