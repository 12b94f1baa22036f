"""The session runner: plays a protocol's trial plan on a device and stores every trial durably.

:func:`run_session` loads the protocol and plan (:func:`prepare`), asks everything that can
refuse the run before anything is written (the responder, the clock, the consent gate for a
real device, the resume checks of :mod:`crs_study.session.resume`), then opens the device and
plays the trials one by one (:mod:`crs_study.session.trials`); :mod:`crs_study.session.dry_run`
runs many simulated participants.

Session time: ``onset`` and ``trial_end`` are seconds since the session started, not counting
the time a session spent interrupted: a resumed session continues from the last stored
``trial_end``. Each trial ends on a whole millisecond of session time (so the stored value is
exact). On a virtual clock a resumed session first replays the stored trials' frames on the
fresh simulated device, without responder or writing, so the device's history (wire timing,
refresh phase, servo positions) is the uninterrupted run's; the rest of the session is then
bit for bit what an uninterrupted run writes: every column of every row and every frame log.

Consent: a session under a person's label passes the consent gate on every device and with
every responder, before anything is written, and again before every trial (a withdrawal
stops it at the next trial boundary, display neutral, session interrupted, one line saying
how to withdraw the data); only a simulated participant (a ``sim...`` label, a simulated
responder, ``sim://``) skips it (:mod:`crs_study.consent.gate`).

Pauses: the keypad's ``p`` pauses in place (display neutral, the trial under way played again
with ``rerun = 1``, the session goes on when the experimenter presses Space).

Failures: Ctrl-C (or the keypad's quit key, SIGTERM, or SIGHUP: the terminal closed) is a
safe pause: the display goes neutral, the session is marked ``interrupted`` and the run
returns status ``interrupted`` (exit 130). A :class:`~crs_study.errors.DeviceError` during a
trial (a board that stops answering the heartbeat included) marks the session interrupted,
records the fault in the sidecar, moves to neutral and is raised again as one line; the trial
is rerun on resume and its row then says ``device_fault = 1``. Every interruption's cause is
recorded in the sidecar's ``Interruptions`` (pause key, signal, device fault, consent
withdrawn, another error, or a crash found on resume: the sidecar still said ``running``); a
trial an interruption cut after its stimulus began is rerun with ``rerun = 1`` in its row.

Resume: the sidecar, the trial file and the frame log must agree beyond a torn last line
(:meth:`~crs_study.dataset.SessionStore.check_resumable`); any other disagreement is a
one-line refusal naming the file, before anything is changed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

from crs_study.clock import Clock, RealClock, VirtualClock
from crs_study.consent import read_form
from crs_study.consent.gate import ConsentGate, needs_consent
from crs_study.dataset import schema
from crs_study.dataset.bids import SessionPaths
from crs_study.dataset.folder import Dataset
from crs_study.dataset.lock_file import PlanLock
from crs_study.dataset.session_metadata import (
    Fault,
    SessionMetadata,
    now_utc,
)
from crs_study.dataset.session_store import SessionStore, sidecar_lag
from crs_study.device import Device, open_device
from crs_study.errors import ConsentError, DatasetError, DeviceError, SessionError
from crs_study.geometry.layout import Layout, device_file_path
from crs_study.protocol.loader import load_protocol
from crs_study.protocol.lock import current_lock
from crs_study.protocol.model import Protocol, consent_form_path
from crs_study.protocol.plan import TrialPlan, make_plan
from crs_study.rendering.feed_cap import WireSlack
from crs_study.session.adaptive import choose, next_to_play, rebuild
from crs_study.session.prompts import resume_prompt
from crs_study.session.responders import Responder, make_responder
from crs_study.session.responders.base import PauseInPlace
from crs_study.session.responders.keypad import PauseRequested, TerminalClosed
from crs_study.session.resume import (
    Fingerprints,
    check_frames,
    check_resume,
    check_rows,
    check_same_kind_of_run,
    fingerprints,
)
from crs_study.session.sidecar import session_metadata
from crs_study.session.spec import Progress, SessionResult, SessionSpec
from crs_study.session.state import (
    SessionState,
    ignore_interrupts,
    record_interruption,
    save,
    save_after_failure,
)
from crs_study.session.trials import TrialFrames, replay, run_trial, trial_frames
from crs_study.signals import describe, terminate_as_interrupt
from crs_study.stimuli.symbol_set import StimulusSet

#: Session time spent before the first trial with the display neutral (settled and flat).
SETTLE_S = 1.0


def device_file_text(layout: Layout, protocol: Protocol) -> str:
    """The device file's text, stored with the session."""
    for candidate in (layout.source, protocol.device):
        if candidate is None:
            continue
        path = device_file_path(candidate)
        if path.exists():
            return path.read_text(encoding="utf-8")
    raise SessionError(f"cannot find the device file {protocol.device!r} to store with the "
                       "session")


