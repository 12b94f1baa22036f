"""The dataset's file layout (BIDS, datatype ``beh``): one module builds and parses every path.

The runner and the dataset writer (:mod:`crs_study.dataset`) build their paths here, and the
analysis finds sessions here, so the two sides cannot disagree on the layout::

    DATASET/
      dataset_description.json, participants.tsv, participants.json, README.md
      task-<task>_beh.json                                   column dictionary
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.tsv    one row per trial
      sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.json   session sidecar
      sub-<id>/ses-<n>/.sub-<id>_ses-<n>.lock                      the runner's lock
      sourcedata/sub-<id>/ses-<n>/sub-<id>_ses-<n>_task-<task>_frames.tsv.gz   frame log
      sourcedata/sub-<id>/ses-<n>/sub-<id>_ses-<n>_task-<task>_<what>-torn-<time>.bin
                                                             bytes cut from a torn tail
      derivatives/crs-study/                                 analysis outputs

A dataset without sessions (``sub-<id>/beh/sub-<id>_task-<task>_beh.tsv``, legal in BIDS and
written by other tools) is read too; crs-study itself always writes ``ses-<n>``.

File names follow the BIDS specification ("Common principles: file name structure"):
``key-label`` entities joined by ``_`` in the specification's order (``sub``, ``ses``,
``task``, ...), then ``_<suffix>`` and the extension; labels are alphanumeric.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from crs_study.dataset.schema import TASK
from crs_study.errors import DatasetError

DATASET_DESCRIPTION = "dataset_description.json"
PARTICIPANTS_TSV = "participants.tsv"
PARTICIPANTS_JSON = "participants.json"
DATASET_README = "README.md"
SOURCEDATA = "sourcedata"
DERIVATIVES = "derivatives"
#: The pipeline folder of crs-study's analysis outputs under ``derivatives/``.
PIPELINE = "crs-study"

_LABEL = r"[A-Za-z0-9]+"
_LABEL_RE = re.compile(_LABEL)
_NAME_RE = re.compile(rf"(?P<entities>sub-{_LABEL}(?:_{_LABEL}-{_LABEL})*)"
                      rf"_(?P<suffix>{_LABEL})(?P<extension>(?:\.[A-Za-z0-9]+)+)")


def task_sidecar_name(task: str = TASK) -> str:
    """The dataset-level column dictionary's name, ``task-<task>_beh.json``."""
    return f"task-{task}_beh.json"


def derivatives_dir(root: str | Path, pipeline: str = PIPELINE) -> Path:
    """Where a pipeline's outputs go: ``DATASET/derivatives/<pipeline>``."""
    return Path(root) / DERIVATIVES / pipeline


@dataclass(frozen=True)
class BidsName:
    """A BIDS file name taken apart: entities in order, suffix and extension.

    ``BidsName.parse("sub-p01_ses-1_task-digitid_beh.tsv")`` has ``participant`` ``"p01"``,
    ``session`` ``"1"``, ``task`` ``"digitid"``, ``suffix`` ``"beh"``, ``extension``
    ``".tsv"``; :attr:`name` puts it back together.
    """

    entities: tuple[tuple[str, str], ...]
    suffix: str
    extension: str

    @classmethod
    def parse(cls, name: str) -> BidsName | None:
        """The parts of ``name``, or None when it is not a BIDS file name (or repeats a key)."""
        match = _NAME_RE.fullmatch(name)
        if match is None:
            return None
        pairs = tuple(tuple(part.split("-", 1)) for part in match["entities"].split("_"))
        if len({key for key, _ in pairs}) != len(pairs):
            return None
        return cls(pairs, match["suffix"], match["extension"])

    def get(self, key: str) -> str | None:
        return dict(self.entities).get(key)

    @property
    def participant(self) -> str:
        return dict(self.entities)["sub"]

    @property
    def session(self) -> str | None:
        return self.get("ses")

    @property
    def task(self) -> str | None:
        return self.get("task")

    @property
    def name(self) -> str:
        return "_".join(f"{k}-{v}" for k, v in self.entities) + f"_{self.suffix}{self.extension}"


def _check_label(kind: str, label: str) -> str:
    if not isinstance(label, str) or not _LABEL_RE.fullmatch(label):
        raise DatasetError(f"{kind} label {label!r} is not valid: BIDS labels are letters and "
                           "digits only")
    return label


