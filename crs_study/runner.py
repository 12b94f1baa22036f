"""The session runner: plays a protocol's trial plan on a device and stores every trial durably.

One trial (all times on the session's :class:`~crs_study.clock.Clock`):

1. a prompt to the experimenter at a block start or a break (mount or remove the skeleton);
   simulated responders continue at once, the keypad waits for Space or Enter;
2. the stimulus: the pre-rendered frames of the (digit, condition) pair are commanded at the
   protocol's frame rate, each at its due time ``onset + frame_times[k]`` (``sleep_until``); a
   frame commanded more than one period after its due time counts as late; the displayed
   setpoints are sampled one period after each frame (what the skin meets) for the responder;
   at the offset, the end of the last frame's period (``onset + n / f``), the display returns
   to the neutral (flat) pose;
3. the response (:class:`~crs_study.responders.base.Responder`), with the protocol's time limit
   from stimulus offset;
4. the trial's frame log and its row are stored durably (:mod:`crs_study.dataset`), then the
   sidecar; feedback after practice trials; the inter-trial interval.

Session time: ``onset`` and ``trial_end`` are seconds since the session started, not counting
the time a session spent interrupted: a resumed session continues from the last stored
``trial_end``. Each trial ends on a whole millisecond of session time (so the stored value is
exact). On a virtual clock a resumed session first replays the stored trials' frames on the
fresh simulated device, without responder or writing, so the device's history (wire timing,
refresh phase, servo positions) is the uninterrupted run's; the rest of the session is then
bit for bit what an uninterrupted run writes: every column of every row and every frame log.

Failures: Ctrl-C (or the keypad's quit key, or SIGTERM) is a safe pause: the display goes
neutral, the session is marked ``interrupted`` and the run returns status ``interrupted``
(exit 130). A :class:`~crs_study.errors.DeviceError` during a trial marks the session
interrupted, records the fault in the sidecar, moves to neutral and is raised again as one
line; the trial is rerun on resume and its row then says ``device_fault = 1``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import signal
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from crs_study import __version__
from crs_study._files import sha256_bytes
from crs_study.clock import RealClock, VirtualClock
from crs_study.dataset import Dataset, SessionStore, schema
from crs_study.dataset.session_metadata import FINGERPRINTS, Fault, Resume, SessionMetadata, now_utc
from crs_study.errors import CrsStudyError, DeviceError, SessionError
from crs_study.paths import recorded_path, resolve_protocol
from crs_study.signals import deferred, handling, terminate_as_interrupt

#: Session time spent before the first trial with the display neutral (settled and flat).
SETTLE_S = 1.0
#: Without per-trial durability (dry-runs) the sidecar is rewritten every this many trials
#: (and when the session stops); the trial file is the authority on what is done.
DRY_RUN_SIDECAR_EVERY = 10
FRAME_LOG_COLUMNS = ("kind", "frame", "due", "commanded_at", "wire_done_at", "bytes",
                     "channels", "merged")

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


def plan_sha256(plan: Any) -> str:
    """The plan's fingerprint: ``plan.sha256()``, else sha256 of canonical JSON of it."""
    if callable(getattr(plan, "sha256", None)):
        return plan.sha256()
    trials = [asdict(t) if is_dataclass(t) else dict(t) for t in plan.trials]
    text = json.dumps({"seed": int(plan.seed), "counterbalance": int(plan.counterbalance),
                       "trials": trials}, sort_keys=True, default=str)
    return sha256_bytes(text.encode("utf-8"))


def ceil_ms(seconds: float) -> float:
    """The next whole millisecond at or after ``seconds`` (exactly ``k / 1000``)."""
    return math.ceil(round(seconds * 1000.0, 6)) / 1000.0


