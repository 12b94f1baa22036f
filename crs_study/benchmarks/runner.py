"""Bench area ``runner``: how fast a dry-run plays the default protocol.

One simulated participant (the perceptual observer when installed, else the random
responder) runs session 1 of ``protocols/digit_identification.toml`` through the whole
runner: pre-rendered stimuli, the full-fidelity simulated device (``sim://``: LSC bytes,
virtual boards, servo motion) on a virtual clock, the responder, and the dataset written as a
dry-run writes it (rows, frame log, sidecar; fsync when the session stops). A fresh dataset
every repeat; the median wall time over the repeats.

Figure: session seconds simulated per wall second, against real time (1 s of session per
second, the baseline: the session's own real-time duration, read off the virtual clock in the
same run); target ratio >= 100.
"""

from __future__ import annotations

import csv
import importlib.util
import statistics
import tempfile
import time
from pathlib import Path

from crs_study.benchmarks import Figure
from crs_study.paths import shipped_file
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec

AREA = "runner"
DESCRIPTION = "dry-run speed: the default protocol, one simulated participant, vs real time"
TARGET_SPEEDUP = 100.0


def _responder() -> str:
    return "observer" if importlib.util.find_spec("crs_study.session.responders.observer") \
        else "random"


def run(quick: bool) -> list[Figure]:
    protocol = shipped_file("protocols/digit_identification.toml")
    responder = _responder()
    repeat = 1 if quick else 3
    walls, sessions, frames = [], [], 0
    for k in range(repeat + 1):  # the first run warms the stimulus cache, not timed
        with tempfile.TemporaryDirectory(prefix="crs-bench-runner-") as tmp:
            # a simulated participant's label (sim...): it needs no consent record
            spec = SessionSpec(protocol, f"simbench{k:02d}", Path(tmp), "sim://", 1, responder,
                               "virtual", 0, durable=False)
            start = time.perf_counter()
            result = run_session(spec)
            wall = time.perf_counter() - start
            if k:
                walls.append(wall)
                sessions.append(result.session_seconds)
            if k == 1:
                with open(result.tsv, newline="") as handle:
                    frames = sum(int(r["frames"]) for r in csv.DictReader(handle,
                                                                         delimiter="\t"))
    wall = statistics.median(walls)
    session = statistics.median(sessions)
    speed = session / wall
    return [
        Figure(AREA, f"dry-run session s per wall s ({responder}, {frames} frames)", speed,
               "s/s", f"real time ({session:.0f} s session, {wall:.2f} s wall)", 1.0,
               f"ratio >= {TARGET_SPEEDUP:g}", speed >= TARGET_SPEEDUP),
    ]
