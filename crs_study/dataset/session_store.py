"""One session's files, written trial by trial so that nothing is ever lost.

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

import csv
import fcntl
import gzip
import hashlib
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

from crs_study._files import (
    append_durably,
    cut_tail,
    fsync_path,
    make_dirs,
    os_errors,
    sha256_bytes,
    write_atomically,
)
from crs_study.dataset import schema
from crs_study.dataset.bids import SessionPaths
from crs_study.dataset.folder import Dataset, json_text
from crs_study.dataset.schema import tsv_line
from crs_study.dataset.session_metadata import SessionMetadata
from crs_study.errors import DatasetError, SessionError

#: Without per-trial durability (dry-runs) the sidecar is rewritten every this many trials
#: (and when the session stops), so it may lag the trial file by as many rows; with it, by
#: one (a kill between a row and the sidecar write after it).
UNDURABLE_SIDECAR_EVERY = 10


def sidecar_lag(stored: SessionMetadata) -> int:
    """How many rows the trial file of the session ``stored`` describes may hold beyond its
    ``TrialsCompleted`` after a kill: :data:`UNDURABLE_SIDECAR_EVERY` for a session on the
    virtual clock (a dry-run, written without per-trial durability), else one."""
    return UNDURABLE_SIDECAR_EVERY if stored.virtual_clock else 1


@dataclass(frozen=True)
class StoppedSession:
    """A session that stopped before its end whose trial file and sidecar disagree only as
    an interruption leaves them (:func:`explained_by_interruption`)."""

    #: whole rows in the trial file (every one of them a trial done)
    rows: int
    #: rows beyond the sidecar's ``TrialsCompleted`` (the sidecar lagged when it stopped)
    unrecorded: int
    #: bytes of a torn last line (a kill in the middle of an append), to be left out
    torn_bytes: int
    #: the most rows the sidecar may lag by (:func:`sidecar_lag`)
    lag: int


def explained_by_interruption(data: bytes, stored: SessionMetadata) -> StoppedSession | None:
    """Whether an interruption explains how the trial file ``data`` disagrees with the
    sidecar ``stored``; None when it does not (the file or the sidecar was changed).

    The check :meth:`SessionStore.check_resumable` makes before a resume, read-only: the
    session is not complete; after a torn last line (no newline) is set aside, the file
    holds ``TrialsCompleted`` whole rows plus at most :func:`sidecar_lag` more; and its
    header and first ``TrialsCompleted`` rows hash to ``TrialsSha256``, the rows the sidecar
    recorded. A complete session, more rows than the lag, fewer rows than recorded, or
    recorded rows rewritten are not explained.
    """
    if stored.is_complete or stored.trials_sha256 is None:
        return None
    keep = len(data) if data.endswith(b"\n") else data.rfind(b"\n") + 1
    if keep == 0:
        return None
    rows = data[:keep].count(b"\n") - 1
    done, lag = stored.trials_completed, sidecar_lag(stored)
    if not done <= rows <= done + lag:
        return None
    if sha256_bytes(_first_lines(data, done + 1)) != stored.trials_sha256:
        return None
    return StoppedSession(rows, rows - done, len(data) - keep, lag)


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
        self._lock_handle: TextIO | None = None
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

    def started_trial(self) -> int | None:
        """The trial whose stimulus began last, as :meth:`mark_started` noted it in the lock
        file (read it before the first mark of this run); None when nothing was noted."""
        if self._lock_handle is None:
            return None
        self._lock_handle.seek(0)
        text = self._lock_handle.read().strip()
        kind, _, number = text.partition(" ")
        return int(number) if kind == "started" and number.isdigit() else None

    def mark_started(self, trial_index: int) -> None:
        """Note in the lock file that ``trial_index``'s stimulus begins (not fsynced: a kill
        keeps it in the page cache; a power cut may lose it, and a resume then treats the
        trial as possibly felt)."""
        if self._lock_handle is not None:
            self._lock_handle.seek(0)
            self._lock_handle.truncate()
            self._lock_handle.write(f"started {trial_index}\n")
            self._lock_handle.flush()

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

    def _adopt_older_header(self, data: bytes) -> None:
        """A session begun before a column of :data:`~crs_study.dataset.schema.LATER_COLUMNS`
        existed keeps the columns it began with."""
        older = tuple(c for c in self.columns if c not in schema.LATER_COLUMNS)
        if older != self.columns and data.startswith("\t".join(older).encode() + b"\n"):
            self.columns = older

    def check_resumable(self, stored: SessionMetadata | None, sidecar_lag: int = 1) -> None:
        """The sidecar, the trial file and the frame log agree, beyond a torn last line or
        frame-log member (which :meth:`recover_rows` cuts and keeps). Reads only.

        ``stored`` is the sidecar (None when there is none); it may lag the trial file by up
        to ``sidecar_lag`` rows. Disagreement is a one-line :class:`DatasetError` naming the
        file and what disagrees, and what the experimenter can do: a missing or emptied trial
        file, one cut inside its header or shorter than the sidecar says, rows that differ
        from those the sidecar recorded (``TrialsSha256`` of its first rows), rows without a
        sidecar, a missing frame log, or one holding more or fewer trials than the rows.
        """
        tsv, sidecar, log = self.paths.tsv, self.paths.sidecar, self.paths.frame_log
        data = self._read(tsv) if tsv.exists() else None
        if data:
            self._adopt_older_header(data)
        rows, keep = self._parse_tsv(tsv, data) if data else ([], 0)
        n_rows = len(rows)
        frames = self._scan_frames(self._read(log), None)[0] if log.exists() else None
        advice = ("restore the session's files from a backup, or leave them as they are and "
                  "start another --session (a dry-run's session: remove its files and run the "
                  "same command to regenerate it)")
        if stored is None:
            if n_rows or frames:
                what = f"holds {n_rows} trial(s)" if n_rows else "has no rows"
                raise DatasetError(
                    f"{tsv}: {what} and the frame log {frames or 0}, but the session sidecar "
                    f"{sidecar} is missing, so nothing vouches for the plan they belong to; "
                    f"{advice}")
            return
        done = stored.trials_completed
        if data is None and done:
            raise DatasetError(f"{tsv}: missing, but the sidecar {sidecar} says {done} "
                               f"trial(s) were done; {advice}")
        if n_rows < done:
            state = ("empty" if not data else "cut inside its header" if not keep
                     else f"{n_rows} whole row(s)")
            raise DatasetError(f"{tsv}: holds {state}, but the sidecar {sidecar} says {done} "
                               f"trial(s) were done; {advice}")
        if n_rows > done + sidecar_lag:
            raise DatasetError(f"{tsv}: holds {n_rows} rows, but the sidecar {sidecar} says "
                               f"{done} trial(s) were done and lags by at most {sidecar_lag}; "
                               f"{advice}")
        if stored.trials_sha256 is not None and data is not None:
            prefix = _first_lines(data, done + 1)
            if sha256_bytes(prefix) != stored.trials_sha256:
                raise DatasetError(f"{tsv}: its first {done} row(s) differ from those the "
                                   f"sidecar {sidecar} recorded (TrialsSha256); the file was "
                                   f"edited or damaged; {advice}")
        if n_rows and frames is None:
            raise DatasetError(f"{log}: missing, but the trial file {tsv} holds {n_rows} "
                               f"trial(s); {advice}")
        if frames is not None and not n_rows <= frames <= n_rows + 1:
            lost = "rows were lost" if frames > n_rows else "frames were lost"
            raise DatasetError(f"{log}: holds {frames} trial(s), the trial file {tsv} "
                               f"{n_rows}: {lost}; {advice}")

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
        self._adopt_older_header(data)
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
                               f"crs_study.dataset.schema.TRIAL_COLUMNS")
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
        self._adopt_older_header(data)
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
        count, keep = self._scan_frames(data, n_rows)
        if count < n_rows:
            raise DatasetError(f"{path}: frame log holds trials up to {count - 1}, the "
                               f"trial file has {n_rows} rows; the files were edited or damaged "
                               "(a dry-run cut by a power failure: remove this session's files "
                               "and run the same command to regenerate it)")
        if keep < len(data):
            self._cut(path, data, keep, "frames")
        self._frames_created = keep > 0

    @staticmethod
    def _scan_frames(data: bytes, limit: int | None) -> tuple[int, int]:
        """Whole trial members of a frame log, in order (at most ``limit``), and the bytes
        they and the header member take."""
        keep = 0
        position = 0
        expected = -1  # the header member first, then trial 0, 1, ...
        while position < len(data) and (limit is None or expected < limit):
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
        return max(expected, 0), keep

    def _cut(self, path: Path, data: bytes, keep: int, what: str) -> None:
        """Truncate ``path`` to ``keep`` bytes, saving the rest under ``sourcedata`` first.

        The cut bytes are durable in their backup before the file is truncated (and the
        truncation is fsynced), so a crash at any point keeps every byte somewhere.
        """
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        backup = self.paths.torn_backup(what, stamp)
        with os_errors(DatasetError, "cut the torn tail of", path):
            make_dirs(self.paths.source_dir)
            cut_tail(path, data, keep, backup,
                     backups=self.paths.torn_backup(what, "*").name)

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


def _first_lines(data: bytes, count: int) -> bytes:
    """The first ``count`` lines of ``data`` (each with its newline)."""
    end = 0
    for _ in range(count):
        found = data.find(b"\n", end)
        if found < 0:
            return data[:end]
        end = found + 1
    return data[:end]


def _gzip(text: str) -> bytes:
    return gzip.compress(text.encode("utf-8"), compresslevel=6, mtime=0)


def read_frame_log(path: str | Path) -> list[dict[str, str]]:
    """Rows of a session's frame log (every member), for inspection and tests."""
    with gzip.open(path, "rt", encoding="utf-8", newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))
