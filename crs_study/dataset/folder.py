"""The stored dataset's folder: BIDS ``beh``, its shared files and its participants.

Layout (docs/architecture.md, "The stored dataset"; every path is built by
:mod:`crs_study.dataset.bids`)::

    DATASET/
      dataset_description.json, participants.tsv, participants.json, task-<task>_beh.json
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.tsv    one row per trial
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.json   session sidecar
      sub-<id>/ses-<n>/.sub-<id>_ses-<n>.lock                       the runner's lock
      sourcedata/sub-<id>/ses-<n>/..._frames.tsv.gz                 per-frame device log
      sourcedata/sub-<id>/ses-<n>/..._beh-torn-<time>.bin           bytes cut from a torn tail

The sidecar is a :class:`~crs_study.dataset.session_metadata.SessionMetadata`, read strictly.
The task is the stimulus set's (``digitid`` for digits, ``letterid`` for the letters); a
dataset may hold sessions of several sets, each task with its own column dictionary.

Written trial by trial so that nothing is ever lost: one session's files are
:class:`~crs_study.dataset.session_store.SessionStore`'s (durability, torn tails, the session
lock). This module holds what the whole dataset shares: ``dataset_description.json``,
``participants.tsv`` (the order of arrival, under the dataset lock), the column dictionary
and the README.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import re
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from crs_study import __version__
from crs_study._files import make_dirs, os_errors, write_atomically
from crs_study.dataset import bids, schema
from crs_study.dataset.bids import SessionPaths
from crs_study.dataset.schema import DEFAULT_TASK, Task, tsv_line
from crs_study.errors import DatasetError, SessionError

BIDS_VERSION = "1.10.0"
DATASET_LOCK = ".crs-study.lock"
#: Journal of a participant's withdrawal in progress (crs_study.consent); while it exists no
#: session may start in the dataset.
WITHDRAWAL_JOURNAL = ".crs-study-withdrawal.json"
#: How many participants ever arrived in the dataset (no labels: a withdrawal must not leave
#: the withdrawn participant's label behind); the next participant's default counterbalance.
ARRIVALS_FILE = ".crs-study-arrivals.json"
#: Labels of simulated participants begin with this, in any case (``sim01``); a person's label
#: never does (:func:`is_simulated_label`; the consent register refuses such labels).
SIMULATED_LABEL_PREFIX = "sim"
#: The labels of crs_study.power's simulated studies (``r<seed>s<study>p<NN>``, made before
#: the ``sim`` space existed; its fixtures are drawn from them): simulated too.
_POWER_LABEL = re.compile(r"r[0-9]+s[0-9]+p[0-9]+")
PARTICIPANT_COLUMNS = ("participant_id", "counterbalance")
PARTICIPANTS_SIDECAR = {
    "participant_id": {"Description": "Pseudonymous participant label (never a name)"},
    "counterbalance": {
        "Description": "Counterbalancing index: the participant's 0-based order of arrival in "
        "the dataset (or as set with --counterbalance); the protocol maps it to the order of "
        "the condition blocks",
        "Units": "index",
    },
}
_LABEL_RE = re.compile(r"[A-Za-z0-9]+")


def check_label(label: str) -> str:
    """BIDS participant labels: letters and digits only."""
    if not isinstance(label, str) or not _LABEL_RE.fullmatch(label):
        raise SessionError(f"participant label {label!r} is not valid: use letters and digits "
                           "only (BIDS), e.g. p7k2m9q")
    return label


def dataset_dir(value: str | os.PathLike[str], option: str = "--out") -> Path:
    """A dataset folder as the user gave it; an empty name (``--out ''``, which ``Path``
    would take for the current folder) is a one-line :class:`DatasetError`."""
    if not os.fspath(value).strip():
        raise DatasetError(f"{option}: expected a folder, got {os.fspath(value)!r} (which "
                           "would mean the current folder); name one (it is created when "
                           "missing), e.g. --out study")
    return Path(value)


def is_simulated_label(label: str) -> bool:
    """Whether ``label`` is in the simulated participants' label space (``sim...``, any case,
    and power's ``r<seed>s<study>p<NN>``).

    The two label spaces never meet: a simulated participant (a dry-run's ``sim01``) is
    never a person, so such a session needs no consent, and a person's label (any other) is
    gated by consent on every device (:mod:`crs_study.consent.gate`).
    """
    return isinstance(label, str) and (
        label[:len(SIMULATED_LABEL_PREFIX)].lower() == SIMULATED_LABEL_PREFIX
        or _POWER_LABEL.fullmatch(label) is not None)


def utc_now() -> str:
    """The current time, ISO 8601 in UTC, to the second."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def json_text(data: Any) -> str:
    return json.dumps(data, indent=2, ensure_ascii=False) + "\n"


# --- the dataset -------------------------------------------------------------------------------

class Dataset:
    """A BIDS dataset directory: top-level files, participants, sessions.

    ``task`` is the task (the stimulus set) of the sessions this writer adds (the default
    task, digits, when None): it names their files and the column dictionary :meth:`ensure`
    writes; ``name`` (default ``crs-study <the task's title>``) goes to a new
    ``dataset_description.json``."""

    def __init__(self, root: str | Path, name: str | None = None, task: Task | None = None
                 ) -> None:
        self.root = Path(root)
        self.task = task if task is not None else DEFAULT_TASK
        self.name = name if name is not None else f"crs-study {self.task.title}"

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the dataset-wide lock (short updates of shared files such as participants)."""
        if self.root.exists() and not self.root.is_dir():
            raise DatasetError(f"{self.root}: exists and is not a directory")
        with os_errors(DatasetError, "create the dataset", self.root):
            make_dirs(self.root)
            handle = open(self.root / DATASET_LOCK, "a+")  # noqa: SIM115 - closed below
        with handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    def refuse_pending_withdrawal(self) -> None:
        """A :class:`SessionError` while a withdrawal is unfinished (call under :meth:`locked`).

        Withdrawal writes its journal under the same lock, so a session either holds its lock
        before the journal exists (and the withdrawal waits for it) or never starts.
        """
        if (self.root / WITHDRAWAL_JOURNAL).exists():
            raise SessionError(
                f"{self.root}: a participant's withdrawal was interrupted; no session may run "
                f"until it is finished: crs-study consent recover --dataset {self.root}")

    def ensure(self) -> None:
        """Create the top-level files that are missing (never rewrites existing ones)."""
        if self.root.exists() and not self.root.is_dir():
            raise DatasetError(f"{self.root}: exists and is not a directory")
        with self.locked():
            self.refuse_pending_withdrawal()
            files = {
                bids.DATASET_DESCRIPTION: json_text({
                    "Name": self.name,
                    "BIDSVersion": BIDS_VERSION,
                    "DatasetType": "raw",
                    "GeneratedBy": [{
                        "Name": "crs-study",
                        "Version": __version__,
                        "Description": f"CRS haptic display {self.task.title} sessions",
                    }],
                }),
                bids.PARTICIPANTS_JSON: json_text(PARTICIPANTS_SIDECAR),
                bids.task_sidecar_name(self.task.label): json_text(column_dictionary(self.task)),
                bids.PARTICIPANTS_TSV: "\t".join(PARTICIPANT_COLUMNS) + "\n",
                bids.DATASET_README: DATASET_README,
            }
            for name, text in files.items():
                if not (self.root / name).exists():
                    with os_errors(DatasetError, "write", self.root / name):
                        write_atomically(self.root / name, text)

    def participants(self) -> dict[str, int]:
        """Label -> counterbalance index, from ``participants.tsv``."""
        path = self.root / bids.PARTICIPANTS_TSV
        if not path.exists():
            return {}
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: cannot read the participants table: {exc}") from None
        rows = list(csv.reader(io.StringIO(text), delimiter="\t"))
        if not rows or tuple(rows[0][:2]) != PARTICIPANT_COLUMNS:
            raise DatasetError(f"{path}: expected columns {PARTICIPANT_COLUMNS}, got "
                               f"{rows[0] if rows else []!r}")
        found = {}
        for number, row in enumerate(rows[1:], start=2):
            if not row:
                continue
            try:
                label = row[0].removeprefix("sub-")
                found[label] = int(row[1])
            except (IndexError, ValueError):
                raise DatasetError(f"{path}:{number}: malformed row {row!r}") from None
        return found

    def arrivals(self, known: dict[str, int] | None = None) -> int:
        """How many participants ever arrived in the dataset, withdrawn ones included.

        Kept in :data:`ARRIVALS_FILE` (a count, no labels). A dataset written before the file
        existed counts its participants, or one past the largest index stored when that is
        more (a withdrawal there left a gap, and the count alone would repeat an index).
        """
        known = self.participants() if known is None else known
        legacy = max(len(known), max(known.values(), default=-1) + 1)
        path = self.root / ARRIVALS_FILE
        if not path.exists():
            return legacy
        try:
            count = json.loads(path.read_text(encoding="utf-8"))["arrivals"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DatasetError(f"{path}: unreadable count of arrivals ({exc}); expected "
                               '{"arrivals": N}') from None
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise DatasetError(f"{path}: expected a whole number of arrivals, got {count!r}")
        return max(count, len(known))

    def next_counterbalance(self) -> int:
        """The counterbalance index the next new participant gets by default: the 0-based
        order of arrival (:meth:`arrivals`), never the count of rows, which a withdrawal
        lowers so that the next participant would repeat an index in use."""
        return self.arrivals()

    def register_participant(self, label: str, counterbalance: int | None = None) -> int:
        """The participant's counterbalance index, adding the participant when new.

        A new participant gets ``counterbalance`` when given, else its 0-based order of
        arrival (:meth:`next_counterbalance`). A known participant keeps the index stored;
        asking for another one is a :class:`SessionError`.
        """
        check_label(label)
        self.ensure()
        with self.locked():
            self.refuse_pending_withdrawal()
            known = self.participants()
            if label in known:
                if counterbalance is not None and counterbalance != known[label]:
                    raise SessionError(
                        f"participant {label!r} has counterbalance {known[label]} in "
                        f"{self.root / bids.PARTICIPANTS_TSV}; --counterbalance "
                        f"{counterbalance} disagrees")
                return known[label]
            arrived = self.arrivals(known)
            index = arrived if counterbalance is None else int(counterbalance)
            if index < 0:
                raise SessionError(f"counterbalance must be >= 0, got {index!r}")
            known[label] = index
            with os_errors(DatasetError, "write", self.root / ARRIVALS_FILE):
                write_atomically(self.root / ARRIVALS_FILE,
                                 json.dumps({"arrivals": arrived + 1}) + "\n")
            lines = ["\t".join(PARTICIPANT_COLUMNS) + "\n"]
            lines += [tsv_line([f"sub-{k}", v]) for k, v in sorted(known.items())]
            with os_errors(DatasetError, "write", self.root / bids.PARTICIPANTS_TSV):
                write_atomically(self.root / bids.PARTICIPANTS_TSV, "".join(lines))
            return index

    def session_paths(self, participant: str, session: int) -> SessionPaths:
        """Where a session of this writer's set (its task) lives."""
        check_label(participant)
        if not isinstance(session, int) or session < 1:
            raise SessionError(f"session must be a whole number >= 1, got {session!r}")
        return SessionPaths(self.root, participant, session, self.task.label)

    def sessions(self, participant: str) -> list[int]:
        """Session numbers of a participant found in the dataset."""
        return bids.session_numbers(self.root, check_label(participant))


_LEVEL_TEXT = {
    "0|1": {"0": "no", "1": "yes"},
    "practice|test": {"practice": "practice trial, with feedback, not analysed",
                      "test": "test trial"},
}


def column_dictionary(task: Task = DEFAULT_TASK) -> dict[str, Any]:
    """The BIDS column dictionary (``task-<task>_beh.json``) of a task's sessions, from
    :mod:`crs_study.dataset.schema`.

    Closed sets become ``Levels`` (an object level -> meaning, as BIDS requires): the symbol
    and response columns' levels are the set's symbols (``"7": "the digit 7"``); numeric
    columns get ``Units``; free labels (condition, responder) only a description. The level
    columns (:func:`crs_study.dataset.schema.level_columns`) are described too: the file is
    one per task, and only sessions of protocols with ``[levels]`` hold them. ``TaskName``,
    ``TaskDescription`` and ``Instructions`` are the task's.
    """
    levels = {**_LEVEL_TEXT, schema.SYMBOLS: {s: f"the {task.noun} {s}" for s in task.symbols}}
    columns: dict[str, Any] = {}
    described = {**schema.trial_column_docs(task), **schema.level_columns(task),
                 **schema.ADAPTIVE_COLUMNS}
    for name, (description, units) in described.items():
        entry: dict[str, Any] = {"LongName": name.replace("_", " "), "Description": description}
        if units in levels:
            entry["Levels"] = levels[units]
        elif units != "label":
            entry["Units"] = units
        columns[name] = entry
    return {"TaskName": task.label, "TaskDescription": task.description,
            "Instructions": task.instructions, **columns}


DATASET_README = """\
# crs-study dataset

Identification sessions (digits, letters or another stimulus set: the task of each file) on
the continuity reinforcement skeleton (CRS) haptic display, written by crs-study (BIDS,
datatype beh). One row per trial in sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.tsv;
task-<task>_beh.json describes its columns; the session's protocol, device file, seed and
status are in the .json beside it; per-frame device logs are under sourcedata/. Participant
labels are pseudonyms; names are never stored here.
"""
