"""Load one or several stored datasets into one tidy trial table, checked and with exclusions.

The trial table (:attr:`LoadedData.trials`) has one row per trial and these columns:

=============================  =========  ==================================================
column                         dtype      meaning
=============================  =========  ==================================================
dataset                        str        the dataset's ``Name`` (directory name if absent)
participant                    str        BIDS label without ``sub-``
participant_id                 str        unique across datasets: ``participant``, or
                                          ``dataset/participant`` when several datasets load
session                        str        BIDS label without ``ses-``
trial_index, block,            Int64      as in ``crs_study.dataset.schema.TRIAL_COLUMNS``
repetition, frames,                       (nullable integers; ``n/a`` -> ``<NA>``)
late_frames
digit (or symbol)              int64      the symbol shown (never missing): ``digit`` in a
                               (or str)   digit dataset (ints), ``symbol`` in a dataset of
                                          any other stimulus set (its labels, text)
response                       Int64      the symbol reported, ``<NA>`` when timed out
                               (or str)   (NaN in a text dataset)
correct                        float64    1.0 / 0.0, NaN when timed out (or 0.0 under the
                                          plan's ``timeouts = "count_as_error"``)
response_time, ... (seconds)   float64    NaN for ``n/a``
timed_out, device_fault,       bool       (``rerun`` False in sessions written before it existed)
rerun
trial_type, condition,         str
responder
<level columns>                float64    extra numeric columns (``digit_height``, ...) kept
excluded                       bool       True when an exclusion of the plan applies
exclusion                      str        the first reason that applies ("" when kept):
                                          practice, device_fault, timeout, anticipation, slow
=============================  =========  ==================================================

Sessions are found by :func:`crs_study.dataset.bids.find_sessions` (the layout the runner
writes) and each sidecar is read as :class:`~crs_study.dataset.SessionMetadata`, strictly: a
missing, unreadable or invalid sidecar leaves its trials unchecked (a warning, or a
:class:`DatasetError` with ``strict``).

Checks on every session: the sidecar exists and names the same participant, session and task;
``TrialsSha256`` equals the sha256 of the ``_beh.tsv`` bytes, ``ProtocolSha256`` and
``DeviceFileSha256`` those of the recorded texts; ``TrialsCompleted`` equals the number of
rows; ``correct`` agrees with ``response`` equal to the symbol shown; an adaptive session's
estimates agree with its replayed tracks (:mod:`.adaptive_replay`). The sessions of every
task are found; one analysis takes one task (one stimulus set): datasets holding several
are a one-line error unless ``task`` chooses one. A failed check means the data were edited
after the session (or a bug): a warning by default, a :class:`DatasetError` with ``strict``.

A session that stopped before its end (status ``running`` after a kill, ``interrupted``
after a pause) is analysed as it stands, with a warning saying so, also with ``strict``: it
is not a failed check. Its sidecar may lag its trial file (a dry-run rewrites it every 10
trials) and a kill may tear the last row; when the recorded rows hash to ``TrialsSha256`` and
the rows beyond them are within that lag
(:func:`crs_study.dataset.session_store.explained_by_interruption`, the check a resume
makes), the disagreement is the interruption's, and the torn row is left out. Any other
disagreement (more rows than the lag, recorded rows rewritten, a complete session with fewer
rows) remains a tampering alarm.

No session is left out silently. A trial file that cannot be read (a folder or a named pipe
in its place, an OS error, bytes that are not UTF-8) leaves its session out with a warning
naming the participant; a session or participant the dataset shows existed but whose trial
file is gone (:func:`crs_study.dataset.evidence.missing_sessions`: participants.tsv, the
sidecar, sourcedata, the record of analysis outputs) is a warning of possible tampering.
Each is a :class:`DatasetError` with ``strict``.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from crs_study._files import not_a_regular_file, sha256_bytes
from crs_study.analysis.adaptive_replay import replay_adaptive
from crs_study.analysis.exclusions import apply_exclusions
from crs_study.analysis.plan import Exclusions
from crs_study.dataset import WITHDRAWAL_JOURNAL, SessionMetadata, SessionPaths, find_sessions
from crs_study.dataset.evidence import UnreadableSession, missing_sessions, read_trial_file
from crs_study.dataset.schema import (
    MISSING,
    SYMBOL_COLUMNS,
    symbol_column,
    symbols_are_numbers,
    trial_columns,
)
from crs_study.dataset.session_store import StoppedSession, explained_by_interruption
from crs_study.errors import DatasetError

INT_COLUMNS = ("trial_index", "block", "repetition", "frames", "late_frames", "response")
FLOAT_COLUMNS = ("correct", "response_time", "response_time_from_offset", "onset",
                 "stimulus_duration", "median_wire_latency", "trial_end")
BOOL_COLUMNS = ("timed_out", "device_fault", "rerun")
TEXT_COLUMNS = ("trial_type", "condition", "responder")
#: Required besides the symbol shown (a column of ``SYMBOL_COLUMNS``).
REQUIRED_COLUMNS = ("trial_type", "condition", "correct", "response")
EXCLUSION_REASONS = ("practice", "device_fault", "timeout", "anticipation", "slow")
#: Sidecar keys each session's row of :attr:`LoadedData.sessions` holds (as the sidecar has
#: them), besides ``Protocol`` and ``PlanLock`` (full texts).
SESSION_SUMMARY_KEYS = ("Status", "Seed", "SoftwareVersion", "StartTime", "EndTime",
                        "ConsentFormVersion", "DeviceURL", "Responder", "Clock", "ProtocolPath",
                        "TrialsSha256", "ProtocolSha256", "PlanLockSha256")


@dataclass(frozen=True)
class LoadedData:
    """Every trial of the datasets, the sessions' metadata, the warnings and exclusions."""

    trials: pd.DataFrame
    sessions: pd.DataFrame
    warnings: tuple[str, ...] = ()
    exclusion_counts: dict[str, dict[str, int]] = field(default_factory=dict)

    @property
    def analysed(self) -> pd.DataFrame:
        """The trials kept after the plan's exclusions."""
        return self.trials.loc[~self.trials["excluded"]].reset_index(drop=True)


