"""Withdrawal: a participant's data removed from a dataset, all or nothing, with an audit line.

What goes is exactly what BIDS names for the participant (:mod:`.withdrawal_plan`: the
``sub-<label>`` paths, the ``participant_id`` rows, the analysis outputs holding them), listed
before anything is done (``announce``) and shown without acting by :func:`plan_withdrawal`
(``crs-study consent withdraw --dry-run``).

Withdrawal is all-or-nothing per dataset. A journal naming every path to remove is made
durable first (``DATASET/.crs-study-withdrawal.json``), under the dataset lock and only when no
session of the participant holds its lock; while the journal exists no session may start in
the dataset (:meth:`crs_study.dataset.Dataset.refuse_pending_withdrawal`), so no runner can
write the participant's data back. The register then marks the withdrawal (so the gate refuses
sessions at once), the paths are renamed into a staging directory, analysis outputs outside
the dataset are deleted, the participants-like TSVs and the outputs record are rewritten
atomically, the staging directory is deleted, the audit line is appended and the journal is
removed. Every step is idempotent, so an interrupted withdrawal is finished by running it
again (or :func:`recover_withdrawal`): the dataset is either as before (journal not yet
written) or, once recovered, fully withdrawn. Files of other participants are never opened
for writing.

A session of the participant running in a dataset: the register is marked withdrawn first,
so the session stops at its next trial boundary (the runner checks the gate before every
trial, :mod:`crs_study.consent.gate`); the withdrawal waits up to ``wait_s`` for it to stop,
saying so, and otherwise is refused, to be run again once it has stopped.
"""

from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil
import signal
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from crs_study._files import fsync_dir, write_atomically
from crs_study.consent.register import Register, check_label
from crs_study.consent.withdrawal_plan import (
    STAGING_DIR,
    DatasetWithdrawal,
    plan_withdrawal,
    without_rows,
)
from crs_study.dataset import WITHDRAWAL_JOURNAL, Dataset, utc_now
from crs_study.dataset.bids import PARTICIPANTS_TSV
from crs_study.dataset.outputs import OUTPUTS_REGISTRY, rewrite_without
from crs_study.errors import ConsentError

#: Journal of a withdrawal in progress, in the dataset (``crs_study.dataset.WITHDRAWAL_JOURNAL``).
JOURNAL_FILE = WITHDRAWAL_JOURNAL
#: Test hook: kill the process at the n-th withdrawal checkpoint (simulates a power cut).
CRASH_ENV = "CRS_STUDY_WITHDRAW_CRASH_AT"
#: How often a withdrawal waiting for a running session looks at its lock (s).
POLL_S = 0.2

#: Where a withdrawal says what it is doing (one line at a time).
Progress = Callable[[str], None]


_checkpoints = 0


def _checkpoint() -> None:
    """Crash here when the test hook says so (simulates a power cut mid-withdrawal)."""
    global _checkpoints
    _checkpoints += 1
    target = os.environ.get(CRASH_ENV)
    if target and int(target) == _checkpoints:
        os.kill(os.getpid(), signal.SIGKILL)


def participant_paths(dataset: Path, participant: str) -> list[str]:
    """The paths of ``dataset`` a withdrawal of ``participant`` removes (relative, sorted):
    :attr:`~.withdrawal_plan.DatasetWithdrawal.paths` of :func:`plan_withdrawal`."""
    check_label(participant)
    return list(plan_withdrawal(Path(dataset), participant).paths)


def running_sessions(dataset: Path, participant: str) -> list[Path]:
    """The session locks of ``participant`` in ``dataset`` that a runner holds now."""
    held = []
    for lock in sorted((dataset / f"sub-{participant}").rglob("*.lock")):
        with open(lock, "a+") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                held.append(lock)
                continue
            fcntl.flock(handle, fcntl.LOCK_UN)
    return held


def _check_not_running(dataset: Path, participant: str) -> None:
    held = running_sessions(dataset, participant)
    if held:
        raise ConsentError(
            f"a session of participant {participant!r} is running ({held[0]}); its consent "
            "is marked withdrawn, so it stops at its next trial boundary: run this command "
            "again once it has stopped")


def _write_json_atomically(path: Path, data: dict) -> None:
    write_atomically(path, json.dumps(data, indent=2, sort_keys=True))


