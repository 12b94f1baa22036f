"""What a session is asked to do (:class:`SessionSpec`) and how it ended (:class:`SessionResult`,
and for a dry-run's many sessions :class:`DryRunResult`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from crs_study._display import Display, Displayed
from crs_study.protocol.model import Protocol

#: Where a session reports its progress (one line at a time), e.g. to stderr.
Progress = Callable[[str], None]
#: How a session ended well: played to the end now, or found complete and left alone.
FINISHED = ("complete", "already-complete")


@dataclass(frozen=True)
class SessionSpec:
    """What ``crs-study run`` asks for.

    ``protocol`` is a protocol file, a shipped protocol's name or a
    :class:`~crs_study.protocol.Protocol` object (one changed in Python runs as
    :func:`~crs_study.protocol.load_protocol` settles it); ``dataset`` a folder (a string
    is taken as a path).
    """

    protocol: str | os.PathLike[str] | Protocol
    participant: str
    dataset: Path
    device_url: str = "sim://"
    session: int = 1
    responder: str = "keypad"
    clock: str = "auto"  # "real", "virtual" or "auto" (virtual for sim:// with a simulation)
    counterbalance: int | None = None
    consent_register: Path | None = None
    #: fsync every trial (True) or only when the session stops (dry-runs: see SessionStore)
    durable: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "dataset", Path(self.dataset))


@dataclass(frozen=True, repr=False)
class SessionResult(Displayed):
    """How a run ended."""

    status: str  # "complete", "interrupted" or "already-complete"
    participant: str
    session: int
    trials_planned: int
    trials_completed: int
    trials_run: int  # trials played by this invocation
    late_frames: int
    session_seconds: float  # session time covered by this invocation
    wall_seconds: float
    tsv: Path
    sidecar: Path
    message: str = ""

    def _display(self) -> Display:
        return Display(f"SessionResult of {self.participant!r}, session {self.session}", (
            ("status", self.status),
            ("trials", f"{self.trials_completed} of {self.trials_planned} "
                       f"({self.trials_run} by this run)"),
            ("late frames", str(self.late_frames)), ("trials file", os.fspath(self.tsv))),
            (self.message,) if self.message else (), ".to_dict()")

    def to_dict(self) -> dict:
        """The fields as plain JSON values (paths as strings)."""
        return {k: os.fspath(v) if isinstance(v, Path) else v for k, v in asdict(self).items()}


@dataclass(frozen=True, repr=False)
class DryRunResult(Displayed, Sequence[SessionResult]):
    """The sessions of a dry-run (:func:`crs_study.session.dry_run`), in participant order.

    A sequence of :class:`SessionResult` (``len``, indexing, unpacking), with the dataset
    they were stored in and the totals ``crs-study dry-run`` prints.
    """

    dataset: Path
    sessions: tuple[SessionResult, ...]

    def __getitem__(self, index):
        return self.sessions[index]

    def __len__(self) -> int:
        return len(self.sessions)

    def _display(self) -> Display:
        statuses: dict[str, int] = {}
        for r in self.sessions:
            statuses[r.status] = statuses.get(r.status, 0) + 1
        return Display(f"DryRunResult of {len(self.sessions)} simulated participants", (
            ("dataset", os.fspath(self.dataset)), ("trials", str(self.trials)),
            ("sessions", ", ".join(f"{n} {s}" for s, n in statuses.items()))),
            tuple(r.message for r in self.sessions if r.message), ".to_frame(), [i]")

    @property
    def trials(self) -> int:
        """Trials stored in the sessions (completed, by this run or an earlier one)."""
        return sum(r.trials_completed for r in self.sessions)

    @property
    def session_seconds(self) -> float:
        """Session time this run covered (simulated time on a virtual clock)."""
        return sum(r.session_seconds for r in self.sessions)

    @property
    def finished(self) -> bool:
        """Every session complete (now or before); False when one was interrupted."""
        return all(r.status in FINISHED for r in self.sessions)

    def to_frame(self):
        """One row per session: the fields of :class:`SessionResult` (paths as strings)."""
        import pandas as pd  # only here: a session needs no pandas

        return pd.DataFrame([r.to_dict() for r in self.sessions],
                            columns=[*SessionResult.__dataclass_fields__])

    def to_dict(self) -> dict:
        """The summary ``crs-study dry-run --json`` prints."""
        return {"dataset": os.fspath(self.dataset), "participants": len(self.sessions),
                "trials": self.trials, "session_seconds": self.session_seconds,
                "sessions": [{"participant": r.participant, "status": r.status,
                              "trials_completed": r.trials_completed,
                              "late_frames": r.late_frames} for r in self.sessions]}

    def to_json(self) -> str:
        return json.dumps(self.to_dict())
