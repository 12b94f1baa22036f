"""Crash safety: SIGKILL at random moments, then the same command, until the session is done.

30 runs of ``crs-study run ... --device sim:// --clock virtual`` (15 with the perceptual
observer, whose answers depend on the device's exact history, on sessions 1, 2, ..; 15 with
the random responder on sessions 101, 102, ..; the two series run side by side) are each
killed (SIGKILL, no clean-up) at a seeded random moment; each is followed by the same
command. When a session completes, the next session number continues. Every session must end
byte-identical to an uninterrupted run of the same command: the trial file (every column: on
a virtual clock no column depends on wall time) and the per-frame device log; the sidecars
differ only in their wall-clock fields (StartTime, EndTime, Resumes), and no temporary file
is left behind. The whole test runs twice: on a fixed protocol, and on an adaptive one
(QUEST+ chooses each test trial's digit height: a resumed run rebuilds the tracks by
replaying the stored responses and must reach the sidecar's fingerprint).

Where the kills land. The child is ``crs_study.cli.main`` behind a few wrappers
(:func:`_kill_child.run`), forked from a server that imported crs_study once (so a run's life
is its session, not the 1.5 s of importing scipy and pandas, before any file is opened); the
wrappers append phase markers (monotonic time, phase) to a file: trial k begins, trial k's
row is stored, a sidecar write begins and ends (``running`` after each trial, ``complete`` at
the end), a replay of stored trials begins and ends. Each kill is classified by the last
marker before it (:func:`phase_at`): start-up (the command line, protocol checks, the first
sidecar), replay, mid-trial, between trials (the row stored, the sidecar not yet rewritten,
the next trial not begun), the completion write, after completion. The moments are drawn
from four kinds, each responder's 15 kills in a seeded random order (:func:`schedule`):

* 3 start-up: uniform over the start-up of an uninterrupted run (measured on the series'
  first reference run) plus half the trial time of the rows a resumed run replays;
* 6 time: uniform over the trials this run has still to play, from its first trial;
* 3 between trials: the child holds for ``HOLD_S`` just after storing the row of a trial
  drawn from those still to run, and the kill falls at a uniform moment of the hold;
* 3 completion write (once half the session is stored): the child holds for ``HOLD_S``
  inside the final sidecar write (the temporary file written and fsynced, not yet renamed;
  ``os.replace`` is where it waits), and the kill falls at a uniform moment from the start
  of that write to the end of the hold.

A run's wall time is a few tenths of a second of start-up and half a second of trials, and
a trial's sidecar write lasts about a millisecond, so kills uniform in time would mostly land
in start-up and almost never between trials or in the completion write; the strata and the
holds (which change nothing that is written) spread them over the whole session. The spread
achieved is printed (``pytest -n 0 -s``) and each of start-up, mid-trial, between trials and
completion write must be hit.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import csv
import gzip
import hashlib
import json
import multiprocessing
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import _kill_child
import pytest
from _session_helpers import adaptive_protocol, assert_same_but_reruns, tiny_protocol

#: The runs are forked from a server that imported crs_study first (:mod:`_kill_child`).
FORKS = multiprocessing.get_context("forkserver")
FORKS.set_forkserver_preload(_kill_child.PRELOAD)
KILLS = 30
HOLD_S = 0.25
WALL_CLOCK_SIDECAR_KEYS = {"StartTime", "EndTime", "Resumes"}
#: Keys a killed session has and its uninterrupted reference has not: why it stopped, and the
#: hash of a trial file whose rerun trials say rerun = 1 (checked against the file instead).
INTERRUPTION_SIDECAR_KEYS = {"Interruptions", "TrialsSha256"}

PHASE_NAMES = ("start-up", "replay", "mid-trial", "between trials", "completion write",
               "after completion")


def arguments(protocol, dataset, session, responder):
    return ["run", str(protocol), "--participant", "sim01", "--device", "sim://", "--out",
            str(dataset), "--responder", responder, "--clock", "virtual", "--session",
            str(session)]


class Run:
    """One ``crs-study run`` forked from the fork server (:mod:`_kill_child`): the few calls
    of :class:`subprocess.Popen` the test makes (poll, wait, SIGKILL, stderr)."""

    def __init__(self, argv: list[str], env: dict[str, str], stderr: Path,
                 phases: Path) -> None:
        self.stderr_path = stderr
        self.phases = phases
        self.killed = False
        self.process = FORKS.Process(target=_kill_child.run, args=(argv, env, str(stderr)),
                                     daemon=True)
        self.process.start()

    def poll(self) -> int | None:
        return self.process.exitcode

    def wait(self, timeout: float) -> int:
        self.process.join(timeout)
        if self.process.exitcode is None:
            raise subprocess.TimeoutExpired("crs-study run", timeout)
        return self.process.exitcode

    def kill(self) -> None:
        if self.process.exitcode is None:
            self.killed = True
            self.process.kill()  # SIGKILL

    #: The exit code multiprocessing's forkserver reports when it could not read a child's
    #: status (popen_forkserver.Popen.poll: EOFError -> 255). Seen once in five loaded runs
    #: for a child this test had just SIGKILLed (its stderr: the trials up to the kill, no
    #: error), and once for an uninterrupted run whose phase log ends with its completion
    #: written (its stderr: every trial, no error); crs-study itself exits 0, 1 or 2.
    STATUS_LOST = 255

    def ended_as_expected(self, code: int) -> bool:
        """Finished (0), or killed by this test (SIGKILL, or a lost status after the kill)."""
        return code in (0, -signal.SIGKILL) or (self.killed and code == self.STATUS_LOST)

    def finished(self, timeout: float = 120) -> bool:
        """The run exited 0, or its status was lost after it wrote its completion (the
        dataset it wrote is compared byte for byte all the same)."""
        code = self.wait(timeout)
        events = markers(self.phases)
        return code == 0 or (code == self.STATUS_LOST and not self.killed and bool(events)
                             and events[-1][1] == "save-end complete")

    def error(self) -> str:
        return self.stderr_path.read_text() if self.stderr_path.exists() else ""


def start(protocol, dataset, session, responder, phases: Path, **holds) -> Run:
    env = dict(os.environ, CRS_TEST_PHASES=str(phases), CRS_TEST_HOLD_S=str(HOLD_S))
    env.update({f"CRS_TEST_HOLD_{k.upper()}": str(v) for k, v in holds.items()})
    return Run(arguments(protocol, dataset, session, responder), env,
               phases.with_suffix(".err"), phases)


def markers(phases: Path) -> list[tuple[float, str]]:
    if not phases.exists():
        return []
    out = []
    for line in phases.read_text().splitlines():
        stamp, _, what = line.partition(" ")
        out.append((float(stamp), what))
    return out


def phase_at(events: list[tuple[float, str]], moment: float) -> str:
    """Where a process was at ``moment``: the phase its last marker before then opened."""
    state = "start-up"
    for stamp, what in events:
        if stamp > moment:
            break
        kind = what.split()[0]
        if kind == "replay-begin":
            state = "replay"
        elif kind == "replay-end":
            state = "start-up"  # a resumed run after its replay, before its next trial
        elif kind == "trial":
            state = "mid-trial"
        elif kind in ("row", "hold"):
            state = "completion write" if what == "hold complete" else "between trials"
        elif what == "save-begin complete":
            state = "completion write"
        elif what == "save-end complete":
            state = "after completion"
    return state


def wait_for(phases: Path, what: str, process: Run, timeout=60.0) -> bool:
    """Poll the marker file until ``what`` appears (True) or the process ends (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(w == what for _, w in markers(phases)):
            return True
        if process.poll() is not None:
            return False
        time.sleep(0.002)
    raise AssertionError(f"{what!r} not reached within {timeout} s")


def session_files(dataset, session):
    beh = dataset / f"sub-sim01/ses-{session}/beh/sub-sim01_ses-{session}_task-digitid_beh"
    frames = (dataset / f"sourcedata/sub-sim01/ses-{session}"
              / f"sub-sim01_ses-{session}_task-digitid_frames.tsv.gz")
    return beh.with_suffix(".tsv"), beh.with_suffix(".json"), frames


def stored_rows(dataset, session) -> int:
    """Whole rows in a session's TSV (a torn last line is rerun, so it does not count)."""
    tsv = session_files(dataset, session)[0]
    return max(0, tsv.read_bytes().count(b"\n") - 1) if tsv.exists() else 0


def is_complete(dataset, session) -> bool:
    sidecar = session_files(dataset, session)[1]
    try:
        return json.loads(sidecar.read_text())["Status"] == "complete"
    except (FileNotFoundError, ValueError):
        return False


def schedule(rng: random.Random) -> list[str]:
    """The kinds of one responder's kills, in a seeded random order."""
    kinds = ["start-up"] * 3 + ["time"] * 6 + ["between trials"] * 3 + ["completion write"] * 3
    rng.shuffle(kinds)
    return kinds


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["fixed", "adaptive"])
def test_sigkill_at_random_moments_loses_and_duplicates_nothing(tmp_path, kind):
    """``adaptive``: QUEST+ chooses each test trial's height; a resumed run
    rebuilds its tracks by replaying the stored responses, checked against the sidecar."""
    if kind == "fixed":
        protocol = tiny_protocol(tmp_path, digits=(1, 4, 7), repetitions=4)
    else:
        protocol = adaptive_protocol(tmp_path, procedure="quest-plus", trials=12)
    planned = 26  # 3 digits x 2 conditions x 4 (adaptive: 12 a block) + 2 practice
    dataset = tmp_path / "killed"
    references: dict[int, Run] = {}

    def reference(number, responder, phases=None):
        """The uninterrupted run of a session, in the background (compared at the end)."""
        if number not in references:
            references[number] = start(protocol, tmp_path / f"whole-{number}", number,
                                       responder, phases or tmp_path / f"whole-{number}.log")

    def kill_sessions(responder: str, session: int, rng: random.Random):
        """15 kills of sessions session, session + 1, .. run with ``responder``.

        Returns the kills (kind, phase hit, time from process start as a fraction of an
        uninterrupted run's life), the sessions (number, responder) and the runs made.
        """
        # The first session's reference first: how long start-up and a trial take.
        timing_log = tmp_path / f"timing-{session}.log"
        reference(session, responder, timing_log)
        assert references[session].finished(), references[session].error()
        timing = markers(timing_log)
        begin = next(t for t, w in timing if w == "process")
        first = next(t for t, w in timing if w == "trial 0")
        end = next(t for t, w in timing if w == "save-end complete")
        startup, per_trial, life = first - begin, (end - first) / planned, end - begin
        kills: list[tuple[str, str, float]] = []
        sessions, runs, plan = [], 0, schedule(rng)
        while len(kills) < KILLS // 2:
            rows = stored_rows(dataset, session)
            feasible = {"start-up": True, "time": rows < planned,
                        "between trials": rows < planned,
                        # the session must get on first: a completion kill restarts no trial
                        "completion write": rows >= planned // 2}
            # none feasible: every row stored, only kills in trials left: the run finishes
            kind = next((k for k in plan if feasible[k]), "finish")
            holds = {"row": rng.randrange(rows, planned)} if kind == "between trials" else \
                {"complete": 1} if kind == "completion write" else {}
            runs += 1
            phases = tmp_path / f"phases-{session}-{runs}.log"
            process = start(protocol, dataset, session, responder, phases, **holds)
            try:
                if kind == "start-up":  # interpreter, imports, checks, replay of stored rows
                    delay = rng.uniform(0.0, startup + rows * per_trial / 2)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        process.wait(timeout=delay)
                elif kind == "time":  # a moment among the trials this run has to play
                    delay = rng.uniform(0.0, (planned - rows) * per_trial)
                    if wait_for(phases, f"trial {rows}", process):
                        with contextlib.suppress(subprocess.TimeoutExpired):
                            process.wait(timeout=delay)
                elif kind != "finish":
                    what = f"hold row {holds['row']}" if "row" in holds else \
                        "save-begin complete"
                    if wait_for(phases, what, process):
                        time.sleep(rng.uniform(0.0, HOLD_S))
                else:
                    process.wait(timeout=60)
                if process.poll() is None:
                    moment = time.monotonic()
                    process.kill()  # SIGKILL
                    events = markers(phases)
                    kills.append((kind, phase_at(events, moment),
                                  (moment - events[0][0]) / life if events else 0.0))
                    if kind in plan:
                        plan.remove(kind)
                # killed, or done; a run that fails on its own (a resume refused) is the bug
                code = process.wait(timeout=60)
                assert process.ended_as_expected(code), (code, process.error())
            finally:
                process.kill()
                process.wait(timeout=60)
            if is_complete(dataset, session):  # finished (or killed once it had)
                sessions.append((session, responder))
                session += 1
                reference(session, responder)
        # the same command, once more, finishes the session in progress
        finished = subprocess.run([sys.executable, "-m", "crs_study",
                                   *arguments(protocol, dataset, session, responder)],
                                  capture_output=True, text=True, timeout=120)
        assert finished.returncode == 0, finished.stderr
        sessions.append((session, responder))
        reference(session, responder)
        return kills, sessions, runs

    # The observer's sessions (1, 2, ..) and the random responder's (101, 102, ..) are killed
    # at the same time, each from its own seeded generator: half the wall time on two cores.
    started = time.monotonic()
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        phases = [pool.submit(kill_sessions, responder, first, random.Random(seed))
                  for responder, first, seed in (("observer", 1, 20261122),
                                                 ("random", 101, 20261123))]
        results = [future.result() for future in phases]
    kills = [k for kills, _, _ in results for k in kills]
    sessions = [s for _, sessions, _ in results for s in sessions]
    runs = sum(runs for _, _, runs in results)

    for number, _ in sessions:
        done = references[number]
        assert done.finished(), done.error()
        tsv, sidecar, frames = session_files(dataset, number)
        ref_tsv, ref_sidecar, ref_frames = session_files(tmp_path / f"whole-{number}", number)
        with open(tsv, newline="") as handle:
            rows = list(csv.DictReader(handle, delimiter="\t"))
        assert [int(r["trial_index"]) for r in rows] == list(range(len(rows)))  # order kept
        meta, ref_meta = json.loads(sidecar.read_text()), json.loads(ref_sidecar.read_text())
        # nothing lost, nothing duplicated; a trial a kill cut after its stimulus began says
        # rerun = 1 (the participant felt part of it), and only those
        cut = {i["AtTrial"] for i in meta.get("Interruptions", ()) if i["TrialCut"]}
        assert_same_but_reruns(tsv, ref_tsv, cut)
        assert meta["TrialsSha256"] == hashlib.sha256(tsv.read_bytes()).hexdigest()
        assert gzip.decompress(frames.read_bytes()) == gzip.decompress(ref_frames.read_bytes())
        assert meta["Status"] == "complete" and meta["TrialsCompleted"] == len(rows) == planned
        ignored = WALL_CLOCK_SIDECAR_KEYS | INTERRUPTION_SIDECAR_KEYS
        assert {k: v for k, v in meta.items() if k not in ignored} == \
            {k: v for k, v in ref_meta.items() if k not in ignored}
    # a kill inside an atomic write leaves its temporary file; the next write takes it over
    assert not [p for p in dataset.rglob("*.tmp")]

    assert len(kills) == KILLS == 2 * len(schedule(random.Random(0)))
    hit = collections.Counter(where for _, where, _ in kills)
    by_kind = collections.Counter(kind for kind, _, _ in kills)
    fractions = sorted(round(f, 2) for _, _, f in kills)
    resumed = sum(len(json.loads(session_files(dataset, n)[1].read_text())["Resumes"])
                  for n, _ in sessions)
    print(f"\n{KILLS} kills in {runs} runs over {len(sessions)} sessions "
          f"({time.monotonic() - started:.0f} s): kinds {dict(by_kind)}; phases hit "
          f"{ {p: hit[p] for p in PHASE_NAMES if hit[p]} }; kill times as fractions of an "
          f"uninterrupted run's life: {fractions}; {resumed} resumes")
    for needed in ("start-up", "mid-trial", "between trials", "completion write"):
        assert hit[needed] >= 1, (needed, kills)
    assert resumed >= KILLS // 2  # the kills really landed inside sessions


@pytest.mark.parametrize("procedure", ["quest-plus", "staircase"])
def test_two_kills_at_the_first_adaptive_trial_leave_a_resumable_session(tmp_path, procedure):
    """The kills that found the empty-track fingerprint (tests/test_adaptive_replay.py): the
    first run is killed with trial 0 (practice) stored and the sidecar not yet rewritten;
    its resume writes the sidecar and is killed with trial 1 (the block's first adaptive
    trial) stored; the same command then finishes the session, equal to an uninterrupted
    run of it. Before the fix the third run refused: "the adaptive procedures' state after
    1 trials differs"."""
    protocol = adaptive_protocol(tmp_path, procedure=procedure, trials=4)
    dataset, whole = tmp_path / "killed", tmp_path / "whole"
    reference = start(protocol, whole, 1, "random", tmp_path / "whole.log")
    for row in (0, 1):
        phases = tmp_path / f"phases-{row}.log"
        process = start(protocol, dataset, 1, "random", phases, row=row)
        try:
            assert wait_for(phases, f"hold row {row}", process), process.error()
        finally:
            process.kill()
            process.wait(timeout=60)
        assert stored_rows(dataset, 1) == row + 1 and not is_complete(dataset, 1)
    finished = start(protocol, dataset, 1, "random", tmp_path / "finish.log")
    assert finished.finished(), finished.error()
    assert reference.finished(), reference.error()
    tsv, sidecar, frames = session_files(dataset, 1)
    ref_tsv, _, ref_frames = session_files(whole, 1)
    assert_same_but_reruns(tsv, ref_tsv, set())
    assert gzip.decompress(frames.read_bytes()) == gzip.decompress(ref_frames.read_bytes())
    assert len(json.loads(sidecar.read_text())["Resumes"]) == 2
