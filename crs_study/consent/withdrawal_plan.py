"""What a withdrawal removes: exactly what BIDS names for the participant, never a text search.

In a dataset, for participant ``<label>`` (:func:`plan_withdrawal`):

* **paths** (moved out, then deleted): every directory or file whose name carries the entity
  ``sub-<label>`` (the name's ``_``-separated parts before its extension include it: the
  sessions, ``sourcedata/sub-<label>``, ``derivatives/<any pipeline>/sub-<label>``,
  ``..._desc-x.json`` files named for the participant), anywhere but inside another dataset
  nested outside ``derivatives/``;
* **rows**: the rows whose ``participant_id`` is ``sub-<label>`` in every participants-like
  TSV (any ``.tsv`` outside the ``sub-*`` folders whose header has a ``participant_id``
  column: ``participants.tsv``, a pipeline's own, ``phenotype/*.tsv``); the rest of each file
  is kept byte for byte;
* **analysis outputs** of crs-study (results computed from the participant's trials must not
  keep their data; the decision is to remove them and say "re-run crs-study analyze", not to
  re-run the analysis inside the withdrawal: a withdrawal must be quick and all or nothing,
  whereas an analysis needs its plan, may meet other problems in the data, and changes the
  study's numbers, which an analyst should do knowingly): every file recorded in the
  dataset's outputs record (:mod:`crs_study.dataset.outputs`) for a run that holds the
  participant, inside the dataset or anywhere else, when it still has the recorded sha256;
  and in ``derivatives/crs-study/`` every file no run recorded (written by older software or
  by hand: computed, as far as anyone can tell, from every participant), except the
  pipeline's ``dataset_description.json``;
* **notes**, for what it cannot reach: a recorded output changed since it was written, an
  analysis killed while writing (its files unknown), a folder no longer there, and other
  pipelines' files not named by participant (their group results, if any, are theirs to
  re-run).

Nothing is searched for the label's text: ``01`` never matches a date such as
``2026-01-05``, and another participant's files are never opened for writing.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

from crs_study._files import sha256_file
from crs_study.dataset import bids
from crs_study.dataset.outputs import read_outputs

#: Where a withdrawal in progress keeps the paths it moved (in the dataset, hidden).
STAGING_DIR = ".crs-study-withdrawal-staging"
#: Files of another pipeline's folder that describe it rather than hold results.
_DESCRIPTIVE = ("dataset_description.json", "README", "CHANGES", "LICENSE")


@dataclass(frozen=True)
class DatasetWithdrawal:
    """What withdrawing ``participant`` does to one dataset (the module docstring).

    ``paths`` are relative to the dataset (each with its reason in ``why``); ``rows`` the
    relative TSVs losing the participant's rows; ``outputs`` absolute files outside the
    dataset; ``output_runs`` the recorded analysis runs whose files go; ``notes`` what the
    withdrawal cannot deal with itself.
    """

    dataset: Path
    participant: str
    paths: tuple[str, ...] = ()
    why: dict[str, str] = field(default_factory=dict)
    rows: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    output_runs: tuple[str, ...] = ()
    output_dirs: tuple[str, ...] = ()  # folders of ``outputs``, removed when left empty
    notes: tuple[str, ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.paths or self.rows or self.outputs)

    @property
    def removes_results(self) -> bool:
        """Whether analysis results go (then the analysis must be run again)."""
        return bool(self.outputs) or any(w.startswith("analysis") for w in self.why.values())

    def lines(self) -> list[str]:
        """The plan as the command line prints it, one action a line."""
        out = [f"remove {path}  ({self.why.get(path, 'named for the participant')})"
               for path in self.paths]
        out += [f"remove the rows of sub-{self.participant} from {path}" for path in self.rows]
        out += [f"remove {path}  (analysis output outside the dataset)" for path in self.outputs]
        out += [f"note: {note}" for note in self.notes]
        return out

    def to_dict(self) -> dict:
        return {"dataset": str(self.dataset), "participant": self.participant,
                "paths": list(self.paths), "why": dict(self.why), "rows": list(self.rows),
                "outputs": list(self.outputs), "output_runs": list(self.output_runs),
                "output_dirs": list(self.output_dirs), "notes": list(self.notes)}

    def to_frame(self):
        """One row per action: ``action`` (remove, rows, note), ``path``, ``reason``."""
        import pandas as pd  # only here: sessions and withdrawals need no pandas

        rows = [("remove", p, self.why.get(p, "")) for p in self.paths]
        rows += [("rows", p, f"participant_id sub-{self.participant}") for p in self.rows]
        rows += [("remove", p, "analysis output outside the dataset") for p in self.outputs]
        rows += [("note", "", n) for n in self.notes]
        return pd.DataFrame(rows, columns=["action", "path", "reason"])


def names_participant(name: str, participant: str) -> bool:
    """Whether a file or folder name carries the BIDS entity ``sub-<participant>``."""
    stem = name.split(".", 1)[0]
    return f"sub-{participant}" in stem.split("_")


def _nested_dataset(child: Path, derivatives: Path) -> bool:
    return ((child / bids.DATASET_DESCRIPTION).is_file()
            and derivatives not in child.parents and child != derivatives)


def named_paths(dataset: Path, participant: str) -> list[Path]:
    """Every path of ``dataset`` named for the participant (outermost only)."""
    derivatives = dataset / bids.DERIVATIVES
    found = []
    for root, dirs, files in os.walk(dataset):
        root_path = Path(root)
        for name in list(dirs):
            child = root_path / name
            if name == STAGING_DIR or _nested_dataset(child, derivatives):
                dirs.remove(name)
            elif names_participant(name, participant):
                found.append(child)
                dirs.remove(name)
        found += [root_path / name for name in files if names_participant(name, participant)]
    return found


def participant_rows(dataset: Path, participant: str) -> list[Path]:
    """The participants-like TSVs holding a row of the participant (``participant_id``)."""
    derivatives = dataset / bids.DERIVATIVES
    found = []
    for root, dirs, files in os.walk(dataset):
        root_path = Path(root)
        dirs[:] = [d for d in dirs if not (d.startswith(("sub-", ".")) or d == STAGING_DIR
                                           or _nested_dataset(root_path / d, derivatives))]
        for name in files:
            if name.endswith(".tsv") and not name.startswith("."):
                path = root_path / name
                if any(is_row for is_row in _row_flags(path, participant)):
                    found.append(path)
    return found


def _row_flags(path: Path, participant: str) -> list[bool]:
    """For each data row of a TSV with a ``participant_id`` column: is it the
    participant's? (Empty for any other TSV, or one that cannot be read.)"""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return []
    lines = text.splitlines()
    if not lines:
        return []
    header = lines[0].split("\t")
    if "participant_id" not in header:
        return []
    column = header.index("participant_id")
    flags = []
    for line in lines[1:]:
        cells = line.split("\t")
        flags.append(len(cells) > column and cells[column].strip() == f"sub-{participant}")
    return flags


