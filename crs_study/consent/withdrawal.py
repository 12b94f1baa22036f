"""Withdrawal: a participant's data removed from a dataset, all or nothing, with an audit line.

Withdrawal is all-or-nothing per dataset. A journal naming every path to remove is made
durable first (``DATASET/.crs-study-withdrawal.json``), under the dataset lock and only when no
session of the participant holds its lock; while the journal exists no session may start in
the dataset (:meth:`crs_study.dataset.Dataset.refuse_pending_withdrawal`), so no runner can
write the participant's data back. The register then marks the withdrawal (so the gate refuses
real sessions at once), the paths are renamed into a staging directory, ``participants.tsv``
is rewritten atomically, the staging directory is deleted, the audit line is appended and the
journal is removed. Every step is idempotent, so an interrupted withdrawal is finished by
running it again (or :func:`recover_withdrawal`): the dataset is either as before (journal not
yet written) or, once recovered, fully withdrawn. Files of other participants are never opened
for writing.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import secrets
import shutil
import signal
from collections.abc import Callable, Iterable
from pathlib import Path

from crs_study._files import fsync_dir, write_atomically
from crs_study.consent.register import Register, check_label
from crs_study.dataset import WITHDRAWAL_JOURNAL, Dataset, utc_now
from crs_study.errors import ConsentError

#: Journal of a withdrawal in progress, in the dataset (``crs_study.dataset.WITHDRAWAL_JOURNAL``).
JOURNAL_FILE = WITHDRAWAL_JOURNAL
STAGING_DIR = ".crs-study-withdrawal-staging"
#: Test hook: kill the process at the n-th withdrawal checkpoint (simulates a power cut).
CRASH_ENV = "CRS_STUDY_WITHDRAW_CRASH_AT"
_TEXT_SUFFIXES = {".json", ".tsv", ".md", ".html", ".csv", ".txt", ".jsonl"}


_checkpoints = 0


def _checkpoint() -> None:
    """Crash here when the test hook says so (simulates a power cut mid-withdrawal)."""
    global _checkpoints
    _checkpoints += 1
    target = os.environ.get(CRASH_ENV)
    if target and int(target) == _checkpoints:
        os.kill(os.getpid(), signal.SIGKILL)


def _mentions(path: Path, pattern: re.Pattern[str]) -> bool:
    try:
        return bool(pattern.search(path.read_text(encoding="utf-8", errors="replace")))
    except OSError:
        return False


def participant_paths(dataset: Path, participant: str) -> list[str]:
    """Every path of ``dataset`` holding the participant's data (relative, sorted).

    ``sub-<label>`` directories and files named ``sub-<label>_*`` anywhere in the dataset
    (sessions, ``sourcedata/``, ``derivatives/``), but not inside another dataset nested in
    it (a folder with its own ``dataset_description.json`` outside ``derivatives/``); and
    the group results computed from the participant's data: under ``derivatives/``, every
    text file that mentions the label marks its folder as such. In a pipeline's own folder
    (``derivatives/<pipeline>/``) that means its group outputs (every entry but its
    ``dataset_description.json`` and the other participants' ``sub-*``); deeper down, the
    whole folder. Rerun the analysis afterwards.
    """
    check_label(participant)
    prefix = f"sub-{participant}"
    derivatives = dataset / "derivatives"
    found: set[Path] = set()
    for root, dirs, files in os.walk(dataset):
        root_path = Path(root)
        for name in list(dirs):
            child = root_path / name
            nested = ((child / "dataset_description.json").is_file()
                      and derivatives not in child.parents)
            if name == STAGING_DIR or nested:
                dirs.remove(name)
            elif name == prefix or name.startswith(prefix + "_"):
                found.add(child)
                dirs.remove(name)
        for name in files:
            if name == prefix or name.startswith(prefix + "_") or name.startswith(prefix + "."):
                found.add(root_path / name)
    if derivatives.is_dir():
        token = re.compile(rf"(?<![A-Za-z0-9]){re.escape(participant)}(?![A-Za-z0-9])")
        for path in derivatives.rglob("*"):
            if not (path.is_file() and path.suffix in _TEXT_SUFFIXES
                    and not any(p in found for p in path.parents) and _mentions(path, token)):
                continue
            if path.parent == derivatives:
                found.add(path)
            elif path.parent.parent == derivatives:  # a pipeline's group outputs
                found.update(entry for entry in path.parent.iterdir()
                             if entry.name != "dataset_description.json"
                             and not (entry.name.startswith("sub-") and entry.is_dir()))
            else:
                found.add(path.parent)
    relative = sorted({p.relative_to(dataset) for p in found})
    # drop paths inside another path already listed
    return [str(p) for p in relative if not any(q in p.parents for q in relative)]


def _check_not_running(dataset: Path, participant: str) -> None:
    for lock in (dataset / f"sub-{participant}").rglob("*.lock"):
        with open(lock, "a+") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ConsentError(
                    f"a session of participant {participant!r} is running ({lock}); stop it first"
                ) from None
            fcntl.flock(handle, fcntl.LOCK_UN)


def _write_json_atomically(path: Path, data: dict) -> None:
    write_atomically(path, json.dumps(data, indent=2, sort_keys=True))


def _participant_row(participant: str) -> Callable[[str], bool]:
    return lambda line: line.split("\t", 1)[0].strip() == f"sub-{participant}"


def _without_participant_row(text: str, participant: str) -> str:
    is_row = _participant_row(participant)
    return "".join(line for line in text.splitlines(keepends=True) if not is_row(line))


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


def _remove_stale_temporaries(dataset: Path) -> None:
    """Delete what a withdrawal killed inside an atomic write leaves: the temporary copies
    of the journal (it names the participant) and of participants.tsv. Call under the
    dataset lock, where no other writer of these files can be at work."""
    for name in (JOURNAL_FILE, "participants.tsv"):
        temporary = dataset / f".{name}.tmp"
        if temporary.exists():
            temporary.unlink()
            fsync_dir(dataset)


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


def _begin(dataset: Path, participant: str, register: Register) -> dict:
    """Write the journal under the dataset lock, once no session of the participant runs."""
    with Dataset(dataset).locked():
        _check_not_running(dataset, participant)
        _remove_stale_temporaries(dataset)
        participants = dataset / "participants.tsv"
        listed = participants.exists() and any(
            map(_participant_row(participant),
                participants.read_text(encoding="utf-8").splitlines()))
        journal = {
            "participant": participant, "time": utc_now(),
            "register": str(register.directory.resolve()),
            "paths": participant_paths(dataset, participant),
            "participants_tsv_row": listed, "journal_id": secrets.token_hex(8),
        }
        _write_json_atomically(dataset / JOURNAL_FILE, journal)
    _checkpoint()
    return journal


def _complete(dataset: Path, journal: dict) -> dict:
    participant = journal["participant"]
    register = Register(journal["register"])
    register.mark_withdrawn(participant)  # the gate refuses real sessions from here on
    staging = dataset / STAGING_DIR
    staging.mkdir(exist_ok=True)
    for relative in journal["paths"]:
        source = dataset / relative
        if source.exists() or source.is_symlink():
            target = staging / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            os.rename(source, target)
            _checkpoint()
    participants = dataset / "participants.tsv"
    with Dataset(dataset).locked():  # a runner adding a participant rewrites it too
        if participants.exists():
            text = participants.read_text(encoding="utf-8")
            reduced = _without_participant_row(text, participant)
            if reduced != text:
                write_atomically(participants, reduced)
    _checkpoint()
    shutil.rmtree(staging, ignore_errors=False)
    fsync_dir(dataset)
    _checkpoint()
    entry = {
        "event": "withdrawal", "participant": participant, "time": journal["time"],
        "completed": utc_now(), "dataset": str(dataset.resolve()), "removed": journal["paths"],
        # journals from before this key existed removed the row whenever it was there
        "participants_tsv_row_removed": journal.get("participants_tsv_row", True),
        "journal_id": journal["journal_id"],
    }
    register.audit(entry)
    _checkpoint()
    with Dataset(dataset).locked():
        _remove_stale_temporaries(dataset)
        (dataset / JOURNAL_FILE).unlink()
        fsync_dir(dataset)
    return entry


def withdraw(participant: str, datasets: Iterable[str | Path],
             register_dir: str | Path | None = None) -> list[dict]:
    """Remove every file of ``participant`` from each dataset and mark the record withdrawn.

    Returns one audit entry per dataset: an unfinished withdrawal of another participant
    found in a dataset is finished first and has its own entry. Refused, with nothing
    changed, while a session of the participant runs in any of the datasets, and when the
    participant is neither in the register nor in any dataset (a mistyped label). Safe to
    run again after an interruption.
    """
    check_label(participant)
    register = Register(register_dir)
    datasets = [Path(d) for d in datasets]
    for dataset in datasets:
        _check_dataset(dataset)
        _check_not_running(dataset, participant)
    pending = {d: pending_withdrawal(d) for d in datasets}
    if (not any(event["participant"] == participant for event in register.events())
            and not any(j and j["participant"] == participant for j in pending.values())
            and not any(participant_paths(d, participant) for d in datasets)):
        where = ", ".join(map(str, datasets)) or "no dataset given"
        raise ConsentError(f"participant {participant!r} has no consent record in "
                           f"{register.directory} and no data in {where}: nothing to withdraw")
    entries = []
    for dataset in datasets:
        journal = pending[dataset]
        if journal is not None and journal["participant"] != participant:
            entries.append(_complete(dataset, journal))  # finish the other one first
            journal = None
        entries.append(_complete(dataset, journal or _begin(dataset, participant, register)))
    register.mark_withdrawn(participant)
    return entries
