"""The stored dataset: BIDS ``beh``, written trial by trial so that nothing is ever lost.

Layout (DESIGN.md, "The stored dataset"; every path is built by :mod:`crs_study.bids`)::

    DATASET/
      dataset_description.json, participants.tsv, participants.json, task-digitid_beh.json
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-digitid_beh.tsv    one row per trial
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-digitid_beh.json   session sidecar
      sub-<id>/ses-<n>/.sub-<id>_ses-<n>.lock                       the runner's lock
      sourcedata/sub-<id>/ses-<n>/..._frames.tsv.gz                 per-frame device log
      sourcedata/sub-<id>/ses-<n>/..._beh-torn-<time>.bin           bytes cut from a torn tail

The sidecar is a :class:`~crs_study.session_metadata.SessionMetadata`, read strictly.

Durability (the order matters): a trial's frames are appended to the session's frame log as
one gzip member with a single ``write`` and fsynced; then its row is appended to the
``_beh.tsv`` the same way; then the sidecar is rewritten atomically (temporary file, fsync,
``os.replace``; the directory is fsynced at the start and the end of a session). The TSV is
the authority on which trials are done; the sidecar may lag it after a crash and is brought
up to date on resume. ``crs-study run`` fsyncs after every trial; dry-runs
(``durable=False``, a documented choice: a seed regenerates them) fsync each session once,
when it stops, and keep every write atomic and ordered, so a killed dry-run loses nothing.

A session whose sidecar says ``complete`` is never written again: resuming it checks the
TSV against the recorded ``TrialsSha256`` without changing a byte, and a mismatch is a
one-line :class:`~crs_study.errors.SessionError`. Failures of the operating system (disk
full, permission denied) are one-line :class:`~crs_study.errors.DatasetError` s naming the
file; an append cut short by a full disk is cut back, so the file keeps whole rows only.

A process killed in the middle of an append can leave a torn last line (no newline, or fewer
fields than the header). :meth:`SessionStore.recover_rows` cuts it off, keeps the cut bytes
under ``sourcedata/`` and fsyncs, so the trial is rerun, never duplicated. A malformed line
anywhere else is a :class:`~crs_study.errors.DatasetError` (the file was edited by hand).

The lock is ``fcntl.flock`` on a hidden file beside the session: the kernel drops it when the
process dies, so a crash never leaves a stale lock, and a second runner on the same session
is refused with a one-line :class:`~crs_study.errors.SessionError`.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import gzip
import hashlib
import io
import json
import math
import os
import re
import zlib
from collections.abc import Iterator, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from crs_study import __version__, bids, schema
from crs_study._files import (  # noqa: F401  (re-exported: older imports)
    append_durably,
    fsync_dir,
    fsync_path,
    make_dirs,
    os_errors,
    sha256_bytes,
    write_atomically,
)
from crs_study.bids import SessionPaths  # noqa: F401  (re-exported: older imports)
from crs_study.errors import DatasetError, SessionError
from crs_study.session_metadata import SessionMetadata

BIDS_VERSION = "1.10.0"
DATASET_LOCK = ".crs-study.lock"
#: Journal of a participant's withdrawal in progress (crs_study.consent); while it exists no
#: session may start in the dataset.
WITHDRAWAL_JOURNAL = ".crs-study-withdrawal.json"
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


def utc_now() -> str:
    """The current time, ISO 8601 in UTC, to the second."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def json_text(data: Any) -> str:
    return json.dumps(data, indent=2, ensure_ascii=False) + "\n"


def format_value(value: Any) -> str:
    """A TSV cell: ``n/a`` for missing, 0/1 for booleans, floats to the microsecond."""
    if value is None:
        return schema.MISSING
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        if not math.isfinite(value):
            return schema.MISSING
        text = f"{value:.6f}"
        return "0.000000" if text == "-0.000000" else text
    text = str(value)
    if any(c in text for c in "\t\n\r"):
        raise DatasetError(f"a TSV value may not contain tabs or newlines: {text!r}")
    return text


def tsv_line(values: Sequence[Any]) -> str:
    return "\t".join(format_value(v) for v in values) + "\n"


# --- the dataset -------------------------------------------------------------------------------

