"""What a dataset keeps that shows a session existed, so a session gone missing is noticed.

The analysis reads the sessions it finds (:func:`crs_study.dataset.bids.find_sessions`, the
trial files); a session whose trial file was deleted, or whose whole ``sub-<id>/`` folder
was, would otherwise simply not be there. These traces outlive such a deletion, and each is
written by crs-study itself, so none can be there for a session that never began:

* ``participants.tsv``: a participant is added (under the dataset lock) just before the
  session's files are created, so each one listed has begun a session (a run that failed in
  between leaves a listed participant without one: the warning says "no session" and the
  experimenter knows which it is);
* the session's sidecar (``..._beh.json``): written right after the trial file's header;
* the session's frame log and torn-tail backups under ``sourcedata/sub-<id>/ses-<n>/``:
  the frames of each trial are written before its row;
* the record of analysis outputs (:mod:`crs_study.dataset.outputs`): the participants whose
  trials an earlier analysis held.

A withdrawal (:mod:`crs_study.consent`) removes all four for its participant (the row, the
files, the sourcedata, the label in the outputs record) and, while unfinished, keeps a
journal that stops the analysis; so a trace without a readable session is never what a
withdrawal leaves, and is reported (:func:`missing_sessions`). Deleting every trace as well
is not caught: the dataset cannot vouch for what it no longer holds.

A trial file that cannot be read at all (a folder or a named pipe in its place, an OS error,
bytes that are not UTF-8; :func:`read_trial_file`) is an :class:`UnreadableSession`: the
analysis leaves that session out with a warning naming the participant.

Not used: the count of arrivals (:data:`~crs_study.dataset.folder.ARRIVALS_FILE`). It holds
no labels (on purpose: a withdrawal must leave no label behind), and a withdrawal lowers the
participants without lowering it, so a count above the participants cannot tell a withdrawal
from a deletion.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Collection
from pathlib import Path

from crs_study._files import not_a_regular_file
from crs_study.dataset.bids import (
    PARTICIPANTS_TSV,
    SOURCEDATA,
    BidsName,
    SessionPaths,
    beh_files,
)
from crs_study.dataset.outputs import read_outputs
from crs_study.errors import DatasetError

#: A session as (participant, session label, task), the session "" for a dataset without
#: sessions.
SessionKey = tuple[str, str, str]


class UnreadableSession(DatasetError):
    """A session's trial file that cannot be read at all: the session is left out, with a
    warning (an error with ``strict``)."""


def read_trial_file(paths: SessionPaths) -> bytes:
    """The bytes of the session's trial file; :class:`UnreadableSession` (naming the participant)
    when it is not a regular file, cannot be read, or is not UTF-8 text."""
    tsv = paths.tsv
    why = not_a_regular_file(tsv)
    if why is None:
        try:
            data = tsv.read_bytes()
        except OSError as exc:
            why = exc.strerror or type(exc).__name__
        else:
            try:
                data.decode("utf-8")
            except UnicodeDecodeError as exc:
                why = f"not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})"
            else:
                return data
    session = "" if paths.session is None else f" ses-{paths.session}"
    raise UnreadableSession(f"{tsv}: the trial file of sub-{paths.participant}{session} cannot be "
                      f"read ({why}): participant {paths.participant!r}'s session is left out "
                      "of the analysis")


def session_traces(root: str | Path, task: str | None) -> dict[SessionKey, list[str]]:
    """Sessions of ``task`` (None: of every task) the dataset at ``root`` shows existed, each
    with the traces that show it (paths relative to ``root``): sidecars and files under
    ``sourcedata/``."""
    root = Path(root)
    found: dict[SessionKey, list[str]] = {}
    label = "*" if task is None else task
    patterns = (f"sub-*/ses-*/beh/sub-*_task-{label}_beh.json",
                f"sub-*/beh/sub-*_task-{label}_beh.json",
                f"{SOURCEDATA}/sub-*/ses-*/sub-*_task-{label}_*",
                f"{SOURCEDATA}/sub-*/sub-*_task-{label}_*")
    for pattern in patterns:
        for path in sorted(root.glob(pattern)):
            name = BidsName.parse(path.name)
            if name is None or name.task is None or task not in (None, name.task):
                continue
            key = (name.participant, name.session or "", name.task)
            found.setdefault(key, []).append(str(path.relative_to(root)))
    return found


def missing_sessions(root: str | Path, accounted: Collection[SessionKey], task: str | None
                     ) -> list[str]:
    """A warning for each session of ``task`` (None: of every task) or participant the
    dataset at ``root`` shows existed but ``accounted`` (the sessions read, or reported
    unreadable) does not hold; a participant with a trial file of another task has a
    session.

    One line each, naming the participant and the traces: a session with a trace is
    "missing (possible tampering)"; a participant of ``participants.tsv`` or of the outputs
    record with no session at all is named with where they are listed.
    """
    root = Path(root)
    warnings = []
    have = {participant for participant, _, _ in accounted}
    have |= {BidsName.parse(tsv.name).participant for tsv in beh_files(root, None)}
    traced = session_traces(root, task)
    for (participant, session, of_task), traces in sorted(traced.items()):
        if (participant, session, of_task) in accounted:
            continue
        where = f"sub-{participant}" + (f" ses-{session}" if session else "")
        shown = ", ".join(traces[:3]) + (f" and {len(traces) - 3} more" if len(traces) > 3
                                         else "")
        warnings.append(f"{root}: {where} has no trial file, though {shown} show(s) the "
                        "session was recorded: its trials are missing (possible tampering: "
                        "deleted by hand?); restore them from a backup, or withdraw the "
                        "participant with crs-study consent withdraw")
    gone = {participant for participant, _, _ in traced} | have
    listed, unread = _listed(root)
    warnings += unread
    for participant, source in listed:
        if participant in gone:
            continue
        gone.add(participant)
        warnings.append(f"{root}: participant {participant!r} is listed in {source} but has "
                        f"no readable session (sub-{participant}/ missing or unreadable): "
                        "their trials are missing (possible tampering: deleted by hand?); "
                        "restore them from a backup, or withdraw the participant with "
                        "crs-study consent withdraw")
    return warnings


def _listed(root: Path) -> tuple[list[tuple[str, str]], list[str]]:
    """(participant, where listed): ``participants.tsv`` first, then the outputs record; and
    a warning when ``participants.tsv`` cannot be read (its column ``participant_id`` is all
    it needs: BIDS requires no other, and other tools write no other)."""
    listed, warnings = [], []
    table = root / PARTICIPANTS_TSV
    if table.exists():
        why = not_a_regular_file(table)
        try:
            rows = [] if why else list(csv.reader(
                io.StringIO(table.read_text(encoding="utf-8")), delimiter="\t"))
        except (OSError, UnicodeDecodeError) as exc:
            why = str(exc)
        if why is None and (not rows or "participant_id" not in rows[0]):
            why = "no participant_id column"
        if why is not None:
            warnings.append(f"{table}: cannot read the participants table ({why}), so a "
                            "listed participant whose sessions are missing is not noticed")
        else:
            column = rows[0].index("participant_id")
            listed += [(row[column].removeprefix("sub-"), PARTICIPANTS_TSV)
                       for row in rows[1:] if len(row) > column and row[column]]
    for output in read_outputs(root):
        listed += [(label, f"the record of analysis outputs (an analysis of {output.time} "
                    f"in {output.out})") for label in output.participants]
    return listed, warnings
