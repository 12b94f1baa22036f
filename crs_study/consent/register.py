"""The consent register: consent and withdrawal events, kept outside every dataset.

The **register** is a directory kept outside every dataset (owner-only: 0700, files 0600)::

    register.jsonl   one JSON object per event: {"event": "consent" | "withdrawal", ...}
    audit.jsonl      one line per completed withdrawal: label, time, what was removed

Consent events hold the participant's pseudonymous label, the UTC time, the form's path,
version and sha256, the experimenter's initials and, only when the lab chooses, a name. Names
never leave the register: datasets hold labels alone.

A register inside a dataset (any folder with a ``dataset_description.json`` above it) is
refused: names would travel with the data.

A label has one current consent: a second consent event for it is refused unless it says it
renews the first (``renew``: a new form version, a changed name); the earlier events are kept
and :attr:`ConsentRecord.earlier` lists them.

Damage. Each event is appended with one ``write``, so a power cut during ``consent record``
can leave a torn last line (no newline). Before anything is appended, and by every consent
command, a torn last line is repaired as a session's trial file is
(:meth:`Register.repair`): its bytes are kept aside in ``register-torn-<time>.bin`` (0600)
and the repair is reported; a withdrawal it held is completed, never lost. Any other line
that is not an event fails closed where consent is granted (the gate, ``record``: an
unreadable line might be a withdrawal), while a withdrawal, and ``list``, go past it, naming
it in a warning: a participant's withdrawal must always be possible.

The gate before a real session is :mod:`crs_study.consent.gate`; withdrawal, which marks the
register and removes the participant's data, is :mod:`crs_study.consent.withdrawal`.
"""

from __future__ import annotations

import glob
import json
import os
import re
import secrets
import stat
import string
import warnings
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from crs_study._files import append_durably, cut_tail, fsync_dir, os_errors
from crs_study.consent.form import ConsentForm
from crs_study.dataset import check_label as dataset_check_label
from crs_study.dataset import is_simulated_label, utc_now
from crs_study.errors import ConsentError, CrsStudyWarning, SessionError

REGISTER_ENV = "CRS_STUDY_CONSENT_DIR"
REGISTER_FILE = "register.jsonl"
AUDIT_FILE = "audit.jsonl"

_INITIALS_RE = re.compile(r"^[A-Za-z]{1,4}$")
#: Keys a consent event must have (besides ``event`` and ``participant``).
_CONSENT_KEYS = ("time", "form_path", "form_version", "form_sha256", "experimenter")
_LABEL_ALPHABET = string.ascii_lowercase + string.digits
#: The start of a withdrawal event as :meth:`Register._append` writes it (keys sorted): a torn
#: line that begins so names whose withdrawal a power cut interrupted.
_TORN_WITHDRAWAL = re.compile(rb'^\{"event": "withdrawal", "participant": "([A-Za-z0-9]+)"')


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


def check_person_label(label: str) -> str:
    """A person's label: BIDS-valid and outside the simulated participants' label space
    (``sim...``, :func:`crs_study.dataset.is_simulated_label`), so a person can never be
    taken for a simulated participant and pass no gate."""
    check_label(label)
    if is_simulated_label(label):
        raise ConsentError(f"participant label {label!r} begins with 'sim', which is reserved "
                           "for simulated participants; give a person another label (or none: "
                           "one is generated, e.g. p7k2m9q)")
    return label


