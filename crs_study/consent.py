"""Consent records, the gate before real sessions, and withdrawal.

The **register** is a directory kept outside every dataset (owner-only: 0700, files 0600)::

    register.jsonl   one JSON object per event: {"event": "consent" | "withdrawal", ...}
    audit.jsonl      one line per completed withdrawal: label, time, what was removed

Consent events hold the participant's pseudonymous label, the UTC time, the form's path,
version and sha256, the experimenter's initials and, only when the lab chooses, a name. Names
never leave the register: datasets hold labels alone.

A register inside a dataset (any folder with a ``dataset_description.json`` above it) is
refused: names would travel with the data.

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
import stat
import string
import warnings
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

from crs_study._files import append_durably, fsync_dir, os_errors, write_atomically
from crs_study.consent_form import ConsentForm, read_form  # noqa: F401  (re-exported)
from crs_study.dataset import WITHDRAWAL_JOURNAL, Dataset, utc_now
from crs_study.dataset import check_label as dataset_check_label
from crs_study.errors import ConsentError, CrsStudyWarning, SessionError

REGISTER_ENV = "CRS_STUDY_CONSENT_DIR"
REGISTER_FILE = "register.jsonl"
AUDIT_FILE = "audit.jsonl"
JOURNAL_FILE = WITHDRAWAL_JOURNAL
STAGING_DIR = ".crs-study-withdrawal-staging"
#: Test hook: kill the process at the n-th withdrawal checkpoint (simulates a power cut).
CRASH_ENV = "CRS_STUDY_WITHDRAW_CRASH_AT"

_INITIALS_RE = re.compile(r"^[A-Za-z]{1,4}$")
_LABEL_ALPHABET = string.ascii_lowercase + string.digits
_TEXT_SUFFIXES = {".json", ".tsv", ".md", ".html", ".csv", ".txt", ".jsonl"}


def default_register_dir() -> Path:
    """``$CRS_STUDY_CONSENT_DIR``, else ``~/.crs-study/consent``."""
    return Path(os.environ.get(REGISTER_ENV) or Path.home() / ".crs-study" / "consent")


def enclosing_dataset(path: str | Path) -> Path | None:
    """The dataset (a folder with ``dataset_description.json``) holding ``path``, or None."""
    resolved = Path(path).resolve()
    for folder in (resolved, *resolved.parents):
        if (folder / "dataset_description.json").is_file():
            return folder
    return None


def check_label(label: str) -> str:
    """A participant label must be BIDS-valid: letters and digits only (as in the dataset)."""
    try:
        return dataset_check_label(label)
    except SessionError as error:
        raise ConsentError(str(error)) from None


def generate_label(existing: Iterable[str] = (), length: int = 7) -> str:
    """A random pseudonymous label such as ``p7k2m9q`` (a letter, then letters and digits)."""
    taken = set(existing)
    while True:
        label = "p" + "".join(secrets.choice(_LABEL_ALPHABET) for _ in range(length - 1))
        if label not in taken:
            return label


@dataclass(frozen=True)
class ConsentRecord:
    """The current consent state of one participant, folded from the register's events."""

    participant: str
    time: str
    form_path: str
    form_version: str
    form_sha256: str
    experimenter: str
    name: str | None = None
    withdrawn_at: str | None = None

    @property
    def status(self) -> str:
        return "withdrawn" if self.withdrawn_at else "consented"


