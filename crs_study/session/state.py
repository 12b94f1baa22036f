"""The mutable state of one run of a session, and the sidecar write that records it."""

from __future__ import annotations

import contextlib
import signal
from dataclasses import dataclass, field, replace

from crs_study.adaptive import AdaptiveRun
from crs_study.dataset.session_metadata import Interruption, SessionMetadata, Status, now_utc
from crs_study.dataset.session_store import SessionStore
from crs_study.errors import CrsStudyError
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import TrialPlan
from crs_study.session.spec import SessionSpec
from crs_study.signals import handling


@dataclass
class SessionState:
    """Mutable state of one run."""

    spec: SessionSpec
    protocol: Protocol
    layout: Layout
    plan: TrialPlan
    store: SessionStore
    metadata: SessionMetadata
    rows: list[dict[str, str]]
    faults: set[int] = field(default_factory=set)
    late_frames: int = 0
    in_trial: bool = False  # a device fault now interrupts a trial (rerun with device_fault)
    adaptive: AdaptiveRun | None = None  # the blocks' procedures ([adaptive] protocols)
    #: the procedures' fingerprint after ``rows`` (set with each stored row)
    adaptive_sha256: str | None = None
    #: the trial whose stimulus has begun and whose row is not yet stored (None between)
    started: int | None = None
    #: trials an earlier run cut after their stimulus began (their rows say rerun = 1)
    cut: set[int] = field(default_factory=set)


def record_interruption(state: SessionState, cause: str, detail: str) -> None:
    """Add why the session stops now to its sidecar's ``Interruptions`` (saved by the next
    :func:`save`); the trial is cut when its stimulus had begun."""
    cut = state.started is not None
    # the trial cut (its plan index: an adaptive staircase may have skipped trials), else
    # the number of trials stored
    at = state.started if cut else len(state.rows)
    entry = Interruption(now_utc(), at, cause, detail.splitlines()[0] if detail else "", cut)
    state.metadata = replace(state.metadata,
                             interruptions=(*state.metadata.interruptions, entry))


def ignore_interrupts() -> contextlib.AbstractContextManager[None]:
    """Ignore Ctrl-C while the session is being put safely to rest."""
    return handling(signal.SIG_IGN, (signal.SIGINT,))


def save(state: SessionState, status: Status, final: bool = False) -> None:
    """Rewrite the sidecar; ``final`` (start, stop) also fsyncs the session's files."""
    if final:
        state.store.sync()
    state.metadata = state.metadata.with_progress(
        status, len(state.rows), state.store.trials_sha256,
        now_utc() if status != "running" else None, state.adaptive_sha256)
    state.store.write_sidecar(state.metadata, final=final)


def save_after_failure(state: SessionState) -> None:
    """Mark the session interrupted while another error is on its way out.

    A failure here (the disk that just filled up) must not hide the first error: the TSV is
    the authority and the sidecar is brought up to date on resume, so it is let go.
    """
    with ignore_interrupts():
        try:
            save(state, "interrupted", final=True)
        except CrsStudyError:
            pass