def _withdrawal_time(event: dict, line: int) -> str:
    """The time a withdrawal event gives, or words saying it is unknown: a null or malformed
    time still withdraws (it must never reopen the gate)."""
    value = event.get("time")
    if isinstance(value, str):
        try:
            datetime.fromisoformat(value)
            return value
        except ValueError:
            pass
    return f"an unknown time (register line {line} gives {value!r})"


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
    #: the consent events this one renewed, oldest first (kept in the register, never lost)
    earlier: tuple[ConsentRecord, ...] = ()

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
        for message in self.repair(path):
            warnings.warn(message, CrsStudyWarning, stacklevel=3)
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

    def repair(self, path: Path | None = None) -> list[str]:
        """Repair a torn last line of ``path`` (default the register file); what was done.

        A last line without its newline that is a whole event gets the newline; any other
        torn tail (or a last line holding NUL bytes, as a power cut can leave) is kept aside
        in ``<name>-torn-<time>.bin`` beside it, durably, before the file is cut back to its
        whole lines. A torn withdrawal is then appended again whole (its label is at the start
        of the line), so the cut never reopens the gate.
        """
        path = self.path if path is None else path
        self._check_outside_datasets()
        try:
            data = path.read_bytes() if path.is_file() else b""
        except OSError as exc:
            raise ConsentError(f"{path}: cannot read the consent register: {exc}") from None
        keep = data.rfind(b"\n", 0, len(data) - 1) + 1 if data.endswith(b"\n") \
            else data.rfind(b"\n") + 1
        tail = data[keep:]
        if not tail or (tail.endswith(b"\n") and b"\x00" not in tail):
            return []
        if b"\x00" not in tail and _event_problem(_parsed(tail)) is None:
            with os_errors(ConsentError, "repair the consent register", path):
                append_durably(path, b"\n", mode=0o600)
            return [f"{path}: its last line lacked its newline (cut by an interruption); "
                    "the newline was added, the event is whole"]
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        backup = path.with_name(f"{path.stem}-torn-{stamp}.bin")
        with os_errors(ConsentError, "repair the consent register", path):
            cut_tail(path, data, keep, backup, mode=0o600,
                     backups=f"{glob.escape(path.stem)}-torn-*.bin")
        line = data[:keep].count(b"\n") + 1
        said = (f"{path}:{line}: a torn last line ({len(tail)} bytes, cut off mid-write, as "
                f"by a power cut) was set aside in {backup}")
        withdrawn = _TORN_WITHDRAWAL.match(tail)
        if path == self.path and withdrawn:
            label = withdrawn.group(1).decode()
            self._append(path, {"event": "withdrawal", "participant": label,
                                "time": utc_now(), "repaired": True})
            return [f"{said}; it was the withdrawal of {label}, now recorded whole"]
        return [f"{said}; the event it held was not recorded: if it was a consent, record "
                "it again"]

    def scan(self) -> tuple[list[dict], list[str]]:
        """Every event of the register (each with its ``_line``), and one message per line
        that is not an event."""
        self._check_outside_datasets()
        if not self.path.exists():
            return [], []
        self._restore_privacy()
        events, unreadable = [], []
        try:
            text = self.path.read_bytes().decode("utf-8", "replace")
        except OSError as exc:
            raise ConsentError(f"{self.path}: cannot read the consent register: {exc}"
                               ) from None
        for number, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            event = _parsed(line)
            problem = _event_problem(event)
            if problem:
                unreadable.append(f"{self.path}:{number}: not a consent register line "
                                  f"({problem}): {line[:60]!r}")
                continue
            events.append({**event, "_line": number})
        return events, unreadable

    def events(self, *, past_unreadable: bool = False) -> list[dict]:
        """The register's events. A line that is not one fails closed (a one-line
        :class:`ConsentError`: it might be a withdrawal), unless ``past_unreadable`` (a
        withdrawal, a listing): then each such line is a warning naming it."""
        events, unreadable = self.scan()
        if unreadable and not past_unreadable:
            raise ConsentError(f"{unreadable[0]}; no consent is granted from a damaged "
                               "register (a withdrawal still works): a torn last line is "
                               "set aside by any crs-study consent command (e.g. list), "
                               "another is repaired by hand or from a backup")
        for message in unreadable:
            warnings.warn(f"{message}; left out", CrsStudyWarning, stacklevel=3)
        return events

    def stamp(self) -> tuple[int, int, int] | None:
        """What changes whenever the register file does: inode, size, modification time
        (None when it is missing). A stat, so a session can look before every trial."""
        try:
            info = os.stat(self.path)
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise ConsentError(f"{self.path}: cannot read the consent register: {exc}"
                               ) from None
        return (info.st_ino, info.st_size, info.st_mtime_ns)

    def withdrawn(self, *, past_unreadable: bool = False) -> dict[str, str]:
        """Label -> when it was withdrawn, for every withdrawal event (also of labels without a
        consent record); a withdrawal is final whatever follows it in the register."""
        found: dict[str, str] = {}
        for event in self.events(past_unreadable=past_unreadable):
            if event["event"] == "withdrawal":
                found.setdefault(event["participant"], _withdrawal_time(event, event["_line"]))
        return found

    def records(self, *, past_unreadable: bool = False) -> dict[str, ConsentRecord]:
        """The current record per participant (a later consent renews an earlier one, which
        it keeps in ``earlier``; a withdrawal is final: no consent event after it, and no
        time it lacks, reopens it)."""
        records: dict[str, ConsentRecord] = {}
        events = self.events(past_unreadable=past_unreadable)
        for event in events:
            if event["event"] == "consent":
                label = event["participant"]
                before = records.get(label)
                earlier = () if before is None else (*before.earlier, before)
                records[label] = ConsentRecord(
                    label, event["time"], event["form_path"], event["form_version"],
                    event["form_sha256"], event["experimenter"], event.get("name"),
                    earlier=earlier)
        withdrawn: dict[str, str] = {}
        for event in events:
            if event["event"] == "withdrawal":
                withdrawn.setdefault(event["participant"],
                                     _withdrawal_time(event, event["_line"]))
        for label, when in withdrawn.items():
            if label in records:
                records[label] = ConsentRecord(**{**asdict(records[label]), "withdrawn_at": when})
        return records

    def record(self, form: ConsentForm, experimenter: str, participant: str | None = None,
               name: str | None = None, *, renew: bool = False) -> ConsentRecord:
        """Store a consent event; a label is generated when none is given. A label with a
        consent already is refused unless ``renew`` (the new event replaces the current one,
        which stays in the register and in :attr:`ConsentRecord.earlier`)."""
        if not _INITIALS_RE.match(experimenter or ""):
            raise ConsentError(
                f"experimenter initials {experimenter!r} are not valid: 1 to 4 letters"
            )
        for message in self.repair():
            warnings.warn(message, CrsStudyWarning, stacklevel=2)
        records = self.records()
        withdrawn = self.withdrawn()
        if participant is None:
            participant = generate_label({*records, *withdrawn})
        check_person_label(participant)
        if participant in withdrawn:
            raise ConsentError(
                f"participant {participant!r} withdrew on {withdrawn[participant]}; "
                "give a returning person a new label"
            )
        current = records.get(participant)
        if current is not None and not renew:
            raise ConsentError(
                f"participant {participant!r} already consented on {current.time} (form "
                f"version {current.form_version}, experimenter {current.experimenter}); to "
                "replace that record (a new form version, a corrected name) say so with "
                "--renew (the first stays in the register's history), or give another "
                "person a new label")
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
        """Append a withdrawal of ``participant`` (once), past any unreadable line."""
        for message in self.repair():
            warnings.warn(message, CrsStudyWarning, stacklevel=2)
        if participant in self.withdrawn(past_unreadable=True):
            return  # idempotent (also for a simulated participant with no consent record)
        self._append(self.path, {"event": "withdrawal", "participant": participant,
                                 "time": utc_now()})

    def audit(self, entry: dict) -> None:
        for message in self.repair(self.audit_path):
            warnings.warn(message, CrsStudyWarning, stacklevel=2)
        if self.audit_path.exists() and any(
            isinstance(line := _parsed(text), dict)
            and line.get("journal_id") == entry["journal_id"]
            for text in self.audit_path.read_bytes().decode("utf-8", "replace").splitlines()
        ):
            return  # idempotent
        self._append(self.audit_path, entry)


#: The keys each kind of register line must carry, as strings ("name" is optional; a
#: withdrawal without a time is still final, see :meth:`Register.withdrawn`).
EVENT_KEYS = {"consent": ("participant", *_CONSENT_KEYS), "withdrawal": ("participant",)}


def _parsed(line: str | bytes) -> object:
    """The JSON value of one line (None when it is not JSON, or nested too deeply)."""
    try:
        return json.loads(line)
    except (ValueError, RecursionError):
        return None


def _event_problem(event: object) -> str | None:
    """Why ``event`` is not a register line (None when it is)."""
    if not isinstance(event, dict):
        return "expected a JSON object"
    kind = event.get("event")
    if kind not in EVENT_KEYS:
        return f"'event' must be one of {', '.join(EVENT_KEYS)}, got {kind!r}"
    missing = [k for k in EVENT_KEYS[kind] if not isinstance(event.get(k), str)]
    if missing:
        return f"a {kind} line needs the key {missing[0]!r} (a string)"
    return None