class Register:
    """The consent register directory (see the module docstring)."""

    def __init__(self, directory: str | Path | None = None) -> None:
        self.directory = Path(directory) if directory else default_register_dir()
        self.path = self.directory / REGISTER_FILE
        self.audit_path = self.directory / AUDIT_FILE

    def _check_outside_datasets(self) -> None:
        dataset = enclosing_dataset(self.directory)
        if dataset is not None:
            raise ConsentError(
                f"{self.directory}: the consent register lies inside the dataset {dataset}; "
                "keep it outside every dataset (names must never travel with the data)")

    def _ensure(self) -> None:
        self._check_outside_datasets()
        try:
            self.directory.mkdir(mode=0o700, parents=True, exist_ok=True)
            os.chmod(self.directory, 0o700)
        except OSError as exc:
            raise ConsentError(f"{self.directory}: cannot create the consent register: {exc}"
                               ) from None

    def _append(self, path: Path, event: dict) -> None:
        self._ensure()
        with os_errors(ConsentError, "write the consent register", path):
            new = not path.exists()
            append_durably(path, json.dumps(event, sort_keys=True).encode("utf-8") + b"\n",
                           mode=0o600)
            os.chmod(path, 0o600)
            if new:
                fsync_dir(path.parent)

    def _restore_privacy(self) -> None:
        """Owner-only permissions back on the register (0700) and its files (0600), with a
        warning that names what others could read: a copy restored from a backup or a chmod
        must not leave names readable by the group."""
        for path, mode in ((self.directory, 0o700), (self.path, 0o600),
                           (self.audit_path, 0o600)):
            try:
                current = stat.S_IMODE(path.stat().st_mode)
            except FileNotFoundError:
                continue
            if current & 0o077:
                try:
                    os.chmod(path, mode)
                except OSError as exc:
                    raise ConsentError(f"{path}: readable by others (mode {current:o}) and "
                                       f"cannot be made owner-only: {exc}") from None
                warnings.warn(f"{path} was readable by others (mode {current:o}); made "
                              f"owner-only ({mode:o}) again", CrsStudyWarning, stacklevel=3)

    def events(self) -> list[dict]:
        self._check_outside_datasets()
        if not self.path.exists():
            return []
        self._restore_privacy()
        events = []
        try:
            text = self.path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConsentError(f"{self.path}: cannot read the consent register: {exc}"
                               ) from None
        for number, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            try:
                event = json.loads(line)
                event["event"], event["participant"]  # noqa: B018  (required keys)
            except (json.JSONDecodeError, KeyError, TypeError):
                raise ConsentError(f"{self.path}:{number}: not a consent register line: "
                                   f"{line[:60]!r}") from None
            events.append(event)
        return events

    def records(self) -> dict[str, ConsentRecord]:
        """The current record per participant (a later consent replaces an earlier one)."""
        records: dict[str, ConsentRecord] = {}
        for event in self.events():
            label = event["participant"]
            if event["event"] == "consent":
                records[label] = ConsentRecord(
                    label, event["time"], event["form_path"], event["form_version"],
                    event["form_sha256"], event["experimenter"], event.get("name"),
                )
            elif event["event"] == "withdrawal" and label in records:
                old = records[label]
                records[label] = ConsentRecord(**{**asdict(old), "withdrawn_at": event["time"]})
        return records

    def record(self, form: ConsentForm, experimenter: str, participant: str | None = None,
               name: str | None = None) -> ConsentRecord:
        """Store a consent event; a label is generated when none is given."""
        if not _INITIALS_RE.match(experimenter or ""):
            raise ConsentError(
                f"experimenter initials {experimenter!r} are not valid: 1 to 4 letters"
            )
        records = self.records()
        if participant is None:
            participant = generate_label(records)
        check_label(participant)
        if participant in records and records[participant].withdrawn_at:
            raise ConsentError(
                f"participant {participant!r} withdrew on {records[participant].withdrawn_at}; "
                "give a returning person a new label"
            )
        event = {
            "event": "consent", "participant": participant, "time": utc_now(),
            "form_path": str(form.path), "form_version": form.version,
            "form_sha256": form.sha256, "experimenter": experimenter.upper(),
        }
        if name:
            event["name"] = name
        self._append(self.path, event)
        return self.records()[participant]

    def mark_withdrawn(self, participant: str) -> None:
        if any(e["event"] == "withdrawal" and e["participant"] == participant
               for e in self.events()):
            return  # idempotent (also for a simulated participant with no consent record)
        self._append(self.path, {"event": "withdrawal", "participant": participant,
                                 "time": utc_now()})

    def audit(self, entry: dict) -> None:
        if self.audit_path.exists() and any(
            json.loads(line).get("journal_id") == entry["journal_id"]
            for line in self.audit_path.read_text(encoding="utf-8").splitlines() if line
        ):
            return  # idempotent
        self._append(self.audit_path, entry)


def require_consent(register_dir: str | Path | None, participant: str, form_version: str,
                    form: ConsentForm | None = None) -> ConsentRecord:
    """The gate before a real session: a current consent on ``form_version`` or a refusal.

    With ``form`` (the protocol's consent form) the consent must also be on that very text
    (same sha256): a form edited without a new version is refused, not silently accepted.
    """
    register = Register(register_dir)
    record = register.records().get(participant)
    if record is None:
        raise ConsentError(
            f"no consent record for participant {participant!r} in {register.directory}; "
            f"record it first: crs-study consent record --participant {participant} "
            f"--form FORM --experimenter INITIALS"
        )
    if record.withdrawn_at:
        raise ConsentError(
            f"participant {participant!r} withdrew consent on {record.withdrawn_at}; "
            "no session may run"
        )
    if record.form_version != form_version:
        raise ConsentError(
            f"participant {participant!r} consented to form version {record.form_version!r}, "
            f"the protocol needs version {form_version!r}; record consent on the current form"
        )
    if form is not None and record.form_sha256 != form.sha256:
        raise ConsentError(
            f"participant {participant!r} consented on a form whose text differs from "
            f"{form.path} (sha256 {record.form_sha256[:12]} vs {form.sha256[:12]}, both "
            f"version {form_version!r}); give a changed form a new version and record "
            "consent on it")
    return record


# --- withdrawal ---------------------------------------------------------------------------

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