def load_datasets(paths: list[str | Path] | str | Path, exclusions: Exclusions | None = None,
                  strict: bool = False, task: str | None = None) -> LoadedData:
    """Load the datasets under ``paths``, check them, and apply ``exclusions`` (none if None).

    ``task`` chooses the sessions of one BIDS task (one stimulus set: ``digitid``,
    ``letterid``); None takes every session, which must then be of one task.

    Raises :class:`DatasetError` for a missing or unreadable dataset, for a dataset named twice
    (by any path) or datasets holding the same session (a copy: its trials would count twice),
    for sessions of several tasks, and with ``strict`` for any failed integrity check
    (otherwise each failure is a warning).
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    if not paths:
        raise DatasetError("no dataset given: expected at least one dataset directory")
    _refuse_repeated_datasets([Path(p) for p in paths])
    warnings: list[str] = []
    frames, sessions, files = [], [], []
    names = [_dataset_name(Path(p)) for p in paths]
    if len(set(names)) < len(names):
        names = [str(Path(p)) for p in paths]
    seen: dict[tuple[str, str, str], Path] = {}   # (participant, session, sha256) -> dataset
    found = {Path(p): _sessions_of(Path(p), task) for p in paths}
    _refuse_several_tasks(found)
    for path, name in zip(paths, names, strict=True):
        accounted: set[tuple[str, str, str]] = set()
        for session in found[Path(path)]:
            tsv = session.tsv
            accounted.add((session.participant, "" if session.session is None
                           else str(session.session), session.task))
            try:
                table, meta, problems, notes = _read_session(session, name, len(files))
            except UnreadableSession as exc:
                warnings += _raise_if_strict([str(exc)], strict)
                continue
            key = (meta["participant"], meta["session"], meta.pop("_sha256"))
            if key in seen and seen[key] != Path(path):
                raise DatasetError(
                    f"{tsv}: the same session (sub-{key[0]} ses-{key[1]}, identical trial "
                    f"file) is also in {seen[key]}: the datasets are copies of each other, "
                    "and analysing both would count its trials twice; give one of them")
            seen.setdefault(key, Path(path))
            files.append(tsv)
            warnings += _raise_if_strict(problems, strict) + notes
            frames.append(table)
            sessions.append(meta)
        warnings += _raise_if_strict(missing_sessions(path, accounted, task), strict)
    if not frames:
        raise DatasetError(f"no readable session in {', '.join(map(str, paths))}: "
                           f"{warnings[0] if warnings else 'none found'}")
    trials, problems = _typed(pd.concat(frames, ignore_index=True), files)
    trials, replayed = replay_adaptive(trials, sessions, files)  # derived columns checked
    warnings += _raise_if_strict(problems + replayed, strict)
    trials = trials.drop(columns=["_file", "_row"])
    several = len(paths) > 1
    trials["participant_id"] = (trials["dataset"] + "/" + trials["participant"]) if several \
        else trials["participant"]
    trials = _order_columns(trials)
    if exclusions is None:
        trials["exclusion"], trials["excluded"] = "", False
        counts: dict[str, dict[str, int]] = {}
    else:
        trials, counts = apply_exclusions(trials, exclusions)
    return LoadedData(trials, pd.DataFrame(sessions), tuple(warnings), counts)


def _refuse_repeated_datasets(paths: list[Path]) -> None:
    """One dataset named twice (``D D``, ``D ./D/``, a symlink to ``D``) is an error.

    Refused rather than deduplicated: each trial must count once, and a command line that
    names a dataset twice is a mistake whose intent (a typo for another dataset?) only the
    user knows; silently dropping one would also make ``results.json`` list other datasets
    than the command asked for.
    """
    first: dict[tuple[int, int], Path] = {}
    for path in paths:
        try:
            stat = path.stat()
        except OSError:
            continue    # reported as missing by _sessions_of, with the path as given
        identity = (stat.st_dev, stat.st_ino)
        if identity in first:
            raise DatasetError(f"{path}: the same dataset as {first[identity]} (given twice); "
                               "each dataset may be analysed once")
        first[identity] = path


def _refuse_several_tasks(found: dict[Path, list[SessionPaths]]) -> None:
    """One analysis, one task: sessions of two stimulus sets are not pooled."""
    tasks = {s.task: root for root, sessions in found.items() for s in sessions}
    if len(tasks) > 1:
        where = ", ".join(f"{t} (in {root})" for t, root in sorted(tasks.items()))
        raise DatasetError(f"the datasets hold sessions of several tasks: {where}; one "
                           "analysis takes one task (one stimulus set): choose it with "
                           "load_datasets(..., task=...) or analyse the sets apart")


def _raise_if_strict(problems: list[str], strict: bool) -> list[str]:
    if strict and problems:
        raise DatasetError(problems[0])
    return problems


def with_exclusions(data: LoadedData, exclusions: Exclusions) -> LoadedData:
    """The same data with ``exclusions`` applied afresh (loaded with ``exclusions=None``)."""
    trials, counts = apply_exclusions(data.trials, exclusions)
    return LoadedData(trials, data.sessions, data.warnings, counts)


def _dataset_name(path: Path) -> str:
    description = path / "dataset_description.json"
    try:
        if not_a_regular_file(description):  # missing, or a named pipe that would block
            raise OSError
        name = json.loads(description.read_text(encoding="utf-8")).get("Name")
    except (OSError, ValueError, AttributeError, RecursionError):
        name = None
    try:  # a symbolic link loop cannot resolve: named as given, and _sessions_of refuses it
        return str(name) if name else path.resolve().name
    except (OSError, RuntimeError):
        return path.name


def _sessions_of(root: Path, task: str | None = None) -> list[SessionPaths]:
    """The sessions of ``task`` (None: of every task) of the dataset at ``root``
    (:func:`crs_study.dataset.bids.find_sessions`)."""
    if not root.is_dir():
        raise DatasetError(f"{root}: no such dataset directory")
    if (root / WITHDRAWAL_JOURNAL).exists():
        # A withdrawal was interrupted: analysing now could include data that must go.
        raise DatasetError(f"{root}: a participant's withdrawal was interrupted; finish it "
                           f"first: crs-study consent recover --dataset {root}")
    sessions = find_sessions(root, task)
    if not sessions:
        raise DatasetError(f"{root}: no sessions found (expected "
                           f"sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-{task or '<task>'}"
                           "_beh.tsv)")
    return sessions


def _read_sidecar(paths: SessionPaths) -> tuple[SessionMetadata | None, list[str]]:
    """The session's sidecar, read strictly (:class:`SessionMetadata`); a missing, unreadable
    or invalid one is a problem (a warning, or an error with ``strict``), its trials then
    unchecked."""
    sidecar = paths.sidecar
    if not sidecar.exists():
        return None, [f"{sidecar}: session metadata missing; its trials are unchecked"]
    why = not_a_regular_file(sidecar)
    if why is not None:   # a named pipe would block the read forever
        return None, [f"{sidecar}: session metadata unreadable ({why}); its trials are "
                      "unchecked"]
    try:
        return SessionMetadata.read(sidecar), []
    except DatasetError as exc:
        reason = str(exc).removeprefix(f"{sidecar}: ")
        return None, [f"{sidecar}: session metadata unreadable ({reason}); its trials are "
                      "unchecked"]


def _read_session(paths: SessionPaths, dataset: str, file_number: int
                  ) -> tuple[pd.DataFrame, dict, list[str], list[str]]:
    """One session's rows as read (typed later, all files at once), its metadata, its
    problems (failed checks) and notes (an interruption, a warning even with ``strict``)."""
    tsv = paths.tsv
    participant = paths.participant
    session = "" if paths.session is None else str(paths.session)
    data = read_trial_file(paths)
    metadata, problems = _read_sidecar(paths)
    notes: list[str] = []
    stopped = None if metadata is None else explained_by_interruption(data, metadata)
    if stopped is not None:
        notes.append(_stopped_note(metadata, stopped, paths))
        data = data[:len(data) - stopped.torn_bytes]
    if metadata is not None:
        problems += _check_metadata(metadata, paths, data, session, stopped is not None)
    header = data.split(b"\n", 1)[0].decode("utf-8", "replace").rstrip("\r").split("\t")
    symbol = symbol_column(header)
    text = TEXT_COLUMNS if symbol is None or symbols_are_numbers(symbol) else \
        (*TEXT_COLUMNS, symbol, "response")
    try:
        raw = pd.read_csv(io.BytesIO(data), sep="\t", keep_default_na=False,
                          na_values=[MISSING], dtype={c: str for c in text})
    except (ValueError, pd.errors.ParserError) as exc:
        raise DatasetError(f"{tsv}: not a readable TSV: {str(exc).splitlines()[0]}") from None
    missing = [repr(c) for c in REQUIRED_COLUMNS[:2] if c not in raw.columns]
    missing += [" or ".join(map(repr, SYMBOL_COLUMNS))] if symbol is None else []
    missing += [repr(c) for c in REQUIRED_COLUMNS[2:] if c not in raw.columns]
    if missing:
        raise DatasetError(f"{tsv}: missing column {missing[0]} "
                           f"(expected the columns of crs_study.dataset.schema.TRIAL_COLUMNS)")
    if metadata is not None and stopped is None and metadata.trials_completed != len(raw):
        problems.append(f"{tsv}: TrialsCompleted is {metadata.trials_completed!r} but the file "
                        f"holds {len(raw)} trials (possible tampering)")
    raw.insert(0, "_row", np.arange(2, len(raw) + 2))
    raw.insert(0, "_file", file_number)
    raw.insert(0, "session", session)
    raw.insert(0, "participant", participant)
    raw.insert(0, "dataset", dataset)
    recorded = metadata.to_dict() if metadata is not None else {}  # the sidecar's own text
    summary = {"dataset": dataset, "participant": participant, "session": session,
               "file": str(tsv), "n_rows": len(raw),
               **{k: recorded.get(k) for k in SESSION_SUMMARY_KEYS}}
    summary["Protocol"] = recorded.get("Protocol")
    summary["PlanLock"] = recorded.get("PlanLock")
    summary["_sha256"] = sha256_bytes(data)   # for the copy check; popped by load_datasets
    return raw, summary, problems, notes


def _stopped_note(metadata: SessionMetadata, stopped: StoppedSession, paths: SessionPaths
                  ) -> str:
    """What a session that stopped before its end is: interrupted, not tampered with."""
    how = ("interrupted (its status was never updated: the process was killed or crashed)"
           if metadata.status == "running" else "interrupted")
    if stopped.unrecorded:
        how += (f"; its trial file holds {stopped.unrecorded} row(s) more than the sidecar's "
                f"TrialsCompleted {metadata.trials_completed}, within the {stopped.lag} the "
                "sidecar may lag by, and the rows it recorded are intact")
    if stopped.torn_bytes:
        how += (f"; a torn last row ({stopped.torn_bytes} bytes, cut by the interruption) is "
                "left out")
    return (f"{paths.sidecar}: session status is {metadata.status!r}: the session stopped "
            f"before its end, {how}; its {stopped.rows} of {metadata.trials_planned} trials "
            "are analysed as they stand (running the same command again completes it)")


def _check_metadata(metadata: SessionMetadata, paths: SessionPaths, data: bytes,
                    session: str, stopped: bool) -> list[str]:
    """The integrity checks of one session (``stopped``: an interruption explains how its
    trial file and sidecar disagree, :func:`explained_by_interruption`)."""
    problems = []
    sidecar, tsv = paths.sidecar, paths.tsv
    recorded = metadata.trials_sha256
    actual = sha256_bytes(data)
    if recorded is None:
        problems.append(f"{sidecar}: TrialsSha256 missing; the trials cannot be verified")
    elif recorded != actual and not stopped:
        problems.append(f"{tsv}: TAMPERED? sha256 is {actual[:16]}... but the session recorded "
                        f"TrialsSha256 {str(recorded)[:16]}...; the file changed after the "
                        "session was written")
    for text, sha, sha_key, text_key in (
            (metadata.protocol_text, metadata.protocol_sha256, "ProtocolSha256", "Protocol"),
            (metadata.device_file_text, metadata.device_file_sha256, "DeviceFileSha256",
             "DeviceFile")):
        if sha256_bytes(text.encode("utf-8")) != sha:
            problems.append(f"{sidecar}: {sha_key} does not match the recorded {text_key} "
                            "text (possible tampering)")
    for key, value, expected in (("Participant", metadata.participant, paths.participant),
                                 ("Session", str(metadata.session), session),
                                 ("TaskName", metadata.task_name, paths.task)):
        if value != expected:
            problems.append(f"{sidecar}: {key} is {value!r} but the file name says "
                            f"{expected!r} (possible tampering)")
    if metadata.status in ("running", "interrupted") and not stopped:
        problems.append(f"{sidecar}: session status is {metadata.status!r}: its "
                        f"{metadata.trials_completed} of {metadata.trials_planned} "
                        "trials are analysed as they stand")
    return problems


def _typed(raw: pd.DataFrame, files: list[Path]) -> tuple[pd.DataFrame, list[str]]:
    """Type every column (see the module table); check ``correct`` against the response."""
    def where(mask: pd.Series) -> str:
        first = int(np.flatnonzero(mask.to_numpy())[0])
        return f"{files[int(raw['_file'].iloc[first])]}: row {int(raw['_row'].iloc[first])}"

    symbols = [c for c in SYMBOL_COLUMNS if c in raw.columns]
    if len(symbols) > 1:  # a file of one task with the other's header (edited by hand)
        raise DatasetError(f"{where(raw[symbols[0]].isna())}: the trial files name the "
                           f"symbol shown differently ({' and '.join(symbols)}); expected one")
    symbol = symbols[0]
    numeric = symbols_are_numbers(symbol)
    out = pd.DataFrame(index=raw.index)
    for column in raw.columns:
        values = raw[column]
        if column in ("dataset", "participant", "session", "_file", "_row"):
            out[column] = values
        elif column in BOOL_COLUMNS:
            out[column] = _numbers(values, column, where).fillna(0).astype(bool)
        elif column in (symbol, "response") and not numeric:
            out[column] = values.astype(object).where(values.notna(), np.nan)
        elif column in INT_COLUMNS or column == symbol:
            numbers = _numbers(values, column, where)
            # a whole number an int64 holds: 1e308 or 99999999999999999999 is no trial's count
            fraction = numbers.notna() & ((numbers % 1 != 0) | (numbers.abs() >= 2.0 ** 53))
            if fraction.any():
                raise DatasetError(f"{where(fraction)}: column {column!r}: expected a whole "
                                   f"number below 2**53, got {values[fraction].iloc[0]!r}")
            out[column] = numbers.astype("Int64")
        elif column in FLOAT_COLUMNS:
            out[column] = _numbers(values, column, where)
        elif column in TEXT_COLUMNS:
            out[column] = values.fillna("").astype(str)
        else:  # protocol-specific columns: as pandas reads them (numbers when all parse)
            out[column] = values
    if out[symbol].isna().any():
        raise DatasetError(f"{where(out[symbol].isna())}: column {symbol!r} is {MISSING!r}; "
                           f"every trial must name the {symbol} shown")
    if numeric:
        out[symbol] = out[symbol].astype("int64")
    for column in trial_columns(symbol=symbol):
        if column in out:
            continue
        if column in BOOL_COLUMNS:
            out[column] = False
        elif column in TEXT_COLUMNS:
            out[column] = ""
        elif column in INT_COLUMNS:
            out[column] = pd.Series(pd.NA, index=out.index, dtype="Int64")
        else:
            out[column] = np.nan
    problems = []
    answered = out["response"].notna() & out["correct"].notna()
    recomputed = (out["response"] == out[symbol]).astype("Float64").astype(float)
    disagree = answered & (recomputed != out["correct"])
    for number in pd.unique(out.loc[disagree, "_file"]):
        mask = disagree & (out["_file"] == number)
        first = out.loc[mask].iloc[0]
        problems.append(f"{where(mask)}: correct={first['correct']:g} disagrees with "
                        f"{symbol}={first[symbol]} response={first['response']} "
                        f"({int(mask.sum())} such row(s) in the file; possible tampering); "
                        f"'correct' recomputed from response and {symbol}")
    out.loc[disagree, "correct"] = recomputed[disagree]
    return out, problems


def _numbers(values: pd.Series, column: str, where) -> pd.Series:
    if pd.api.types.is_numeric_dtype(values) and not pd.api.types.is_bool_dtype(values):
        numbers = values.astype(float)
    else:
        numbers = pd.to_numeric(values, errors="coerce").astype(float)
    bad = (numbers.isna() & values.notna()) | np.isinf(numbers)
    if bad.any():
        value = values[bad].iloc[0]  # a numpy scalar as the Python value it holds
        value = value.item() if isinstance(value, np.generic) else value
        raise DatasetError(f"{where(bad)}: column {column!r}: expected a finite number or "
                           f"{MISSING!r}, got {value!r}")
    return numbers


def _order_columns(trials: pd.DataFrame) -> pd.DataFrame:
    symbol = symbol_column(trials.columns)
    first = ["dataset", "participant", "participant_id", "session"] + \
        list(trial_columns(symbol=symbol))
    rest = [c for c in trials.columns if c not in first]
    return trials[first + rest]