def pending_withdrawal(dataset: str | Path) -> dict | None:
    """The journal of an unfinished withdrawal in ``dataset``, or None."""
    journal = Path(dataset) / JOURNAL_FILE
    if not journal.exists():
        return None
    try:
        return json.loads(journal.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        # A journal is written atomically, so a torn one cannot exist; an unreadable one
        # must not be guessed at.
        raise ConsentError(f"{journal}: unreadable withdrawal journal; inspect it by hand"
                           ) from None


def journal_plan(dataset: Path, journal: dict) -> DatasetWithdrawal:
    """The plan a journal carries (a journal of older software: its paths and
    participants.tsv)."""
    rows = journal.get("rows")
    if rows is None:
        rows = [PARTICIPANTS_TSV] if journal.get("participants_tsv_row", True) else []
    return DatasetWithdrawal(
        dataset, journal["participant"], tuple(journal["paths"]), dict(journal.get("why", {})),
        tuple(rows), tuple(journal.get("outputs", ())), tuple(journal.get("output_runs", ())),
        tuple(journal.get("output_dirs", ())), tuple(journal.get("notes", ())))


def _remove_stale_temporaries(dataset: Path, rows: Iterable[str] = ()) -> None:
    """Delete what a withdrawal killed inside an atomic write leaves: the temporary copies
    of the journal (it names the participant), of the TSVs losing rows and of the outputs
    record. Call under the dataset lock, where no other writer of these files can be at work."""
    for name in (JOURNAL_FILE, PARTICIPANTS_TSV, OUTPUTS_REGISTRY, *rows):
        path = dataset / name
        temporary = path.with_name(f".{path.name}.tmp")
        if temporary.exists():
            temporary.unlink()
            fsync_dir(temporary.parent)


def recover_withdrawal(dataset: str | Path) -> dict | None:
    """Finish an interrupted withdrawal from its journal; returns the audit entry or None."""
    dataset = Path(dataset)
    _check_dataset(dataset)  # a mistyped path is an error, never a new folder with a lock
    journal = pending_withdrawal(dataset)
    if journal is None:
        with Dataset(dataset).locked():
            _remove_stale_temporaries(dataset)
        return None
    return _complete(dataset, journal)


def _check_dataset(dataset: Path) -> None:
    if not dataset.is_dir():
        raise ConsentError(f"{dataset}: no such dataset directory")
    if not (dataset / "dataset_description.json").is_file():
        raise ConsentError(f"{dataset}: not a dataset (no dataset_description.json); give the "
                           "dataset's top folder")


def preview_withdrawal(participant: str, datasets: Iterable[str | Path]
                       ) -> list[DatasetWithdrawal]:
    """What :func:`withdraw` would remove from each dataset, changing nothing (the command
    line's ``consent withdraw --dry-run``)."""
    check_label(participant)
    plans = []
    for dataset in map(Path, datasets):
        _check_dataset(dataset)
        plans.append(plan_withdrawal(dataset, participant))
    return plans


def _begin(dataset: Path, participant: str, register: Register) -> dict:
    """Write the journal under the dataset lock, once no session of the participant runs."""
    with Dataset(dataset).locked():
        _check_not_running(dataset, participant)
        _remove_stale_temporaries(dataset)
        plan = plan_withdrawal(dataset, participant)
        journal = {
            **plan.to_dict(), "time": utc_now(),
            "register": str(register.directory.resolve()),
            "participants_tsv_row": PARTICIPANTS_TSV in plan.rows,
            "journal_id": secrets.token_hex(8),
        }
        del journal["dataset"]
        _write_json_atomically(dataset / JOURNAL_FILE, journal)
    _checkpoint()
    return journal


def _remove_outputs(plan: DatasetWithdrawal) -> None:
    """Delete the analysis outputs outside the dataset, then their folders left empty."""
    for name in plan.outputs:
        path = Path(name)
        if path.exists() or path.is_symlink():
            path.unlink()
            fsync_dir(path.parent)
            _checkpoint()
    for folder in plan.output_dirs:
        try:
            Path(folder).rmdir()
        except OSError:
            pass  # not empty (other files of the user's), or already gone


def _complete(dataset: Path, journal: dict) -> dict:
    plan = journal_plan(dataset, journal)
    participant = plan.participant
    register = Register(journal["register"])
    register.mark_withdrawn(participant)  # the gate refuses sessions from here on
    staging = dataset / STAGING_DIR
    staging.mkdir(exist_ok=True)
    for relative in plan.paths:
        source = dataset / relative
        if source.exists() or source.is_symlink():
            target = staging / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            os.rename(source, target)
            _checkpoint()
    _remove_outputs(plan)
    with Dataset(dataset).locked():  # a runner adding a participant rewrites participants.tsv
        for relative in plan.rows:
            path = dataset / relative
            if path.exists():
                text = path.read_text(encoding="utf-8")
                reduced = without_rows(text, participant)
                if reduced != text:
                    write_atomically(path, reduced)
        rewrite_without(dataset, participant, plan.output_runs)
    _checkpoint()
    shutil.rmtree(staging, ignore_errors=False)
    fsync_dir(dataset)
    _checkpoint()
    entry = {
        "event": "withdrawal", "participant": participant, "time": journal["time"],
        "completed": utc_now(), "dataset": str(dataset.resolve()), "removed": list(plan.paths),
        # journals from before this key existed removed the row whenever it was there
        "participants_tsv_row_removed": journal.get("participants_tsv_row", True),
        "rows_removed_from": list(plan.rows), "outputs_removed": list(plan.outputs),
        "notes": list(plan.notes), "journal_id": journal["journal_id"],
    }
    register.audit(entry)
    _checkpoint()
    with Dataset(dataset).locked():
        _remove_stale_temporaries(dataset, plan.rows)
        (dataset / JOURNAL_FILE).unlink()
        fsync_dir(dataset)
    return entry


def _wait_for_sessions(datasets: list[Path], participant: str, register: Register,
                       wait_s: float, progress: Progress | None) -> None:
    """Close the gate, then wait up to ``wait_s`` for running sessions of ``participant``."""
    running = [lock for d in datasets for lock in running_sessions(d, participant)]
    if not running:
        return
    register.mark_withdrawn(participant)  # the session stops at its next trial boundary
    if progress and wait_s > 0:
        progress(f"a session of participant {participant} is running ({running[0]}); its "
                 "consent is now marked withdrawn, so it stops at its next trial boundary: "
                 f"waiting up to {wait_s:g} s for it")
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and any(running_sessions(d, participant)
                                              for d in datasets):
        time.sleep(POLL_S)
    for dataset in datasets:
        _check_not_running(dataset, participant)


def withdraw(participant: str, datasets: Iterable[str | Path],
             register_dir: str | Path | None = None, *, wait_s: float = 0.0,
             announce: Callable[[DatasetWithdrawal], None] | None = None,
             progress: Progress | None = None) -> list[dict]:
    """Remove every file of ``participant`` from each dataset and mark the record withdrawn.

    Returns one audit entry per dataset: an unfinished withdrawal of another participant
    found in a dataset is finished first and has its own entry. ``announce`` is given each
    dataset's plan once its journal is durable and before anything is removed (the command
    line prints it). While a session of the participant runs in one of the datasets the
    register is marked withdrawn (the session stops at its next trial boundary) and the
    withdrawal waits up to ``wait_s`` seconds for it, else is refused with the data left
    (module docstring). Refused, with nothing changed, when the participant is neither in
    the register nor in any dataset (a mistyped label; an unreadable register line might
    be theirs, so then it proceeds, each such line a warning). Safe to run again after an
    interruption.
    """
    check_label(participant)
    register = Register(register_dir)
    datasets = [Path(d) for d in datasets]
    for dataset in datasets:
        _check_dataset(dataset)
    pending = {d: pending_withdrawal(d) for d in datasets}
    events, unreadable = register.scan()  # past unreadable lines: a withdrawal always works
    if (not unreadable and not any(event["participant"] == participant for event in events)
            and not any(j and j["participant"] == participant for j in pending.values())
            and all(plan_withdrawal(d, participant).empty for d in datasets)):
        where = ", ".join(map(str, datasets)) or "no dataset given"
        raise ConsentError(f"participant {participant!r} has no consent record in "
                           f"{register.directory} and no data in {where}: nothing to withdraw")
    _wait_for_sessions(datasets, participant, register, wait_s, progress)
    entries = []
    for dataset in datasets:
        journal = pending[dataset]
        if journal is not None and journal["participant"] != participant:
            if announce:
                announce(journal_plan(dataset, journal))
            entries.append(_complete(dataset, journal))  # finish the other one first
            journal = None
        journal = journal or _begin(dataset, participant, register)
        if announce:
            announce(journal_plan(dataset, journal))
        entries.append(_complete(dataset, journal))
    register.mark_withdrawn(participant)
    return entries