def without_rows(text: str, participant: str) -> str:
    """A participants-like TSV's text without the participant's rows (others byte for byte)."""
    lines = text.splitlines(keepends=True)
    if not lines:
        return text
    header = next(csv.reader(io.StringIO(lines[0]), delimiter="\t"))
    if "participant_id" not in header:
        return text
    column = header.index("participant_id")

    def is_row(line: str) -> bool:
        cells = line.rstrip("\r\n").split("\t")
        return len(cells) > column and cells[column].strip() == f"sub-{participant}"

    return lines[0] + "".join(line for line in lines[1:] if not is_row(line))


def plan_withdrawal(dataset: str | Path, participant: str) -> DatasetWithdrawal:
    """What withdrawing ``participant`` removes from ``dataset`` (module docstring); reads
    only, writes nothing."""
    dataset = Path(dataset)
    why: dict[Path, str] = {p: "named for the participant"
                            for p in named_paths(dataset, participant)}
    outputs, runs, notes, folders = [], [], [], set()
    recorded: set[Path] = set()
    root = dataset.resolve()
    for run in read_outputs(dataset):
        files = run.files or {}
        recorded.update(Path(f) for f in files)
        if participant not in run.participants:
            continue
        if run.files is None:
            notes.append(f"an analysis writing to {run.out} (begun {run.time}) was "
                         "interrupted before it recorded its files: check that folder by hand "
                         f"for results holding sub-{participant}")
            continue
        runs.append(run.id)
        for name, digest in files.items():
            path = Path(name)
            if not path.exists() or path.name == bids.DATASET_DESCRIPTION:
                continue  # a pipeline's description holds no one's data
            if not os.access(path.parent, os.W_OK):
                notes.append(f"{path}: an analysis output holding sub-{participant} that "
                             "cannot be removed (no write permission): delete it by hand")
            elif sha256_file(path) != digest:
                notes.append(f"{path}: changed since crs-study analyze wrote it ({run.time}), "
                             f"so it was left; if it holds sub-{participant}'s data, delete it")
            elif root in path.parents:
                why[dataset / path.relative_to(root)] = "analysis output holding the participant"
            else:
                outputs.append(str(path))
                folders.update(p for p in (path.parent, *path.parent.parents)
                               if p == run.out or run.out in p.parents)
    pipeline = bids.derivatives_dir(dataset)
    if pipeline.is_dir():
        for path in _unrecorded_outputs(pipeline, recorded, participant):
            why.setdefault(path, "analysis output not recorded (computed from every "
                                 "participant)")
    for folder in sorted((dataset / bids.DERIVATIVES).glob("*")):
        if folder.is_dir() and folder.name != bids.PIPELINE and _group_files(folder):
            notes.append(f"{folder.relative_to(dataset)}: files of another pipeline not named "
                         "by participant were left; if they were computed from "
                         f"sub-{participant}'s data, re-run that pipeline")
    paths = _outermost(dataset, why)
    rows = [str(p.relative_to(dataset)) for p in participant_rows(dataset, participant)]
    return DatasetWithdrawal(
        dataset, participant, tuple(paths), {p: _reason(dataset, p, why) for p in paths},
        tuple(sorted(rows)), tuple(sorted(outputs)), tuple(runs),
        tuple(sorted(map(str, folders), key=lambda f: (-len(Path(f).parts), f))), tuple(notes))


