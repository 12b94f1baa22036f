"""The sidecar of a session beginning now, or resumed now: its history carried over.

A resumed session keeps the stored sidecar's resumes, faults and interruptions and adds this
run's resume; a stored sidecar that still said ``running`` means the run before ended without
a word (killed, a power cut, a crash), recorded as a ``crash`` interruption with whether its
trial had begun.
"""

from __future__ import annotations

from crs_study import __version__
from crs_study.dataset.lock_file import PlanLock
from crs_study.dataset.session_metadata import (
    Fault,
    Interruption,
    Resume,
    SessionMetadata,
    now_utc,
)
from crs_study.paths import recorded_path
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import TrialPlan
from crs_study.session.resume import Fingerprints
from crs_study.session.spec import SessionSpec


def session_metadata(spec: SessionSpec, protocol: Protocol, plan: TrialPlan, device_text: str,
                     expected: Fingerprints, stored: SessionMetadata | None, clock_kind: str,
                     responder_name: str, n_trials: int, first: int, began: int | None,
                     lock: PlanLock | None = None) -> SessionMetadata:
    """The sidecar of a session beginning now, or resumed now from ``stored`` at trial
    ``first`` (the plan index of the next trial to play: the number of rows stored, unless a
    staircase skipped trials); ``began`` is the trial the previous run noted as begun.
    ``lock`` is the protocol's plan lock now; a resumed session keeps the one it began under
    (none when it began before the lock)."""
    resumes: tuple[Resume, ...] = ()
    faults: tuple[Fault, ...] = ()
    interruptions: tuple[Interruption, ...] = ()
    if stored is not None:
        resumes = (*stored.resumes, Resume(now_utc(), first, spec.device_url, __version__))
        faults = stored.faults
        interruptions = stored.interruptions
        if stored.status == "running":  # the run before this one ended without a word
            cut = began is None or began >= first
            interruptions += (Interruption(
                now_utc(), first, "crash",
                f"found on resume: the sidecar still said 'running' (the process was killed, "
                f"the power cut or it crashed) with {first} trial(s) stored; trial {first} "
                + ("had begun" if began is not None and cut else
                   "had not begun" if not cut else "may have begun (nothing noted)"),
                cut),)
    symbol_set = protocol.symbol_set
    return SessionMetadata(
        task_name=symbol_set.task,
        task_description=symbol_set.description,
        instructions=symbol_set.instructions,
        protocol_text=protocol.text,
        protocol_sha256=protocol.sha256,
        protocol_path=recorded_path(protocol.path),
        study_id=protocol.study_id,
        study_version=protocol.version,
        device_file_text=device_text,
        device_file_sha256=expected["DeviceFileSha256"],
        device_url=spec.device_url,
        software_version=__version__,
        seed=int(plan.seed),
        counterbalance=int(plan.counterbalance),
        plan_sha256=expected["PlanSha256"],
        # a session begun before the fingerprint existed cannot be vouched for: none recorded
        stimulus_sha256=(expected["StimulusSha256"]
                         if stored is None or stored.stimulus_sha256 is not None else None),
        participant=spec.participant,
        session=spec.session,
        consent_form_version=protocol.consent_form_version,
        responder=responder_name,
        clock=clock_kind,  # real or virtual (choose_clock)
        frame_rate_hz=float(protocol.frame_rate_hz),
        start_time=stored.start_time if stored is not None else now_utc(),
        end_time=None,
        status="running",
        trials_planned=n_trials,
        trials_completed=0,
        trials_sha256=None,
        resumes=resumes,
        faults=faults,
        interruptions=interruptions,
        plan_lock=(stored.plan_lock if stored is not None else
                   None if lock is None else lock.to_json()),
        plan_lock_sha256=(stored.plan_lock_sha256 if stored is not None else
                          None if lock is None else lock.sha256),
    )