def choose_clock(spec: SessionSpec, responder: Responder) -> str:
    """``"real"`` or ``"virtual"``: the spec's clock, checked against responder and device."""
    if spec.clock not in ("real", "virtual", "auto"):
        raise SessionError(f"--clock must be real, virtual or auto, got {spec.clock!r}")
    if spec.clock == "auto":
        return "virtual" if spec.device_url.startswith("sim://") and responder.simulated \
            else "real"
    if spec.clock == "virtual" and responder.needs_real_clock:
        raise SessionError(f"the {responder.name} responder needs --clock real (a person answers "
                           "in real time)")
    if spec.clock == "virtual" and not simulated_url(spec.device_url):
        raise SessionError(f"--clock virtual needs the simulated device (sim://) or virtual "
                           f"boards (serial://lscsim://A,lscsim://B); {spec.device_url} moves "
                           "real servos in real time")
    return spec.clock


def simulated_url(url: str) -> bool:
    """True for a device with no real servos behind it: ``sim://`` or ``serial://`` whose every
    port is a virtual board (``lscsim://NAME``)."""
    if url.startswith("sim://"):
        return True
    ports = url[len("serial://"):].split(",") if url.startswith("serial://") else []
    return bool(ports) and all(p.startswith("lscsim://") for p in ports)


def prepare(spec: SessionSpec) -> tuple[Protocol, Layout, TrialPlan, Dataset]:
    """Load the protocol, layout and plan for ``spec`` (nothing is written)."""
    if not spec.device_url.startswith(("sim://", "serial://")):
        raise DeviceError(f"unknown device URL {spec.device_url!r}; expected "
                          "serial:///dev/ttyUSB0[,/dev/ttyUSB1] or sim://")
    dataset = Dataset(spec.dataset)
    dataset.session_paths(spec.participant, spec.session)  # checks label and session
    dataset.refuse_pending_withdrawal()  # before the gate: say what blocks the dataset itself
    protocol = load_protocol(spec.protocol)  # a file, a shipped name or a Protocol object
    dataset = Dataset(spec.dataset, task=dataset_task(protocol.symbol_set))
    layout = protocol.layout()
    known = dataset.participants() if (spec.dataset / "participants.tsv").exists() else {}
    if spec.participant in known:
        counterbalance = known[spec.participant]
        if spec.counterbalance is not None and spec.counterbalance != counterbalance:
            raise SessionError(
                f"participant {spec.participant!r} has counterbalance {counterbalance} in "
                f"{spec.dataset / 'participants.tsv'}; --counterbalance {spec.counterbalance} "
                "disagrees")
    elif spec.counterbalance is None:
        counterbalance = dataset.next_counterbalance() if spec.dataset.is_dir() else 0
    else:
        counterbalance = spec.counterbalance
    plan = make_plan(protocol, spec.participant, spec.session, counterbalance)
    return protocol, layout, plan, dataset


def dataset_task(symbol_set: StimulusSet) -> schema.Task:
    """What the dataset records about a stimulus set (:class:`crs_study.dataset.Task`)."""
    return schema.Task(label=symbol_set.task, title=symbol_set.title,
                       description=symbol_set.description, instructions=symbol_set.instructions,
                       noun=symbol_set.noun, column=symbol_set.column,
                       symbols=tuple(str(s) for s in symbol_set.symbols))


def session_columns(protocol: Protocol) -> tuple[str, ...]:
    """The session TSV's columns: the schema's with the set's symbol column, plus the level
    column when levels vary (and the adaptive columns when a procedure chooses them)."""
    levels = protocol.levels
    return schema.trial_columns(levels.column if levels is not None else None,
                                protocol.symbol_set.column,
                                adaptive=protocol.adaptive is not None)


