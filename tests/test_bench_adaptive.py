"""Bench area ``adaptive``: QUEST+ chooses each next level of a 60-trial block in under
50 ms, and an adaptive dry-run runs above 100x real time (the targets of the bench area)."""

from __future__ import annotations

import contextlib
import io
import json

from crs_study.cli import main


def test_quest_plus_wait_and_dry_run_speed_meet_their_targets():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["bench", "adaptive", "--quick", "--json"]) == 0
    longest, median, replay, speed = [json.loads(line) for line in out.getvalue().splitlines()]
    assert longest["passed"] and longest["value"] < 0.050
    assert median["value"] <= longest["value"] and replay["value"] > 0
    assert speed["unit"] == "s/s" and speed["passed"] and speed["ratio"] >= 100