class Dataset:
    """A BIDS dataset directory: top-level files, participants, sessions."""

    def __init__(self, root: str | Path, name: str = "crs-study digit identification") -> None:
        self.root = Path(root)
        self.name = name

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
                        "Description": "CRS haptic display digit-identification sessions",
                    }],
                }),
                bids.PARTICIPANTS_JSON: json_text(PARTICIPANTS_SIDECAR),
                bids.task_sidecar_name(schema.TASK): json_text(column_dictionary()),
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

    def register_participant(self, label: str, counterbalance: int | None = None) -> int:
        """The participant's counterbalance index, adding the participant when new.

        A new participant gets ``counterbalance`` when given, else the number of participants
        already in the dataset (0-based order of arrival). A known participant keeps the index
        stored; asking for another one is a :class:`SessionError`.
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
            index = len(known) if counterbalance is None else int(counterbalance)
            if index < 0:
                raise SessionError(f"counterbalance must be >= 0, got {index!r}")
            known[label] = index
            lines = ["\t".join(PARTICIPANT_COLUMNS) + "\n"]
            lines += [tsv_line([f"sub-{k}", v]) for k, v in sorted(known.items())]
            with os_errors(DatasetError, "write", self.root / bids.PARTICIPANTS_TSV):
                write_atomically(self.root / bids.PARTICIPANTS_TSV, "".join(lines))
            return index

    def session_paths(self, participant: str, session: int) -> SessionPaths:
        check_label(participant)
        if not isinstance(session, int) or session < 1:
            raise SessionError(f"session must be a whole number >= 1, got {session!r}")
        return SessionPaths(self.root, participant, session)

    def sessions(self, participant: str) -> list[int]:
        """Session numbers of a participant found in the dataset."""
        return bids.session_numbers(self.root, check_label(participant))


_LEVEL_TEXT = {
    "0|1": {"0": "no", "1": "yes"},
    "practice|test": {"practice": "practice trial, with feedback, not analysed",
                      "test": "test trial"},
    "0-9": {str(d): f"the digit {d}" for d in range(10)},
}


def column_dictionary() -> dict[str, Any]:
    """The BIDS column dictionary (``task-digitid_beh.json``) from :mod:`crs_study.schema`.

    Closed sets become ``Levels`` (an object level -> meaning, as BIDS requires); numeric
    columns get ``Units``; free labels (condition, responder) only a description. The level
    columns (:data:`crs_study.schema.LEVEL_COLUMNS`) are described too: the file is one per
    dataset, and only sessions of protocols with ``[levels]`` hold them.
    """
    columns: dict[str, Any] = {}
    described = {**schema.TRIAL_COLUMNS, **schema.LEVEL_COLUMNS}
    for name, (description, units) in described.items():
        entry: dict[str, Any] = {"LongName": name.replace("_", " "), "Description": description}
        if units in _LEVEL_TEXT:
            entry["Levels"] = _LEVEL_TEXT[units]
        elif units != "label":
            entry["Units"] = units
        columns[name] = entry
    return {"TaskName": schema.TASK, **columns}


DATASET_README = """\
# crs-study dataset