def seed_check(spec: SessionSpec) -> dict[str, str | int]:
    """The seed and plan of ``spec``, checked against a stored session (nothing is written).

    A stored session whose seed, protocol, counterbalance, plan or device file differ is a
    :class:`SessionError` naming the difference.
    """
    protocol, layout, plan, dataset = prepare(spec)
    paths = dataset.session_paths(spec.participant, spec.session)
    device_text = device_file_text(layout, protocol)
    expected = fingerprints(protocol, plan, device_text, layout)
    stored = SessionStore(paths, columns=session_columns(protocol)).read_sidecar()
    if stored is not None:
        check_resume(stored, expected, paths.sidecar, device_text)
    return {
        "participant": spec.participant, "session": spec.session,
        "seed": expected["Seed"], "counterbalance": expected["Counterbalance"],
        "trials": len(plan.trials), "plan_sha256": expected["PlanSha256"],
        "protocol_sha256": expected["ProtocolSha256"],
        "stored": "none" if stored is None else
        f"{stored.status} ({stored.trials_completed}/{stored.trials_planned} trials), matches",
    }


@dataclass
class Opening:
    """What :func:`open_session` settled before anything is written: the protocol, its plan
    at this participant's counterbalance index, the responder, the clock, the consent gate
    (None for a simulated participant), the session's files and the fingerprints a stored
    session must match."""

    spec: SessionSpec
    protocol: Protocol
    layout: Layout
    plan: TrialPlan
    responder: Responder
    clock_kind: str
    gate: ConsentGate | None
    paths: SessionPaths
    device_text: str
    expected: Fingerprints
    store: SessionStore
    lock: PlanLock | None = None

    @property
    def n_trials(self) -> int:
        return len(self.plan.trials)


@dataclass
class Run:
    """A session opened or resumed by :func:`resume_session`, ready to play from the plan
    index ``first``: its state, device, clock and frames; ``resume_at`` is the session time
    the stored trials reached, ``origin`` the clock time of session time 0 and ``current``
    the plan index of the trial under way."""

    opening: Opening
    state: SessionState
    device: Device
    clock: Clock
    frames: TrialFrames
    first: int
    resume_at: float
    stored_before: int
    origin: float = 0.0
    current: int = 0


def run_session(spec: SessionSpec, *, progress: Progress | None = None,
                responder: Responder | None = None,
                device_options: dict[str, object] | None = None) -> SessionResult:
    """Run (or resume) one session; see the module docstring.

    Four steps: :func:`open_session` (everything that can refuse the run, before anything is
    written), :func:`resume_session` (the stored trials checked, the device opened, the
    sidecar marked running), :func:`play_trials` (trial by trial, every way of stopping
    recorded) and :func:`close_session` (the sidecar's final status and the result).
    """
    wall_start = time.perf_counter()
    opening = open_session(spec, responder)
    with opening.store:
        stored = opening.store.read_sidecar()
        if stored is not None:
            check_resume(stored, opening.expected, opening.paths.sidecar,
                         opening.device_text)
        if stored is not None and stored.is_complete:
            return already_complete(opening, stored)
        run = resume_session(opening, stored, device_options)
        status = play_trials(run, progress)
        return close_session(run, status, wall_start)


def open_session(spec: SessionSpec, responder: Responder | None = None) -> Opening:
    """Load the protocol and plan and ask everything that can refuse the run (responder,
    clock, consent gate) before anything is written: a typo must not take a counterbalance
    slot or leave an empty session behind. Then the participant is registered (their
    counterbalance index) and the session's store made (not yet opened)."""
    protocol, layout, plan, dataset = prepare(spec)
    if responder is None:
        responder = make_responder(spec.responder, seed=int(plan.seed), layout=layout,
                                   protocol=protocol)
    clock_kind = choose_clock(spec, responder)
    responder.check_ready()
    gate = None
    if needs_consent(spec.participant, spec.device_url, responder.simulated):
        # The gate comes before anything is written: no consent, no trace in the dataset.
        gate = ConsentGate(spec.consent_register, spec.participant,
                           protocol.consent_form_version,
                           read_form(consent_form_path(protocol)))
        gate.check()
    # a lock the protocol or its plan no longer match is refused before anything is written
    lock = current_lock(protocol)
    # The order of arrival is taken under the dataset lock: two runners adding participants
    # at once would otherwise both read the same count and share a counterbalance index.
    counterbalance = dataset.register_participant(spec.participant, spec.counterbalance)
    if counterbalance != int(plan.counterbalance):
        plan = make_plan(protocol, spec.participant, spec.session, counterbalance)
    paths = dataset.session_paths(spec.participant, spec.session)
    device_text = device_file_text(layout, protocol)
    expected = fingerprints(protocol, plan, device_text, layout)
    store = SessionStore(paths, columns=session_columns(protocol), durable=spec.durable)
    return Opening(spec, protocol, layout, plan, responder, clock_kind, gate, paths,
                   device_text, expected, store, lock)