class StimulusCache:
    """Rendered frames per (digit, condition, level), computed once (a stimulus never varies);
    ``level`` is None for protocols without ``[levels]``."""

    def __init__(self, protocol: Any, layout: Any) -> None:
        self.protocol = protocol
        self.layout = layout
        self._renderers: dict[str, Any] = {}
        self._stimuli: dict[tuple[int, float | None], Any] = {}
        self._frames: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._text: dict[tuple, list[str]] = {}

    def get(self, digit: int, condition: str, level: float | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
        """``(frame_times (n,), setpoints (n, n_actuators))``."""
        key = (int(digit), condition, level)
        if key not in self._frames:
            from crs_study.rendering.frames import render_frames
            from crs_study.rendering.render import Renderer
            from crs_study.stimuli.stimulus import make_stimulus

            if (digit, level) not in self._stimuli:
                self._stimuli[(digit, level)] = make_stimulus(self.protocol, self.layout, digit,
                                                              level)
            if condition not in self._renderers:
                self._renderers[condition] = Renderer(self.layout, condition)
            stimulus = self._stimuli[(digit, level)]
            frames = np.asarray(render_frames(stimulus, self._renderers[condition]), float)
            times = np.asarray(stimulus.frame_times, dtype=float)
            if frames.ndim != 2 or len(frames) != len(times) or len(times) == 0:
                raise SessionError(f"stimulus of digit {digit} ({condition}): {len(times)} "
                                   f"frame times but frames of shape {frames.shape}")
            self._frames[key] = (times, frames)
        return self._frames[key]

    def setpoint_text(self, digit: int, condition: str, level: float | None = None
                      ) -> list[str]:
        """The frames' setpoints as tab-separated text (mm, 4 decimals), for the frame log."""
        key = (int(digit), condition, level)
        if key not in self._text:
            _, frames = self.get(digit, condition, level)
            self._text[key] = ["\t".join(f"{v:.4f}" for v in row) for row in frames.tolist()]
        return self._text[key]


_caches: dict[tuple[str, str], StimulusCache] = {}


def stimulus_cache(protocol: Any, layout: Any) -> StimulusCache:
    """One cache per protocol and device file per process (shared by dry-run participants)."""
    key = (protocol.sha256, layout.source)
    if key not in _caches:
        _caches[key] = StimulusCache(protocol, layout)
    return _caches[key]


def _device_file_text(layout: Any, protocol: Any) -> str:
    from crs_study.geometry.layout import device_file_path

    for candidate in (getattr(protocol, "device_path", None), layout.source, protocol.device):
        if candidate is None:
            continue
        path = device_file_path(candidate)
        if path.exists():
            return path.read_text(encoding="utf-8")
    raise SessionError(f"cannot find the device file {protocol.device!r} to store with the "
                       "session")


def _choose_clock(spec: SessionSpec, responder: Any) -> str:
    if spec.clock not in ("real", "virtual", "auto"):
        raise SessionError(f"--clock must be real, virtual or auto, got {spec.clock!r}")
    if spec.clock == "auto":
        return "virtual" if spec.device_url.startswith("sim://") and responder.simulated \
            else "real"
    if spec.clock == "virtual" and responder.needs_real_clock:
        raise SessionError(f"the {responder.name} responder needs --clock real (a person answers "
                           "in real time)")
    if spec.clock == "virtual" and not spec.device_url.startswith("sim://"):
        raise SessionError(f"--clock virtual needs the simulated device (sim://); "
                           f"{spec.device_url} moves real servos in real time")
    return spec.clock


def _ignore_interrupts() -> contextlib.AbstractContextManager[None]:
    """Ignore Ctrl-C while the session is being put safely to rest."""
    return handling(signal.SIG_IGN, (signal.SIGINT,))


@dataclass
class _Session:
    """Mutable state of one run."""

    spec: SessionSpec
    protocol: Any
    layout: Any
    plan: Any
    store: SessionStore
    metadata: SessionMetadata
    rows: list[dict[str, str]]
    faults: set[int] = field(default_factory=set)
    late_frames: int = 0
    in_trial: bool = False  # a device fault now interrupts a trial (rerun with device_fault)


def prepare(spec: SessionSpec) -> tuple[Any, Any, Any, Dataset]:
    """Load the protocol, layout and plan for ``spec`` (nothing is written)."""
    from crs_study.plan import make_plan
    from crs_study.protocol import load_protocol

    if not spec.device_url.startswith(("sim://", "serial://")):
        raise DeviceError(f"unknown device URL {spec.device_url!r}; expected "
                          "serial:///dev/ttyUSB0[,/dev/ttyUSB1] or sim://")
    dataset = Dataset(spec.dataset)
    dataset.session_paths(spec.participant, spec.session)  # checks label and session
    protocol = load_protocol(resolve_protocol(spec.protocol))
    layout = protocol.layout()
    known = dataset.participants() if (spec.dataset / "participants.tsv").exists() else {}
    if spec.participant in known:
        counterbalance = known[spec.participant]
        if spec.counterbalance is not None and spec.counterbalance != counterbalance:
            raise SessionError(
                f"participant {spec.participant!r} has counterbalance {counterbalance} in "
                f"{spec.dataset / 'participants.tsv'}; --counterbalance {spec.counterbalance} "
                "disagrees")
    else:
        counterbalance = len(known) if spec.counterbalance is None else spec.counterbalance
    plan = make_plan(protocol, spec.participant, spec.session, counterbalance)
    return protocol, layout, plan, dataset


def session_columns(protocol: Any) -> tuple[str, ...]:
    """The session TSV's columns: the schema's, plus the level column when levels vary."""
    levels = getattr(protocol, "levels", None)
    return schema.trial_columns(levels.column if levels is not None else None)


def stimulus_sha256(protocol: Any, layout: Any) -> str:
    """sha256 of every bump path the protocol shows on ``layout`` (each digit at each level:
    frame times, centres, heights, diameter), so a resume under software that draws the
    digits differently (another strokes scaling, say) is refused although the protocol file
    is unchanged."""
    from crs_study.stimuli.stimulus import make_stimulus

    digest = hashlib.sha256()
    for level in protocol.level_values:
        for digit in protocol.digits:
            stimulus = make_stimulus(protocol, layout, digit, level)
            for array in (stimulus.frame_times, stimulus.centres_mm, stimulus.heights_mm):
                digest.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
            digest.update(repr((digit, level, float(stimulus.diameter_mm))).encode())
    return digest.hexdigest()


def _fingerprints(protocol: Any, plan: Any, device_text: str, layout: Any) -> dict[str, Any]:
    """What a stored session must match to be resumed (see :func:`check_resume`)."""
    return {
        "ProtocolSha256": protocol.sha256, "Seed": int(plan.seed),
        "Counterbalance": int(plan.counterbalance), "PlanSha256": plan_sha256(plan),
        "DeviceFileSha256": sha256_bytes(device_text.encode("utf-8")),
        "StimulusSha256": stimulus_sha256(protocol, layout),
    }


def check_resume(stored: SessionMetadata, expected: dict, sidecar: Path) -> None:
    """A stored session may only be resumed with the same plan: one line saying what differs.

    A fingerprint the stored session lacks (``StimulusSha256`` of a session begun by older
    software) is not compared.
    """
    recorded = stored.fingerprints()
    for key, label in FINGERPRINTS.items():
        if recorded[key] is not None and recorded[key] != expected[key]:
            raise SessionError(
                f"{sidecar}: cannot resume: the {label} differs ({key} stored "
                f"{recorded[key]!r}, now {expected[key]!r}); use the original files or start "
                "another --session")


def _device_kind(url: str) -> str:
    return "simulated" if url.startswith("sim://") else "real"


def check_same_kind_of_run(stored: SessionMetadata, spec: SessionSpec, responder_name: str,
                           clock_kind: str, sidecar: Path) -> None:
    """A session is finished as it began: by the same kind of responder, on the same kind of
    device and clock. Ports may differ (a board replugged as another ttyUSB), so only
    ``sim://`` against a real device counts, not the URL."""
    now = {"Responder": responder_name, "Clock": clock_kind,
           "Device": _device_kind(spec.device_url)}
    then = {"Responder": stored.responder, "Clock": stored.clock,
            "Device": "simulated" if stored.simulated_device else "real"}
    for key, option in (("Responder", "--responder"), ("Clock", "--clock"),
                        ("Device", "--device")):
        if then[key] != now[key]:
            raise SessionError(
                f"{sidecar}: cannot resume: the session began with {key.lower()} "
                f"{then[key]!r}, now {now[key]!r}; resume with the same {option} or start "
                "another --session")


def _check_rows(rows: list[dict[str, str]], plan: Any, tsv: Path) -> None:
    if len(rows) > len(plan.trials):
        raise SessionError(f"{tsv}: {len(rows)} rows but the plan has {len(plan.trials)} trials")
    for k, row in enumerate(rows):
        trial = plan.trials[k]
        stored = (row["trial_index"], row["condition"], row["digit"])
        wanted = (str(trial.index), trial.condition, str(trial.digit))
        if stored != wanted:
            raise SessionError(f"{tsv}: row {k + 1} holds (trial_index, condition, digit) = "
                               f"{stored}, the plan says {wanted}; the file does not belong "
                               "to this plan")


def seed_check(spec: SessionSpec) -> dict[str, Any]:
    """The seed and plan of ``spec``, checked against a stored session (nothing is written).

    A stored session whose seed, protocol, counterbalance, plan or device file differ is a
    :class:`SessionError` naming the difference.
    """
    protocol, layout, plan, dataset = prepare(spec)
    paths = dataset.session_paths(spec.participant, spec.session)
    device_text = _device_file_text(layout, protocol)
    expected = _fingerprints(protocol, plan, device_text, layout)
    stored = SessionStore(paths, columns=session_columns(protocol)).read_sidecar()
    if stored is not None:
        check_resume(stored, expected, paths.sidecar)
    return {
        "participant": spec.participant, "session": spec.session,
        "seed": expected["Seed"], "counterbalance": expected["Counterbalance"],
        "trials": len(plan.trials), "plan_sha256": expected["PlanSha256"],
        "protocol_sha256": expected["ProtocolSha256"],
        "stored": "none" if stored is None else
        f"{stored.status} ({stored.trials_completed}/{stored.trials_planned} trials), matches",
    }


def run_session(spec: SessionSpec, *, progress: Progress | None = None,
                responder: Any = None, device_options: dict | None = None) -> SessionResult:
    """Run (or resume) one session; see the module docstring."""
    from crs_study.device.base import open_device
    from crs_study.responders import make_responder

    wall_start = time.perf_counter()
    protocol, layout, plan, dataset = prepare(spec)
    # Everything that can refuse the run is asked before anything is written (a typo must
    # not take a counterbalance slot or leave an empty session behind).
    if responder is None:
        responder = make_responder(spec.responder, seed=int(plan.seed), layout=layout,
                                   protocol=protocol)
    clock_kind = _choose_clock(spec, responder)
    responder.check_ready()
    if not spec.device_url.startswith("sim://"):
        # The gate comes before anything is written: no consent, no trace in the dataset.
        from crs_study.consent import read_form, require_consent
        from crs_study.protocol import consent_form_path

        require_consent(spec.consent_register, spec.participant, protocol.consent_form_version,
                        read_form(consent_form_path(protocol)))
    # The order of arrival is taken under the dataset lock: two runners adding participants
    # at once would otherwise both read the same count and share a counterbalance index.
    counterbalance = dataset.register_participant(spec.participant, spec.counterbalance)
    if counterbalance != int(plan.counterbalance):
        from crs_study.plan import make_plan

        plan = make_plan(protocol, spec.participant, spec.session, counterbalance)
    paths = dataset.session_paths(spec.participant, spec.session)
    n_trials = len(plan.trials)
    device_text = _device_file_text(layout, protocol)
    expected = _fingerprints(protocol, plan, device_text, layout)
    store = SessionStore(paths, columns=session_columns(protocol), durable=spec.durable)
    with store:
        stored = store.read_sidecar()
        if stored is not None:
            check_resume(stored, expected, paths.sidecar)
        if stored is not None and stored.is_complete:
            # Never rewritten: checked read-only (no torn-tail cut), then left alone.
            rows = store.verify_complete(stored.trials_sha256)
            _check_rows(rows, plan, paths.tsv)
            if len(rows) != n_trials:
                raise SessionError(
                    f"{paths.sidecar}: the session is marked complete but holds {len(rows)} "
                    f"of {n_trials} planned trials; a completed session is never rewritten: "
                    "use another --session")
            return SessionResult(
                "already-complete", spec.participant, spec.session, n_trials, n_trials, 0, 0,
                0.0, 0.0, paths.tsv, paths.sidecar,
                f"session {spec.session} of participant {spec.participant} is complete "
                f"({n_trials} trials) in {paths.tsv.parent}; nothing to do (a new session "
                "needs --session N)")
        if stored is not None:
            check_same_kind_of_run(stored, spec, responder.name, clock_kind, paths.sidecar)
        rows = store.recover_rows()
        _check_rows(rows, plan, paths.tsv)
        metadata = _metadata(spec, protocol, plan, device_text, expected, stored, clock_kind,
                             responder.name, n_trials)
        faults = {f.trial for f in metadata.faults}
        state = _Session(spec, protocol, layout, plan, store, metadata, rows, faults)
        resume_at = float(rows[-1]["trial_end"]) if rows else 0.0
        clock: Any = VirtualClock(start=-SETTLE_S) if clock_kind == "virtual" else RealClock()
        cache = stimulus_cache(protocol, layout)
        store.create()
        _save(state, "running", final=True)
        first = len(rows)
        status = "interrupted"
        origin = 0.0
        try:
            with terminate_as_interrupt(), responder, open_device(
                    spec.device_url, layout, clock, **(device_options or {})) as device:
                device.neutral()
                if clock_kind == "virtual":
                    clock.sleep_until(0.0)
                    if rows:
                        if progress:
                            progress(f"sub-{spec.participant} ses-{spec.session}: replaying "
                                     f"{len(rows)} stored trials on the simulated device")
                        _replay(state, device, clock, cache)
                else:
                    clock.sleep(SETTLE_S)
                    origin = clock.now() - resume_at
                if first and not responder.simulated:
                    responder.prompt(_resume_prompt(plan, first), clock)
                for k in range(first, n_trials):
                    if progress:
                        progress(f"sub-{spec.participant} ses-{spec.session}: trial "
                                 f"{k + 1}/{n_trials}")
                    state.in_trial = True
                    _run_trial(state, device, responder, clock, origin, cache, plan.trials[k])
                    state.in_trial = False
                status = "complete"
        except KeyboardInterrupt:
            status = "interrupted"
        except DeviceError as error:
            k = len(state.rows)
            where = f"at trial {k + 1}/{n_trials}" if state.in_trial else \
                f"before trial {k + 1}/{n_trials}"
            if state.in_trial:
                fault = Fault(k, now_utc(), str(error))
                state.metadata = replace(state.metadata, faults=(*state.metadata.faults, fault))
            status = "fault"
            _save_after_failure(state)
            raise DeviceError(f"device fault {where}: {error}; the session is marked "
                              "interrupted: run the same command to resume") from None
        except BaseException:
            status = "failed"
            _save_after_failure(state)  # the first error is the one reported
            raise
        if status == "interrupted":
            with _ignore_interrupts():
                _save(state, "interrupted", final=True)
        if status == "complete":
            _save(state, "complete", final=True)
        done = len(state.rows)
        return SessionResult(
            status, spec.participant, spec.session, n_trials, done, done - first,
            state.late_frames, (clock.now() - origin) - resume_at,
            time.perf_counter() - wall_start, paths.tsv, paths.sidecar,
            f"session {spec.session} of participant {spec.participant}: {done}/{n_trials} "
            f"trials in {paths.tsv}")


def _metadata(spec: SessionSpec, protocol: Any, plan: Any, device_text: str, expected: dict,
              stored: SessionMetadata | None, clock_kind: str, responder_name: str,
              n_trials: int) -> SessionMetadata:
    """The sidecar of a session beginning now, or resumed now from ``stored``."""
    resumes: tuple[Resume, ...] = ()
    faults: tuple[Fault, ...] = ()
    if stored is not None:
        resumes = (*stored.resumes, Resume(now_utc(), stored.trials_completed, spec.device_url,
                                           __version__))
        faults = stored.faults
    return SessionMetadata(
        task_name=schema.TASK,
        task_description="Identify the digit drawn by a moving bump on the CRS display",
        instructions="Rest your fingertips on the display. A bump will draw a digit from "
                     "0 to 9; press that digit's key as soon as you know it.",
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
        clock=clock_kind,  # real or virtual (_choose_clock)
        frame_rate_hz=float(protocol.frame_rate_hz),
        start_time=stored.start_time if stored is not None else now_utc(),
        end_time=None,
        status="running",
        trials_planned=n_trials,
        trials_completed=0,
        trials_sha256=None,
        resumes=resumes,
        faults=faults,
    )


def _resume_prompt(plan: Any, first: int) -> str:
    """What the experimenter sees before a resumed session's first trial: where it stands and
    the current block's prompt (mount or remove the skeleton), which was shown before the
    interruption and may no longer hold."""
    trial = plan.trials[first]
    text = f"Resuming at trial {first + 1} of {len(plan.trials)}"
    if trial.prompt_before:  # the block starts here: its own prompt follows
        return text
    block_start = next((t for t in reversed(plan.trials[:first])
                        if t.block == trial.block and t.prompt_before), None)
    return f"{text}. {block_start.prompt_before}" if block_start else text


def _save_after_failure(state: _Session) -> None:
    """Mark the session interrupted while another error is on its way out.

    A failure here (the disk that just filled up) must not hide the first error: the TSV is
    the authority and the sidecar is brought up to date on resume, so it is let go.
    """
    with _ignore_interrupts():
        try:
            _save(state, "interrupted", final=True)
        except CrsStudyError:
            pass


def _save(state: _Session, status: str, final: bool = False) -> None:
    """Rewrite the sidecar; ``final`` (start, stop) also fsyncs the session's files."""
    if final:
        state.store.sync()
    state.metadata = state.metadata.with_progress(
        status, len(state.rows), state.store.trials_sha256,
        now_utc() if status != "running" else None)
    state.store.write_sidecar(state.metadata, final=final)


def _digit_choices(protocol: Any) -> tuple[int, ...]:
    digits = getattr(protocol, "digits", None)
    return tuple(int(d) for d in digits) if digits is not None else tuple(range(10))


@dataclass
class _Shown:
    """What one stimulus presentation did on the device."""

    onset: float
    offset: float
    reports: list
    displayed: np.ndarray
    late: int
    neutral_due: float
    neutral: Any


def _present(device: Any, clock: Any, frame_times: np.ndarray, frames: np.ndarray,
             period: float) -> _Shown:
    """Command the frames at ``onset + frame_times[k]``, then neutral at the offset."""
    n = len(frame_times)
    displayed = np.empty_like(frames)
    reports = []
    late = 0
    onset = clock.now()
    for i in range(n):
        due = onset + frame_times[i]
        clock.sleep_until(due)
        now = clock.now()
        if i:
            displayed[i - 1] = device.displayed_setpoints(now)
        if now - due > period:
            late += 1
        reports.append(device.send(frames[i]))
    offset = onset + float(frame_times[-1]) + period  # end of the last frame's period
    clock.sleep_until(offset)
    displayed[n - 1] = device.displayed_setpoints(clock.now())
    neutral_due = clock.now()
    neutral = device.neutral()  # the display goes flat at the stimulus offset
    return _Shown(onset, offset, reports, displayed, late, neutral_due, neutral)


def _replay(state: _Session, device: Any, clock: Any, cache: StimulusCache) -> None:
    """Bring a fresh simulated device to where an uninterrupted run had it (virtual clock).

    The stored trials' frames are commanded again at their original session times (no
    responder, nothing written), so the device's history (wire timing, refresh phase, servo
    positions) and therefore every later trial are exactly those of an uninterrupted run.
    """
    period = 1.0 / float(state.protocol.frame_rate_hz)
    for row, trial in zip(state.rows, state.plan.trials, strict=False):
        frame_times, frames = cache.get(trial.digit, trial.condition, _level(trial))
        _present(device, clock, frame_times, frames, period)
        clock.sleep_until(float(row["trial_end"]))


def _level(trial: Any) -> float | None:
    """The trial's stimulus level (None for plans without levels)."""
    return getattr(trial, "level", None)


def _frame_line(kind: str, frame: int, due: float, report: Any, origin: float,
                setpoints: str) -> str:
    """One frame-log line (without the trial column): times in session seconds."""
    return (f"{kind}\t{frame}\t{due - origin:.6f}\t{report.commanded_at - origin:.6f}\t"
            f"{report.wire_done_at - origin:.6f}\t{','.join(map(str, report.bytes_sent))}\t"
            f"{report.channels_sent}\t{int(report.merged)}\t{setpoints}")


def _run_trial(state: _Session, device: Any, responder: Any, clock: Any, origin: float,
               cache: StimulusCache, trial: Any) -> None:
    from crs_study.responders.base import StimulusRecord

    protocol = state.protocol
    if trial.prompt_before or trial.break_before:
        responder.prompt(trial.prompt_before or "Break: rest, then continue", clock)
    if trial.break_before and not responder.needs_real_clock:  # a person rests until ready
        clock.sleep(float(protocol.design.break_duration_s))
    level = _level(trial)
    frame_times, frames = cache.get(trial.digit, trial.condition, level)
    period = 1.0 / float(protocol.frame_rate_hz)
    responder.begin_trial(trial, clock.now(), clock)
    shown = _present(device, clock, frame_times, frames, period)
    onset, offset, reports = shown.onset, shown.offset, shown.reports
    record = StimulusRecord(state.layout, trial.condition, frame_times + period, shown.displayed,
                            _digit_choices(protocol), onset, offset)
    response = responder.respond(trial, record, clock, protocol.time_limit_s)
    duration = offset - onset
    rt = float(response.response_time_s)
    correct = None if response.digit is None else int(response.digit == trial.digit)
    trial_end = ceil_ms(clock.now() - origin + float(protocol.inter_trial_interval_s))
    latencies = [r.wire_done_at - (onset + frame_times[i]) for i, r in enumerate(reports)]
    n = len(frame_times)
    row = {
        "trial_index": trial.index, "trial_type": trial.trial_type, "block": trial.block,
        "condition": trial.condition, "repetition": trial.repetition, "digit": trial.digit,
        "response": response.digit, "correct": correct, "response_time": rt,
        "response_time_from_offset": rt - duration, "onset": onset - origin,
        "stimulus_duration": duration, "timed_out": int(response.digit is None),
        "device_fault": int(trial.index in state.faults), "frames": n,
        "late_frames": shown.late, "median_wire_latency": float(np.median(latencies)),
        "responder": responder.name, "trial_end": trial_end,
    }
    if getattr(protocol, "levels", None) is not None:
        row[protocol.levels.column] = level
    text = cache.setpoint_text(trial.digit, trial.condition, level)
    log = [_frame_line("stimulus", i, onset + frame_times[i], r, origin, text[i])
           for i, r in enumerate(reports)]
    flat = "\t".join(f"{v:.4f}" for v in state.layout.neutral_setpoints().tolist())
    log.append(_frame_line("neutral", n, shown.neutral_due, shown.neutral, origin, flat))
    columns = FRAME_LOG_COLUMNS + tuple(f"a{j:02d}" for j in range(frames.shape[1]))
    with deferred():  # stored whole: frames, row, rows in memory, sidecar
        state.store.append_frames(trial.index, columns, log)
        state.store.append_row(row)
        state.rows.append({k: str(v) for k, v in row.items()})
        state.late_frames += shown.late
        if state.spec.durable or len(state.rows) % DRY_RUN_SIDECAR_EVERY == 0:
            _save(state, "running")
    if trial.feedback:
        responder.feedback(trial, response, bool(correct))
    responder.end_trial()
    clock.sleep_until(origin + trial_end)


# --- dry-runs: many simulated participants ------------------------------------------------------

def simulated_labels(n: int, prefix: str = "sim") -> list[str]:
    """``sim01`` .. ``simNN`` (at least two digits, so labels sort in order)."""
    if not isinstance(n, int) or n < 1:
        raise SessionError(f"--participants must be a whole number >= 1, got {n!r}")
    width = max(2, len(str(n)))
    return [f"{prefix}{i:0{width}d}" for i in range(1, n + 1)]


def _dry_run_one(spec: SessionSpec) -> SessionResult:
    return run_session(spec)


def dry_run(protocol: str | Path, participants: int, dataset: str | Path, *, jobs: int = 1,
            responder: str = "observer", device_url: str = "sim://", prefix: str = "sim",
            progress: Progress | None = None, durable: bool = False) -> list[SessionResult]:
    """Session 1 of ``participants`` simulated participants on a virtual clock.

    ``protocol`` is a protocol file or a shipped protocol's name (``"pilot"``).

    Participant i (from 0) gets counterbalance index i, so the protocol's block orders are
    balanced across the N. With ``jobs > 1`` sessions run in that many worker processes (each
    session is written by one process; the dataset lock serialises ``participants.tsv``).
    Completed sessions already in the dataset are left as they are (a rerun resumes).
    ``durable=False`` (a documented choice; ``--fsync`` turns it off) fsyncs each session
    once, when it stops, rather than after every trial as ``crs-study run`` does: a killed
    dry-run still loses nothing and resumes exactly. A power cut costs at most the unfinished
    sessions; one whose files the cut left inconsistent is refused on resume in one line,
    and removing its files lets the same command regenerate it exactly from its seed.
    """
    if not device_url.startswith("sim://"):
        raise SessionError(f"a dry-run uses the simulated device (sim://...), got "
                           f"{device_url!r}; use crs-study run for a real device")
    if not isinstance(jobs, int) or jobs < 1:
        raise SessionError(f"--jobs must be a whole number >= 1, got {jobs!r}")
    if responder == "keypad":
        raise SessionError("a dry-run has no person at the keypad: use --responder observer, "
                           "random or scripted:FILE")
    labels = simulated_labels(participants, prefix)
    protocol = resolve_protocol(protocol)  # a shipped protocol's name, or a path
    Dataset(dataset).ensure()
    specs = [SessionSpec(protocol, label, Path(dataset), device_url, 1, responder,
                         "virtual", i, durable=durable) for i, label in enumerate(labels)]
    results: list[SessionResult] = []

    def note(result: SessionResult) -> None:
        results.append(result)
        if progress:
            progress(f"dry-run: {len(results)}/{len(specs)} participants "
                     f"(sub-{result.participant}: {result.status}, "
                     f"{result.trials_completed} trials)")

    if jobs == 1 or len(specs) == 1:
        for spec in specs:
            note(run_session(spec))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(jobs, len(specs)),
                                 mp_context=context) as pool:
            futures = [pool.submit(_dry_run_one, spec) for spec in specs]
            try:
                for future in as_completed(futures):
                    note(future.result())
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
    order = {label: i for i, label in enumerate(labels)}
    return sorted(results, key=lambda r: order[r.participant])
