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

Figure: the keypad's key time stamp in a real pseudo-terminal, the median delay from writing a
key on the master to the stamp the responder gives it, against a bare ``select()`` woken by the
same write (measured in the same run); target: a median within a millisecond.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import os
import select
import statistics
import tempfile
import termios
import time
import tty
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from crs_study.benchmarks import Figure
from crs_study.clock import RealClock
from crs_study.paths import shipped_file
from crs_study.session.responders.base import StimulusRecord
from crs_study.session.responders.keypad import KeypadResponder
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec

AREA = "runner"
DESCRIPTION = "dry-run speed: the default protocol, one simulated participant, vs real time"
TARGET_SPEEDUP = 100.0
#: The keypad's median delay from a key's write to its time stamp (s).
TARGET_STAMP_S = 0.001
#: Keys written per figure: (quick, full).
STAMP_KEYS = (5, 30)


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
        _key_stamps(STAMP_KEYS[not quick]),
    ]


def _key_stamps(keys: int) -> Figure:
    """The keypad's stamp delay on a pty, median over ``keys`` keys, against select()."""
    trial = SimpleNamespace(index=0, digit=7, symbol=7, block=1, condition="crs",
                            trial_type="test")
    clock = RealClock()
    delays, wakes = [], []
    master, slave = os.openpty()
    try:
        cooked = termios.tcgetattr(slave)
        tty.setcbreak(slave)  # a key reads without Enter, as the keypad sets it
        for _ in range(keys):  # a bare wake-up: the floor any reader of the terminal meets
            written = time.monotonic()
            os.write(master, b"x")
            select.select([slave], [], [], 1.0)
            wakes.append(time.monotonic() - written)
            os.read(slave, 16)
        termios.tcsetattr(slave, termios.TCSANOW, cooked)
        with KeypadResponder(fd=slave, output=io.StringIO()) as keypad:
            for k in range(keys):
                onset = clock.now()
                keypad.begin_trial(trial, onset, clock)
                time.sleep(0.02)
                written = time.monotonic()
                os.write(master, str(k % 10).encode())
                record = StimulusRecord(None, "crs", np.zeros(1), np.zeros((1, 1)),
                                        tuple(range(10)), onset, onset + 0.01)
                answer = keypad.respond(trial, record, clock, 5.0)
                keypad.end_trial()
                delays.append(answer.response_time_s - (written - onset))
    finally:
        os.close(master)
        os.close(slave)
    delay, wake = statistics.median(delays), statistics.median(wakes)
    return Figure(AREA, f"keypad key stamp, median delay after the write ({keys} keys on a pty)",
                  delay * 1e3, "ms", "a bare select() woken by the same write", wake * 1e3,
                  f"value <= {TARGET_STAMP_S * 1e3:g} ms", delay <= TARGET_STAMP_S)