def _unrecorded_outputs(pipeline: Path, recorded: set[Path], participant: str) -> list[Path]:
    """Files of crs-study's pipeline folder that no analysis run recorded (module docstring)."""
    found = []
    for root, dirs, files in os.walk(pipeline):
        root_path = Path(root)
        dirs[:] = [d for d in dirs if not d.startswith(("sub-", "."))]
        for name in files:
            path = root_path / name
            if name.startswith(".") or (root_path == pipeline
                                        and name == bids.DATASET_DESCRIPTION):
                continue
            if names_participant(name, participant) or path.resolve() in recorded:
                continue
            found.append(path)
    return found


def _group_files(folder: Path) -> bool:
    for _root, dirs, files in os.walk(folder):
        dirs[:] = [d for d in dirs if not d.startswith(("sub-", "."))]
        if any(not name.startswith((".", *_DESCRIPTIVE)) for name in files):
            return True
    return False


def _outermost(dataset: Path, why: dict[Path, str]) -> list[str]:
    """Relative paths, sorted; a folder every file of which goes is named instead of them."""
    chosen = set(why)
    changed = True
    while changed:  # fold whole folders up, innermost first
        changed = False
        parents = {p.parent for p in chosen} - {dataset}
        for folder in sorted(parents, key=lambda p: -len(p.parts)):
            if folder in chosen or folder.parent in (dataset, dataset / bids.DERIVATIVES) \
                    or dataset not in folder.parents:
                continue  # never a top-level folder (sourcedata) or a pipeline's own
            entries = list(folder.iterdir())
            if entries and all(e in chosen for e in entries):
                chosen -= set(entries)
                chosen.add(folder)
                why[folder] = why[entries[0]]
                changed = True
    relative = sorted({p.relative_to(dataset) for p in chosen})
    return [str(p) for p in relative if not any(q in p.parents for q in relative)]


def _reason(dataset: Path, relative: str, why: dict[Path, str]) -> str:
    return why.get(dataset / relative, "named for the participant")
