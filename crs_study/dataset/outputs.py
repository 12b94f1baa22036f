"""Analysis outputs written from a dataset, recorded so that a withdrawal can reach each one.

``crs-study analyze`` may write its results anywhere (``--out DIR``), so the dataset keeps a
record of every output computed from it, in :data:`OUTPUTS_REGISTRY` at its top (a hidden
file, one JSON object per line, appended with one ``write`` each)::

    {"event": "writing", "id": ..., "time": ..., "out": "/abs/DIR", "participants": [...]}
    {"event": "written", "id": ..., "files": {"/abs/DIR/results.json": "<sha256>", ...}}

The first line is appended before any output file is written, the second once all are: an
analysis killed in between leaves a ``writing`` line alone, which names the folder and the
participants even though its files are unknown. ``participants`` are the labels of *this*
dataset whose trials the outputs hold (an analysis of several datasets records in each).

A withdrawal (:mod:`crs_study.consent.withdrawal`) reads the record: each file of an output
holding the participant is removed when it still has the recorded sha256 (otherwise it was
overwritten since, or edited, and is named instead of removed), and the record is then
rewritten without the participant's label.
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from crs_study._files import (
    append_durably,
    not_a_regular_file,
    os_errors,
    sha256_file,
    write_atomically,
)
from crs_study.dataset.folder import Dataset, utc_now
from crs_study.errors import DatasetError

#: The record of analysis outputs, at the dataset's top (hidden: not part of the BIDS layout).
OUTPUTS_REGISTRY = ".crs-study-outputs.jsonl"


@dataclass(frozen=True)
class AnalysisOutput:
    """One analysis run's outputs as recorded: where, from whom, which files (path ->
    sha256; None while the run had not finished writing)."""

    id: str
    time: str
    out: Path
    participants: tuple[str, ...]
    files: dict[str, str] | None = field(default=None)

    def to_dict(self) -> dict:
        return {"id": self.id, "time": self.time, "out": str(self.out),
                "participants": list(self.participants), "files": self.files}


def registry_path(dataset: str | Path) -> Path:
    return Path(dataset) / OUTPUTS_REGISTRY


def read_outputs(dataset: str | Path) -> list[AnalysisOutput]:
    """Every output recorded for ``dataset``, oldest first; a malformed line is one-line
    :class:`DatasetError` (never skipped: a withdrawal must not miss an output)."""
    path = registry_path(dataset)
    if not path.exists():
        return []
    why = not_a_regular_file(path)
    if why is not None:  # a named pipe would block the reader (and a withdrawal) for ever
        raise DatasetError(f"{path}: cannot read the record of analysis outputs ({why})")
    with os_errors(DatasetError, "read", path):
        text = path.read_text(encoding="utf-8")
    runs: dict[str, AnalysisOutput] = {}
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
            kind, run_id = event["event"], str(event["id"])
            if kind == "writing":
                runs[run_id] = AnalysisOutput(
                    run_id, str(event["time"]), Path(event["out"]),
                    tuple(str(p) for p in event["participants"]),
                    _files(event.get("files")))
            elif kind == "written" and run_id in runs:
                old = runs[run_id]
                runs[run_id] = AnalysisOutput(old.id, old.time, old.out, old.participants,
                                              _files(event["files"]))
            else:
                raise ValueError(kind)
        except (ValueError, KeyError, TypeError, AttributeError):
            raise DatasetError(f"{path}:{number}: not a line of the analysis outputs record: "
                               f"{line[:60]!r}") from None
    return list(runs.values())


def _files(value: object) -> dict[str, str] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise TypeError(value)
    return {str(k): str(v) for k, v in value.items()}


def _append(dataset: Path, event: dict) -> None:
    path = registry_path(dataset)
    with os_errors(DatasetError, "record the analysis outputs in", path):
        append_durably(path, (json.dumps(event, sort_keys=True) + "\n").encode("utf-8"))


def participants_by_dataset(datasets: Iterable[str | Path], session_files: Iterable[tuple[str, str]]
                            ) -> dict[Path, list[str]]:
    """Each dataset folder -> the labels of the sessions (``(participant, file)`` pairs)
    stored in it."""
    pairs = [(label, Path(file).resolve()) for label, file in session_files]
    out = {}
    for dataset in map(Path, datasets):
        root = dataset.resolve()
        out[dataset] = sorted({label for label, file in pairs if root in file.parents})
    return out


class OutputsRecord:
    """Records one analysis run's outputs in each dataset it read (module docstring).

    ``participants`` maps each dataset's folder to the labels whose trials the outputs hold.
    :meth:`begin` before the first file is written, :meth:`done` with the files after.
    """

    def __init__(self, participants: Mapping[Path, Iterable[str]], out: str | Path) -> None:
        self.participants = {Path(d): sorted(set(labels)) for d, labels in participants.items()}
        self.out = Path(out).resolve()
        self.id = secrets.token_hex(8)

    def begin(self) -> None:
        """Record the run in each dataset before any output is written. A dataset that cannot
        be written (a read-only archive) keeps no record: no withdrawal can run there either,
        and whoever makes it writable again must look for copies of its results by hand."""
        self.participants = {d: labels for d, labels in self.participants.items()
                             if os.access(d, os.W_OK)}
        for dataset, labels in self.participants.items():
            with Dataset(dataset).locked():
                _append(dataset, {"event": "writing", "id": self.id, "time": utc_now(),
                                  "out": str(self.out), "participants": labels})

    def done(self, files: Iterable[str | Path]) -> None:
        hashes = {str(Path(f).resolve()): sha256_file(f) for f in files}
        for dataset in self.participants:
            with Dataset(dataset).locked():
                _append(dataset, {"event": "written", "id": self.id, "files": hashes})


def rewrite_without(dataset: str | Path, participant: str, gone: Iterable[str] = ()) -> None:
    """Rewrite the record without ``participant``'s label, dropping the runs ``gone`` (ids
    whose files were removed). Atomic; call under the dataset lock."""
    dataset = Path(dataset)
    path = registry_path(dataset)
    if not path.exists():
        return
    gone = set(gone)
    lines = []
    for run in read_outputs(dataset):
        if run.id in gone:
            continue
        kept = [p for p in run.participants if p != participant]
        lines.append(json.dumps({"event": "writing", "id": run.id, "time": run.time,
                                 "out": str(run.out), "participants": kept},
                                sort_keys=True))
        if run.files is not None:
            lines.append(json.dumps({"event": "written", "id": run.id, "files": run.files},
                                    sort_keys=True))
    with os_errors(DatasetError, "rewrite", path):
        write_atomically(path, "".join(line + "\n" for line in lines))
