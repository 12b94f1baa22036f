"""Bench area ``adaptive``: how long a participant waits for QUEST+, and adaptive dry-runs.

Figures:

* QUEST+ choosing each next level in a 60-trial block of the shipped
  ``digit_size_adaptive`` protocol (its grids: 12 levels, 25 thresholds x 4 slopes x 3
  lapse rates), a simulated observer answering: the wait from a response to the next level
  (the posterior's update, the row's estimate and interval, and the choice by expected
  entropy), longest and median of the block's 60 (wall time: the participant waits it);
  target: the longest < 50 ms (a pause a participant does not notice between answering and
  the next stimulus). Baseline, measured in the same run: the same wait with a 1-up/2-down
  staircase on the same grid, the cheapest procedure.
* rebuilding that block from its 60 recorded responses, as a resume does (informative).
* an adaptive dry-run: simulated session seconds per wall second for simulated participants
  (perceptual observer, simulated device, virtual clock) on the shipped protocol, against
  real time (1 s/s); target ratio >= 100. The first participant pays for rendering every
  level's frames (the render cache then serves the rest), as the first participant of any
  dry-run does.
"""

from __future__ import annotations

import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from crs_study.adaptive import AdaptiveRun, RecordedTrial, StaircaseSpec, make_track
from crs_study.adaptive.recovery import Observer
from crs_study.benchmarks import Figure
from crs_study.protocol import load_protocol
from crs_study.session.dry_runs import dry_run

AREA = "adaptive"
DESCRIPTION = "QUEST+ next-level wait in a 60-trial block; adaptive dry-run speed"

#: Longest wait for QUEST+'s next level (s): below what a participant notices.
TARGET_NEXT_S = 0.050
#: Least simulated seconds per wall second of an adaptive dry-run (a rehearsal of a study
#: takes minutes, not the study's hours).
TARGET_SPEEDUP = 100.0
BLOCK_TRIALS = 60


def _block(spec, rng: np.random.Generator) -> tuple[list[float], list[tuple[float, bool]]]:
    """One block against a known observer: the wait for each level (the first choice, then
    each response's update and the next choice), and the history."""
    track = make_track(spec, 10)
    observer, threshold = Observer(slope=4.0, lapse=0.02), sum(spec.axis_bounds) / 2
    waits, history = [], []
    start = time.perf_counter()
    level = track.next_level
    while True:
        waits.append(time.perf_counter() - start)
        correct = bool(rng.random() < observer.p_correct(spec.to_axis(level), threshold, 0.1))
        history.append((level, correct))
        start = time.perf_counter()
        track.update(correct)
        if track.finished:
            return waits, history
        level = track.next_level


def run(quick: bool) -> list[Figure]:
    protocol = load_protocol("digit_size_adaptive")
    quest = dataclasses.replace(protocol.adaptive, trials=BLOCK_TRIALS)
    stair = dataclasses.replace(quest, procedure="staircase", quest_plus=None,
                                target_rate=None, staircase=StaircaseSpec(
                                    "1-up-2-down", quest.grid()[-1], (2, 1)))
    _ = make_track(quest, 10).next_level  # imports and first use, outside the timing
    waits, history = _block(quest, np.random.default_rng(7))
    baseline = statistics.median(_block(stair, np.random.default_rng(7))[0])
    start = time.perf_counter()
    run_ = AdaptiveRun(quest, 10)
    run_.replay(RecordedTrial(0, level, correct) for level, correct in history)
    replay_s = time.perf_counter() - start
    figures = [
        Figure(AREA, f"QUEST+ next level, longest of a {BLOCK_TRIALS}-trial block", max(waits),
               "s", "staircase wait", baseline,
               f"value < {TARGET_NEXT_S * 1000:g} ms", max(waits) < TARGET_NEXT_S),
        Figure(AREA, f"QUEST+ next level, median of a {BLOCK_TRIALS}-trial block",
               statistics.median(waits), "s", "staircase wait", baseline),
        Figure(AREA, f"resume: rebuild a {BLOCK_TRIALS}-trial QUEST+ block by replay",
               replay_s, "s", "staircase wait", baseline),
        _dry_run_speed(2 if quick else 6),
    ]
    return figures


def _dry_run_speed(participants: int) -> Figure:
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        result = dry_run("digit_size_adaptive", participants, Path(folder) / "ds")
        wall = time.perf_counter() - start
    speed = result.session_seconds / wall
    return Figure(AREA, f"adaptive dry-run, {participants} participant(s) of "
                  "digit_size_adaptive (simulated s per wall s)", speed, "s/s", "real time",
                  1.0, f"ratio >= {TARGET_SPEEDUP:g}", speed >= TARGET_SPEEDUP)
