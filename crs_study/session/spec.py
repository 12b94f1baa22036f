"""What a session is asked to do (:class:`SessionSpec`) and how it ended (:class:`SessionResult`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

#: Where a session reports its progress (one line at a time), e.g. to stderr.
Progress = Callable[[str], None]


@dataclass(frozen=True)
class SessionSpec:
    """What ``crs-study run`` asks for."""

    protocol: Path  # the protocol file, or a shipped protocol's name (crs_study.paths)
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


@dataclass(frozen=True)
class SessionResult:
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