def already_complete(o: Opening, stored: SessionMetadata) -> SessionResult:
    """A completed session is never rewritten: checked read-only (no torn-tail cut), then
    left alone."""
    rows = o.store.verify_complete(stored.trials_sha256)
    check_rows(rows, o.plan, o.paths.tsv, o.protocol.symbol_set.column,
               may_skip=o.protocol.adaptive is not None)
    if o.protocol.adaptive is not None:  # trials a finished staircase skipped
        rebuild(o.protocol, o.plan, rows, stored, o.paths.tsv, o.paths.sidecar, complete=True)
    elif len(rows) != o.n_trials:
        raise SessionError(
            f"{o.paths.sidecar}: the session is marked complete but holds {len(rows)} "
            f"of {o.n_trials} planned trials; a completed session is never rewritten: "
            "use another --session")
    spec = o.spec
    return SessionResult(
        "already-complete", spec.participant, spec.session, o.n_trials, o.n_trials, 0, 0,
        0.0, 0.0, o.paths.tsv, o.paths.sidecar,
        f"session {spec.session} of participant {spec.participant} is complete "
        f"({o.n_trials} trials) in {o.paths.tsv.parent}; nothing to do (a new session "
        "needs --session N)")


def resume_session(o: Opening, stored: SessionMetadata | None,
                   device_options: dict[str, object] | None = None) -> Run:
    """Begin the session, or resume it from what is stored: the stored trials checked
    against the plan and the frames, the adaptive procedures rebuilt, the sidecar's history
    extended, the device made (its options checked) and the sidecar marked ``running``."""
    spec, protocol, plan, paths, store = o.spec, o.protocol, o.plan, o.paths, o.store
    if stored is not None:
        check_same_kind_of_run(stored, spec, o.responder.name, o.clock_kind, paths.sidecar)
    # The sidecar lags the trial file by a row at most, or by the trials between two
    # sidecar writes of a session written without per-trial durability (a dry-run).
    lag = sidecar_lag(stored) if stored is not None else 1
    store.check_resumable(stored, sidecar_lag=lag)
    began = store.started_trial()  # what the previous run noted, before this one does
    rows = store.recover_rows()
    check_rows(rows, plan, paths.tsv, protocol.symbol_set.column,
               may_skip=protocol.adaptive is not None)
    adaptive = rebuild(protocol, plan, rows, stored, paths.tsv, paths.sidecar)
    first = next_to_play(plan, rows, adaptive)  # len(rows) unless a staircase skipped trials
    metadata = session_metadata(spec, protocol, plan, o.device_text, o.expected, stored,
                                o.clock_kind, o.responder.name, o.n_trials, first, began,
                                o.lock)
    clock: Clock = VirtualClock(start=-SETTLE_S) if o.clock_kind == "virtual" else RealClock()
    options = dict(device_options or {})
    if spec.device_url.startswith("sim://"):  # injected faults: once per session
        options.setdefault("faults_met", len(metadata.faults))
    # made (its options checked) before anything is written, opened when the trials play;
    # the frames' feed cap leaves room for this device's own dead-band
    device = open_device(spec.device_url, o.layout, clock, **options)
    frames = trial_frames(protocol, o.layout, WireSlack.for_device(device))
    check_frames(paths.frame_log, rows, plan, frames,
                 None if protocol.levels is None else protocol.levels.column)
    state = SessionState(spec, protocol, o.layout, plan, store, metadata, rows,
                         {f.trial for f in metadata.faults}, adaptive=adaptive,
                         adaptive_sha256=None if adaptive is None else adaptive.fingerprint(),
                         cut=metadata.cut_trials())
    resume_at = float(rows[-1]["trial_end"]) if rows else 0.0
    store.create()
    save(state, "running", final=True)
    return Run(o, state, device, clock, frames, first, resume_at, len(rows), current=first)


