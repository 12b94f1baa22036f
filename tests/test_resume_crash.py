"""Crash safety: SIGKILL at random moments, then the same command, until the session is done.

30 runs of ``crs-study run ... --device sim:// --clock virtual --responder random`` are each
killed (SIGKILL, no clean-up) at a seeded random moment after they start playing or replaying
trials; each is followed by the same command. When a session completes before the 30 kills
are spent, the next session number continues. Every session must end byte-identical to an
uninterrupted run of the same command: the trial file (every column: on a virtual clock no
column depends on wall time) and the per-frame device log. Only the sidecar's wall-clock
fields differ: StartTime, EndTime and Resumes (when the session was resumed).
"""

from __future__ import annotations

import csv
import gzip
import json
import os
import random
import select
import signal
import subprocess
import sys
import time

import pytest
from _session_helpers import tiny_protocol

KILLS = 30
WALL_CLOCK_SIDECAR_KEYS = {"StartTime", "EndTime", "Resumes"}


def command(protocol, dataset, session, responder):
    return [sys.executable, "-m", "crs_study", "run", str(protocol), "--participant", "p01",
            "--device", "sim://", "--out", str(dataset), "--responder", responder,
            "--clock", "virtual", "--session", str(session)]


def responders() -> list[str]:
    """The responder of each half of the kills: the perceptual observer (its answers depend on
    the displayed surface, so on the device's exact history) and the random responder."""
    return ["observer", "random"]


def wait_for_trials(process, timeout=60.0) -> bool:
    """Read the child's progress on stderr until it reports a trial (True) or exits (False)."""
    deadline = time.monotonic() + timeout
    seen = b""
    fd = process.stderr.fileno()
    while time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.5)
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:
                return False
            seen += chunk
            if b"trial" in seen:
                return True
    raise AssertionError(f"no progress within {timeout} s: {seen!r}")


def session_files(dataset, session):
    beh = dataset / f"sub-p01/ses-{session}/beh/sub-p01_ses-{session}_task-digitid_beh"
    frames = (dataset / f"sourcedata/sub-p01/ses-{session}"
              / f"sub-p01_ses-{session}_task-digitid_frames.tsv.gz")
    return beh.with_suffix(".tsv"), beh.with_suffix(".json"), frames


@pytest.mark.slow
def test_sigkill_at_random_moments_loses_and_duplicates_nothing(tmp_path):
    protocol = tiny_protocol(tmp_path, digits=tuple(range(10)), repetitions=2)
    dataset = tmp_path / "killed"
    rng = random.Random(20261122)
    kills, session, sessions = 0, 0, []  # sessions: (number, responder)
    for phase, responder in enumerate(responders()):
        session += 1
        while kills < KILLS // 2 * (phase + 1):
            process = subprocess.Popen(command(protocol, dataset, session, responder),
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            try:
                playing = wait_for_trials(process)
                if playing:
                    time.sleep(rng.uniform(0.0, 0.15))
                if process.poll() is None:
                    process.send_signal(signal.SIGKILL)
                    kills += 1
                process.wait(timeout=60)
            finally:
                process.kill()
                process.wait()
                process.stdout.close()
                process.stderr.close()
            _, sidecar, _ = session_files(dataset, session)
            if process.returncode == 0 and json.loads(sidecar.read_text())["Status"] == \
                    "complete":
                sessions.append((session, responder))
                session += 1
        # the same command, once more, finishes the session in progress
        finished = subprocess.run(command(protocol, dataset, session, responder),
                                  capture_output=True, text=True, timeout=120)
        assert finished.returncode == 0, finished.stderr
        sessions.append((session, responder))

    for number, responder in sessions:
        reference = tmp_path / f"whole-{number}"
        done = subprocess.run(command(protocol, reference, number, responder),
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        tsv, sidecar, frames = session_files(dataset, number)
        ref_tsv, ref_sidecar, ref_frames = session_files(reference, number)
        with open(tsv, newline="") as handle:
            rows = list(csv.DictReader(handle, delimiter="\t"))
        assert [int(r["trial_index"]) for r in rows] == list(range(len(rows)))  # order kept
        assert tsv.read_bytes() == ref_tsv.read_bytes()  # nothing lost, nothing duplicated
        assert gzip.decompress(frames.read_bytes()) == gzip.decompress(ref_frames.read_bytes())
        meta, ref_meta = json.loads(sidecar.read_text()), json.loads(ref_sidecar.read_text())
        assert meta["Status"] == "complete" and meta["TrialsCompleted"] == len(rows)
        assert {k: v for k, v in meta.items() if k not in WALL_CLOCK_SIDECAR_KEYS} == \
            {k: v for k, v in ref_meta.items() if k not in WALL_CLOCK_SIDECAR_KEYS}
    assert kills == KILLS
    # the kills really landed inside sessions: some were resumed
    resumed = sum(len(json.loads(session_files(dataset, n)[1].read_text())["Resumes"])
                  for n, _ in sessions)
    assert resumed >= KILLS // 2