Digit-identification sessions on the continuity reinforcement skeleton (CRS) haptic display,
written by crs-study (BIDS, datatype beh). One row per trial in
sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-digitid_beh.tsv; the session's protocol, device
file, seed and status are in the .json beside it; per-frame device logs are under sourcedata/.
Participant labels are pseudonyms; names are never stored here.
"""


# --- one session -------------------------------------------------------------------------------

class SessionStore:
    """A session's files, held under the session lock by one runner.

    Use as a context manager (or :meth:`acquire` / :meth:`release`). ``durable=False`` (for
    dry-runs, which a seed regenerates) keeps every write atomic and ordered, so a killed
    process loses nothing, but fsyncs only when the session stops, not after every trial.
    """

    def __init__(self, paths: SessionPaths, columns: Sequence[str] | None = None,
                 durable: bool = True) -> None:
        self.paths = paths
        self.columns = tuple(columns or schema.TRIAL_COLUMNS)
        self.durable = durable
        self._lock_handle: Any = None
        self._hash = hashlib.sha256()
        self._created = False
        self._frames_created = False

    # --- lock ---
    def acquire(self) -> None:
        """Take the session lock, under the dataset lock and only while no withdrawal is due."""
        dataset = Dataset(self.paths.root)
        with dataset.locked():
            dataset.refuse_pending_withdrawal()
            with os_errors(DatasetError, "create the session", self.paths.session_dir):
                make_dirs(self.paths.session_dir)
                handle = open(self.paths.lock, "a+")  # noqa: SIM115 - held until release()
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                raise SessionError(
                    f"session {self.paths.session} of participant {self.paths.participant!r} "
                    f"is in use by another runner ({self.paths.lock})") from None
        self._lock_handle = handle

    def release(self) -> None:
        if self._lock_handle is not None:
            fcntl.flock(self._lock_handle, fcntl.LOCK_UN)
            self._lock_handle.close()
            self._lock_handle = None

    def __enter__(self) -> SessionStore:
        self.acquire()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()

    # --- reading ---
    def exists(self) -> bool:
        return self.paths.tsv.exists() or self.paths.sidecar.exists()

    def read_sidecar(self) -> SessionMetadata | None:
        """The stored sidecar (None before the first write); any problem is one line."""
        if not self.paths.sidecar.exists():
            return None
        return SessionMetadata.read(self.paths.sidecar)

    def recover_rows(self) -> list[dict[str, str]]:
        """The rows stored so far; a torn last line is cut off (backed up) first.

        Also cuts frame-log members of trials without a row (a kill between the two appends)
        and positions the running sha256 so :attr:`trials_sha256` covers the whole file.
        """
        rows = self._recover_tsv()
        self._recover_frames(len(rows))
        return rows

    def verify_complete(self, recorded_sha256: str | None) -> list[dict[str, str]]:
        """The rows of a session marked complete, checked and read without changing a byte.

        The TSV must hash to ``recorded_sha256`` (the sidecar's ``TrialsSha256``) and parse
        whole; otherwise a :class:`SessionError`: a completed session is never rewritten,
        not even to cut a torn tail.
        """
        path = self.paths.tsv
        data = self._read(path)
        actual = sha256_bytes(data)
        if actual != recorded_sha256:
            raise SessionError(
                f"{path}: the session is marked complete but its trial file changed since "
                f"(sha256 {actual[:12]}..., recorded {str(recorded_sha256)[:12]}...); a "
                "completed session is never rewritten: restore the file or use another "
                "--session")
        rows, keep = self._parse_tsv(path, data)
        if keep != len(data):
            raise SessionError(f"{path}: the session is marked complete but its last line is "
                               "incomplete; a completed session is never rewritten")
        self._hash = hashlib.sha256(data)
        self._created = True
        return rows

    @staticmethod
    def _read(path: Path) -> bytes:
        if not path.exists():
            return b""
        with os_errors(DatasetError, "read", path):
            return path.read_bytes()

    def _parse_tsv(self, path: Path, data: bytes) -> tuple[list[dict[str, str]], int]:
        """Rows of the TSV bytes and how many bytes hold whole lines (the rest is torn)."""
        header = "\t".join(self.columns).encode() + b"\n"
        if not data.startswith(header):
            if header.startswith(data):  # killed while writing the header
                return [], 0
            first = data.split(b"\n", 1)[0].decode("utf-8", "replace")
            raise DatasetError(f"{path}: unexpected header {first!r}; expected the columns of "
                               f"crs_study.schema.TRIAL_COLUMNS")
        keep = len(data) if data.endswith(b"\n") else data.rfind(b"\n") + 1
        lines = data[len(header):keep].split(b"\n")[:-1] if keep > len(header) else []
        rows: list[dict[str, str]] = []
        for number, line in enumerate(lines, start=2):
            fields = line.decode("utf-8", "replace").split("\t")
            if len(fields) != len(self.columns) or b"\x00" in line:
                if number == len(lines) + 1:  # a malformed last line: torn as well
                    keep -= len(line) + 1
                    break
                raise DatasetError(f"{path}:{number}: expected {len(self.columns)} fields, "
                                   f"got {len(fields)}; the file was edited or damaged")
            rows.append(dict(zip(self.columns, fields, strict=True)))
        return rows, keep

    def _recover_tsv(self) -> list[dict[str, str]]:
        path = self.paths.tsv
        if not path.exists():
            return []
        data = self._read(path)
        rows, keep = self._parse_tsv(path, data)
        if keep < len(data):
            self._cut(path, data, keep, "beh")
        self._hash = hashlib.sha256(data[:keep])
        self._created = keep > 0
        return rows

    def _recover_frames(self, n_rows: int) -> None:
        """Keep the header member and the members of trials 0..n_rows-1 of the frame log."""
        path = self.paths.frame_log
        if not path.exists():
            return
        data = self._read(path)
        keep = 0
        position = 0
        expected = -1  # the header member first, then trial 0, 1, ...
        while position < len(data) and expected < n_rows:
            member = zlib.decompressobj(wbits=31)
            try:
                text = member.decompress(data[position:])
            except zlib.error:
                break
            if not member.eof:
                break
            first = text.split(b"\t", 1)[0]
            if (expected == -1 and first != b"trial") or (
                    expected >= 0 and first != str(expected).encode()):
                break
            position = len(data) - len(member.unused_data)
            keep = position
            expected += 1
        if expected < n_rows and n_rows > 0:
            raise DatasetError(f"{path}: frame log holds trials up to {expected - 1}, the "
                               f"trial file has {n_rows} rows; the files were edited or damaged "
                               "(a dry-run cut by a power failure: remove this session's files "
                               "and run the same command to regenerate it)")
        if keep < len(data):
            self._cut(path, data, keep, "frames")
        self._frames_created = keep > 0

    def _cut(self, path: Path, data: bytes, keep: int, what: str) -> None:
        """Truncate ``path`` to ``keep`` bytes, saving the rest under ``sourcedata`` first.

        The cut bytes are durable in their backup before the file is truncated (and the
        truncation is fsynced), so a crash at any point keeps every byte somewhere.
        """
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        backup = self.paths.torn_backup(what, stamp)
        with os_errors(DatasetError, "cut the torn tail of", path):
            make_dirs(self.paths.source_dir)
            write_atomically(backup, data[keep:])
            with open(path, "r+b") as handle:
                handle.truncate(keep)
                handle.flush()
                os.fsync(handle.fileno())

    # --- writing ---
    def _append(self, path: Path, data: bytes, create: bool = False) -> None:
        """One ``write`` (all or, after a kill, a torn tail that recovery cuts), then fsync.

        A failed or short write (disk full) is cut back off and raised as one line.
        """
        with os_errors(DatasetError, "append to", path):
            append_durably(path, data, create=create, sync=self.durable)

    def create(self) -> None:
        """Start the TSV with its header (durably) if it has none."""
        if self._created:
            return
        with os_errors(DatasetError, "create", self.paths.beh_dir):
            make_dirs(self.paths.beh_dir)
        header = ("\t".join(self.columns) + "\n").encode()
        self._append(self.paths.tsv, header, create=True)
        self._hash = hashlib.sha256(header)
        self._created = True

    def append_row(self, row: dict[str, Any]) -> None:
        """Append one trial (one write; fsync when durable) before returning."""
        if not self._created:
            self.create()
        missing = [c for c in self.columns if c not in row]
        if missing:
            raise DatasetError(f"trial row lacks columns {missing}")
        line = tsv_line([row[c] for c in self.columns]).encode("utf-8")
        self._append(self.paths.tsv, line)
        self._hash.update(line)

    @property
    def trials_sha256(self) -> str:
        """sha256 of the TSV bytes as written so far."""
        return self._hash.hexdigest()

    def write_sidecar(self, metadata: SessionMetadata | Mapping[str, Any],
                      final: bool = False) -> None:
        """Rewrite the sidecar atomically (fsynced when durable or ``final``).

        ``metadata`` is the session's :class:`SessionMetadata` (a plain mapping is written
        as given, for tools and tests). On failure (disk full) the old sidecar stays whole
        and the error is one line.
        """
        text = metadata.to_json() if isinstance(metadata, SessionMetadata) else \
            json_text(dict(metadata))
        with os_errors(DatasetError, "write", self.paths.sidecar):
            make_dirs(self.paths.beh_dir)
            write_atomically(self.paths.sidecar, text, durable=self.durable or final,
                             sync_dir=final)

    def append_frames(self, trial_index: int, columns: Sequence[str],
                      rows: Sequence[Sequence[Any] | str]) -> None:
        """Append one trial's frames to the session's frame log (one gzip member).

        The log is a gzip TSV of concatenated members (``zcat`` or ``gzip.open`` read it as
        one table): the first holds the header (``trial`` then ``columns``), then one member
        per trial, in trial order. Appended before the trial's row, so a row always has its
        frames; members without a row are cut on resume. A row given as a string is taken as
        already formatted (tab-separated, without the trial column).
        """
        with os_errors(DatasetError, "create", self.paths.source_dir):
            make_dirs(self.paths.source_dir)
        if not self._frames_created:
            header = "\t".join(("trial", *columns)) + "\n"
            self._append(self.paths.frame_log, _gzip(header), create=True)
            self._frames_created = True
        text = "".join(f"{trial_index}\t{r}\n" if isinstance(r, str)
                       else tsv_line((trial_index, *r)) for r in rows)
        self._append(self.paths.frame_log, _gzip(text))

    def sync(self) -> None:
        """fsync every session file (the end of a session written with ``durable=False``)."""
        for path in (self.paths.tsv, self.paths.frame_log):
            if path.exists():
                with os_errors(DatasetError, "fsync", path):
                    fsync_path(path)


def _gzip(text: str) -> bytes:
    return gzip.compress(text.encode("utf-8"), compresslevel=6, mtime=0)


def read_frame_log(path: str | Path) -> list[dict[str, str]]:
    """Rows of a session's frame log (every member), for inspection and tests."""
    with gzip.open(path, "rt", encoding="utf-8", newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))