@dataclass(frozen=True)
class SessionPaths:
    """Where one session's files live (``session`` None: a dataset without sessions).

    The writer uses whole-number sessions (``ses-1``); a reader may meet any BIDS label. A
    label that is a whole number >= 1 written plainly (``"2"``, not ``"02"``) is stored as
    that number, so ``SessionPaths(root, "a", "2") == SessionPaths(root, "a", 2)``.
    """

    root: Path
    participant: str
    session: int | str | None
    task: str = TASK

    def __post_init__(self) -> None:
        _check_label("participant", self.participant)
        if self.session is not None:
            label = _check_label("session", str(self.session))
            if label.isdigit() and label == str(int(label)) and int(label) >= 1:
                object.__setattr__(self, "session", int(label))  # "2" and 2: one session
        _check_label("task", self.task)

    @classmethod
    def from_beh_file(cls, tsv: str | Path) -> SessionPaths:
        """The session of a ``..._beh.tsv`` inside a dataset, from its name and folders.

        The file must sit where its name says (``sub-<id>[/ses-<n>]/beh/``); the dataset's
        root is the folder above ``sub-<id>``. Anything else is a one-line
        :class:`~crs_study.errors.DatasetError`.
        """
        tsv = Path(tsv)
        parsed = BidsName.parse(tsv.name)
        if parsed is None or parsed.suffix != "beh" or parsed.extension != ".tsv" \
                or parsed.task is None:
            raise DatasetError(f"{tsv}: not a session's trial file (expected "
                               "sub-<id>[_ses-<n>]_task-<task>_beh.tsv)")
        session = parsed.session
        levels = 3 if session is not None else 2
        if len(tsv.parents) <= levels:
            raise DatasetError(f"{tsv}: expected the file inside a dataset's "
                               f"sub-<id>/{'ses-<n>/' if session else ''}beh/ folder")
        paths = cls(tsv.parents[levels], parsed.participant, session, parsed.task)
        if paths.tsv != tsv:
            raise DatasetError(f"{tsv}: the file name says sub-{parsed.participant}"
                               f"{f' ses-{session}' if session else ''} but it is stored in "
                               f"{tsv.parent}; expected {paths.tsv.parent}")
        return paths

    @property
    def stem(self) -> str:
        """``sub-<id>_ses-<n>_task-<task>`` (no ``ses`` without a session)."""
        session = "" if self.session is None else f"_ses-{self.session}"
        return f"sub-{self.participant}{session}_task-{self.task}"

    @property
    def participant_dir(self) -> Path:
        return self.root / f"sub-{self.participant}"

    @property
    def session_dir(self) -> Path:
        if self.session is None:
            return self.participant_dir
        return self.participant_dir / f"ses-{self.session}"

    @property
    def beh_dir(self) -> Path:
        return self.session_dir / "beh"

    @property
    def tsv(self) -> Path:
        return self.beh_dir / f"{self.stem}_beh.tsv"

    @property
    def sidecar(self) -> Path:
        return self.beh_dir / f"{self.stem}_beh.json"

    @property
    def lock(self) -> Path:
        """The runner's lock: hidden, ``.lock``, inside ``sub-<id>/`` (consent withdrawal
        looks for such files to refuse a running session)."""
        session = "" if self.session is None else f"_ses-{self.session}"
        return self.session_dir / f".sub-{self.participant}{session}.lock"

    @property
    def source_dir(self) -> Path:
        return self.root / SOURCEDATA / self.session_dir.relative_to(self.root)

    @property
    def frame_log(self) -> Path:
        return self.source_dir / f"{self.stem}_frames.tsv.gz"

    def torn_backup(self, what: str, stamp: str) -> Path:
        """Where the bytes cut from a torn tail of the ``what`` file (``beh``, ``frames``)
        are kept, ``stamp`` being the time of the cut."""
        return self.source_dir / f"{self.stem}_{what}-torn-{stamp}.bin"


def beh_files(root: str | Path, task: str | None = TASK) -> list[Path]:
    """Every session's trial file (``_beh.tsv``) of ``task`` (None: of every task) in the
    dataset at ``root``.

    Sessions first (``sub-*/ses-*/beh/``, sorted), then sessionless participants
    (``sub-*/beh/``, sorted). A missing dataset folder is an empty list.
    """
    root = Path(root)
    label = "*" if task is None else task
    files = sorted(root.glob(f"sub-*/ses-*/beh/sub-*_ses-*_task-{label}_beh.tsv"))
    files += sorted(root.glob(f"sub-*/beh/sub-*_task-{label}_beh.tsv"))
    return files


def find_sessions(root: str | Path, task: str | None = TASK) -> list[SessionPaths]:
    """The sessions of ``task`` (None: of every task) stored in the dataset at ``root``, in
    :func:`beh_files` order.

    A trial file stored elsewhere than its name says is a one-line
    :class:`~crs_study.errors.DatasetError` (a file moved by hand).
    """
    return [SessionPaths.from_beh_file(tsv) for tsv in beh_files(root, task)]


def session_numbers(root: str | Path, participant: str) -> list[int]:
    """The whole-number sessions (``ses-<n>`` folders) of ``participant``, sorted."""
    base = Path(root) / f"sub-{_check_label('participant', participant)}"
    found = []
    for path in base.glob("ses-*"):
        suffix = path.name.removeprefix("ses-")
        if suffix.isdigit():
            found.append(int(suffix))
    return sorted(found)
