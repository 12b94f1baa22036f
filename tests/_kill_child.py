"""The child process of tests/test_resume_crash.py: ``crs_study.cli.main`` with phase markers
and optional holds, forked from a fork server that has imported crs_study once.

A ``crs-study run`` is about 1.5 s of importing (scipy, pandas, questplus) and well under a
second of session on a virtual clock; the crash test starts some 90 of them. Forked from a
server that imported the package beforehand (``multiprocessing``'s ``forkserver`` context
with :data:`PRELOAD`), a run is only its session: every kill lands in what a run does to
the dataset, none in the import of a library that has not opened a file yet. What a run
writes is the same: the test ends each session with a plain ``python -m crs_study`` process
and compares it byte for byte with the uninterrupted runs made here.

Environment of a run (:func:`run`'s ``env``): CRS_TEST_PHASES (marker file),
CRS_TEST_HOLD_ROW (trial index), CRS_TEST_HOLD_COMPLETE (1), CRS_TEST_HOLD_S.
"""

from __future__ import annotations

import os
import sys
import time

#: What the fork server imports before the first fork: this module, the CLI and what the
#: ``run`` command imports when it runs (the runner, the dataset, the protocol, and what the
#: adaptive procedures import on first use: QUEST+ and scipy.stats).
PRELOAD = ["_kill_child", "crs_study.cli", "crs_study.commands.run", "crs_study.dataset",
           "crs_study.session.runner", "questplus.qp", "scipy.stats"]


def mark(phases: str, what: str) -> None:
    fd = os.open(phases, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.write(fd, f"{time.monotonic():.6f} {what}\n".encode())
    os.close(fd)


def run(argv: list[str], env: dict[str, str], stderr_path: str) -> None:
    """``crs-study ARGV`` in this (forked) process, in ``env``, stderr to ``stderr_path``,
    with the markers and holds of the module docstring; exits with main's status."""
    os.environ.clear()
    os.environ.update(env)
    phases = env["CRS_TEST_PHASES"]
    mark(phases, "process")
    null = os.open(os.devnull, os.O_WRONLY)
    err = os.open(stderr_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(null, 1)
    os.dup2(err, 2)
    os.close(null)
    os.close(err)

    hold_s = float(env.get("CRS_TEST_HOLD_S", "0"))
    hold_row = int(env.get("CRS_TEST_HOLD_ROW", "-1"))
    hold_complete = env.get("CRS_TEST_HOLD_COMPLETE") == "1"

    import crs_study.dataset as dataset
    import crs_study.session.runner as runner
    from crs_study.cli import main

    mark(phases, "imported")
    real_run_trial, real_save, real_replay = runner.run_trial, runner.save, runner.replay
    real_append_row, real_replace = dataset.SessionStore.append_row, os.replace
    completing = False

    def run_trial(state, device, responder, clock, origin, cache, trial):
        mark(phases, f"trial {trial.index}")
        real_run_trial(state, device, responder, clock, origin, cache, trial)

    def append_row(self, row):
        real_append_row(self, row)
        mark(phases, f"row {row['trial_index']}")
        if row["trial_index"] == hold_row:
            mark(phases, f"hold row {hold_row}")
            time.sleep(hold_s)

    def save(state, status, final=False):
        nonlocal completing
        mark(phases, f"save-begin {status}")
        completing = status == "complete"
        real_save(state, status, final)
        completing = False
        mark(phases, f"save-end {status}")

    def replace(src, dst, *args, **kwargs):
        if completing and hold_complete and str(dst).endswith("_beh.json"):
            mark(phases, "hold complete")
            time.sleep(hold_s)
        return real_replace(src, dst, *args, **kwargs)

    def replay(*args):
        mark(phases, "replay-begin")
        real_replay(*args)
        mark(phases, "replay-end")

    runner.run_trial, runner.save, runner.replay = run_trial, save, replay
    dataset.SessionStore.append_row = append_row
    os.replace = replace
    sys.exit(main(argv))