def play_trials(run: Run, progress: Progress | None = None) -> str:
    """Play the trials from ``run.first`` on and return how the run stopped: ``complete``
    or ``interrupted`` (Ctrl-C, a signal or the keypad's quit key, recorded). A consent
    withdrawal, a device fault and a dataset error are recorded in the sidecar and raised
    again as one line saying what to do; any other error is recorded and raised as it is."""
    state, spec, n_trials = run.state, run.opening.spec, run.opening.n_trials
    try:
        _play(run, progress)
        return "complete"
    except KeyboardInterrupt as interrupt:
        if isinstance(interrupt, PauseRequested):
            record_interruption(state, "pause-key", "the keypad's pause key")
        elif isinstance(interrupt, TerminalClosed):
            record_interruption(state, "signal", "the keypad's terminal was closed")
        else:
            name = describe(interrupt)
            record_interruption(state, "signal", {"Ctrl-C": "SIGINT (Ctrl-C)",
                                                  "SIGHUP": "SIGHUP (the terminal was closed)"
                                                  }.get(name, name))
        return "interrupted"
    except ConsentError as error:
        record_interruption(state, "consent-withdrawn", str(error))
        save_after_failure(state)
        k = len(state.rows)
        raise ConsentError(
            f"{error}: session {spec.session} of participant {spec.participant} stopped "
            f"before trial {k + 1}/{n_trials}, display neutral; its {k} stored trial(s) "
            f"stay in {spec.dataset} until withdrawn: crs-study consent withdraw "
            f"--participant {spec.participant} --dataset {spec.dataset}") from None
    except DeviceError as error:
        k = run.current if state.in_trial else len(state.rows)
        where = f"at trial {k + 1}/{n_trials}" if state.in_trial else \
            f"before trial {k + 1}/{n_trials}"
        if state.in_trial:
            fault = Fault(k, now_utc(), str(error))
            state.metadata = replace(state.metadata, faults=(*state.metadata.faults, fault))
        record_interruption(state, "device-fault", str(error))
        save_after_failure(state)
        raise DeviceError(f"device fault {where}: {error}; the session is marked "
                          "interrupted: run the same command to resume") from None
    except DatasetError as error:  # a full disk, a folder gone: the stored trials stay
        record_interruption(state, "error", f"{type(error).__name__}: {error}")
        save_after_failure(state)
        raise DatasetError(
            f"{error}; the session is paused at trial {len(state.rows) + 1}/{n_trials} "
            f"with the {len(state.rows)} trials before it stored: fix that (free some "
            "space) and run the same command to resume") from None
    except BaseException as error:
        record_interruption(state, "error", f"{type(error).__name__}: {error}")
        save_after_failure(state)  # the first error is the one reported
        raise


def _play(run: Run, progress: Progress | None) -> None:
    """The device and responder open, the display neutral and settled (on a virtual clock
    the stored trials replayed first), then one trial after another."""
    o, state, device, clock = run.opening, run.state, run.device, run.clock
    spec, plan, responder = o.spec, o.plan, o.responder
    with terminate_as_interrupt(), responder, device:
        device.neutral()
        responder.start_session(spec.participant, spec.session, plan, run.first)
        if o.clock_kind == "virtual":
            clock.sleep_until(0.0)
            if state.rows:
                if progress:
                    progress(f"sub-{spec.participant} ses-{spec.session}: replaying "
                             f"{len(state.rows)} stored trials on the simulated device")
                replay(state, device, clock, run.frames)
        else:
            clock.sleep(SETTLE_S)
            run.origin = clock.now() - run.resume_at
        if run.first and not responder.simulated:
            responder.prompt(resume_prompt(plan, run.first), clock)
        for k in range(run.first, o.n_trials):
            trial = choose(plan.trials[k], state.adaptive)
            if trial is None:  # its block's staircase has finished
                continue
            run.current = k
            if o.gate is not None:
                o.gate.recheck()  # a withdrawal stops the session here
            if progress:
                progress(f"sub-{spec.participant} ses-{spec.session}: trial "
                         f"{k + 1}/{o.n_trials}")
            while True:
                state.in_trial = True
                try:
                    run_trial(state, device, responder, clock, run.origin, run.frames, trial)
                    break
                except PauseInPlace:  # the display is neutral; the trial is played again
                    state.in_trial = False
                    if state.started is not None:
                        state.cut.add(state.started)
                        state.started = None
                    responder.pause(clock)
                    # its prompt and break were before the pause: played again without them
                    trial = replace(trial, prompt_before=None, break_before=False)
            state.in_trial = False
        responder.end_session()


def close_session(run: Run, status: str, wall_start: float) -> SessionResult:
    """Write the sidecar's final status (an interruption cannot itself be interrupted) and
    say how the run ended."""
    o, state = run.opening, run.state
    if status == "interrupted":
        with ignore_interrupts():
            save(state, "interrupted", final=True)
    if status == "complete":
        save(state, "complete", final=True)
    done = len(state.rows)
    spec = o.spec
    return SessionResult(
        status, spec.participant, spec.session, o.n_trials, done, done - run.stored_before,
        state.late_frames, (run.clock.now() - run.origin) - run.resume_at,
        time.perf_counter() - wall_start, o.paths.tsv, o.paths.sidecar,
        f"session {spec.session} of participant {spec.participant}: {done}/{o.n_trials} "
        f"trials in {o.paths.tsv}")
