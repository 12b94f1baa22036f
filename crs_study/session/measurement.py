"""A measurement session: a measurement protocol's target waveforms held on the device, one
capture window each, with a durable manifest of what was shown when.

:func:`run_measurement` plays the plan of :func:`~crs_study.quality.measurement_protocol.
plan_captures`: per condition a block (the experimenter mounts or removes the skeleton at its
start), its reference capture (the display neutral) and its shapes, each rendered as a
session renders it (the feed cap included), sent, left ``settle_s`` to settle and held for
its capture window. How a capture is taken (``capture``):

``prompt``
    the experimenter takes the DIC images and presses Enter; the window is the time between;
``timed``
    each shape is held ``hold_s`` (a DIC recording continuously, or triggered by the lab's own
    means: the manifest's ``capture_utc`` and window times match its images to the shapes);
``synthetic[?options]``
    on the simulated device only: the stand-in of :mod:`crs_study.quality.dic_standin` writes
    each capture's export (and the fiducials) into ``OUT/captures`` from the servo positions
    the simulated device reached.

It runs on the machinery of participant sessions (:class:`~crs_study.dataset.
SessionStore`): each capture's frame is appended to ``sourcedata/frames.tsv.gz`` and its row
to ``manifest.tsv`` with one ``write`` and an fsync, then ``measurement.json`` is replaced
atomically; a second runner on the folder is refused; a torn last line is cut and kept. Ctrl-C
(or SIGTERM, SIGHUP) is a safe pause: the display goes neutral, the record says
``interrupted``. A device fault is recorded, the record says ``interrupted``, and the fault is
raised as one line. Running the same command again resumes at the next capture, after checking
that protocol, device file and plan are those that began it (their sha256). On a virtual clock
(``sim://``, not ``prompt``) a resumed measurement writes the manifest and the synthetic
captures an uninterrupted one writes: session time continues from the last capture's end, and
every shape settles fully before its window opens.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

from crs_study import __version__
from crs_study._files import sha256_bytes
from crs_study.clock import Clock, RealClock, VirtualClock
from crs_study.dataset.bids import SessionPaths
from crs_study.dataset.schema import tsv_line
from crs_study.dataset.session_store import SessionStore
from crs_study.device import Device, open_device
from crs_study.errors import DatasetError, DeviceError, MeasurementError, SessionError
from crs_study.geometry.layout import Layout, device_file_path
from crs_study.quality.dic_standin import SyntheticDic
from crs_study.quality.manifest import (
    CAPTURES,
    MANIFEST,
    MANIFEST_COLUMNS,
    RECORD,
    MeasurementRecord,
    format_setpoints,
)
from crs_study.quality.measured_analysis import find_capture
from crs_study.quality.measurement_protocol import (
    MeasurementProtocol,
    PlannedCapture,
    device_path,
    load_measurement_protocol,
    plan_captures,
    plan_sha256,
)
from crs_study.rendering.conditions import get_condition
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.render import Renderer
from crs_study.session.runner import simulated_url
from crs_study.signals import describe, terminate_as_interrupt
from crs_study.stimuli.targets import Bump

#: What a capture window asks of a person: shown the message, return when done.
Prompt = Callable[[str], None]
#: Where progress is reported, one line at a time.
Progress = Callable[[str], None]

FRAME_COLUMNS = ("sent_at", "commanded_at", "wire_done_at", "bytes", "channels",
                 "merged")


class MeasurementPaths(SessionPaths):
    """A measurement folder's files, in the places :class:`SessionStore` writes a session's:
    ``manifest.tsv`` for the trial file, ``measurement.json`` for the sidecar, the frame log
    and torn tails under ``sourcedata/``, the lock ``.measurement.lock``."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        super().__init__(Path(root), "measurement", 1, "quality")

    @property
    def session_dir(self) -> Path:
        return self.root

    @property
    def beh_dir(self) -> Path:
        return self.root

    @property
    def tsv(self) -> Path:
        return self.root / MANIFEST

    @property
    def sidecar(self) -> Path:
        return self.root / RECORD

    @property
    def lock(self) -> Path:
        return self.root / ".measurement.lock"

    @property
    def source_dir(self) -> Path:
        return self.root / "sourcedata"

    @property
    def frame_log(self) -> Path:
        return self.source_dir / "frames.tsv.gz"

    def torn_backup(self, what: str, stamp: str) -> Path:
        return self.source_dir / f"{what}-torn-{stamp}.bin"


@dataclass(frozen=True)
class MeasurementSpec:
    """What ``crs-study quality measure`` asks for."""

    protocol: str | os.PathLike[str]
    out: Path
    device_url: str = "sim://"
    capture: str = "prompt"  # "prompt", "timed" or "synthetic[?options]"
    clock: str = "auto"  # "real", "virtual" or "auto" (virtual for sim:// without prompt)

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))


@dataclass(frozen=True)
class MeasurementRun:
    """How a run of a measurement ended."""

    status: str  # "complete", "interrupted" or "already-complete"
    folder: Path
    captures_planned: int
    captures_completed: int
    captures_run: int
    missing: tuple[str, ...]  # captures whose export is not (yet) in OUT/captures
    message: str

    def to_dict(self) -> dict:
        return {"status": self.status, "folder": os.fspath(self.folder),
                "captures_planned": self.captures_planned,
                "captures_completed": self.captures_completed,
                "captures_run": self.captures_run, "missing": list(self.missing),
                "message": self.message}


def capture_kind(capture: str) -> str:
    """``prompt``, ``timed`` or ``synthetic`` (the options stripped); a bad one is refused."""
    kind = capture.split("?", 1)[0]
    if kind not in ("prompt", "timed", "synthetic"):
        raise MeasurementError(f"--capture {capture!r}: expected prompt, timed or "
                               "synthetic[?options]")
    if kind != "synthetic" and "?" in capture:
        raise MeasurementError(f"--capture {capture!r}: only synthetic takes options")
    return kind


def _choose_clock(spec: MeasurementSpec, kind: str) -> str:
    if spec.clock not in ("real", "virtual", "auto"):
        raise SessionError(f"--clock must be real, virtual or auto, got {spec.clock!r}")
    simulated = simulated_url(spec.device_url)
    if kind == "synthetic" and not spec.device_url.startswith("sim://"):
        raise MeasurementError(f"--capture synthetic: the stand-in reads the simulated "
                               f"device's servos; use --device sim://, not {spec.device_url}")
    if spec.clock == "auto":
        return "virtual" if simulated and kind != "prompt" else "real"
    if spec.clock == "virtual" and (kind == "prompt" or not simulated):
        raise SessionError("--clock virtual needs the simulated device and a capture that "
                           "waits for nobody (timed or synthetic)")
    return spec.clock


def _fingerprints(protocol: MeasurementProtocol, device_text: str, plan_digest: str) -> dict:
    return {"protocol_sha256": protocol.sha256,
            "device_file_sha256": sha256_bytes(device_text.encode("utf-8")),
            "plan_sha256": plan_digest}


def _check_resume(stored: MeasurementRecord, expected: dict, kind: str, clock: str,
                  url: str, path: Path) -> None:
    for key, value in expected.items():
        if getattr(stored, key) != value:
            raise SessionError(f"{path}: cannot resume: the {key.removesuffix('_sha256')} "
                               f"differs from the one that began the measurement ({key}); use "
                               "the original files or another --out")
    then = (capture_kind(stored.capture_mode), stored.clock, stored.device_url.startswith(
        "sim://"))
    now = (kind, clock, url.startswith("sim://"))
    if then != now:
        raise SessionError(f"{path}: cannot resume: it began with --capture "
                           f"{stored.capture_mode}, a {stored.clock} clock on "
                           f"{stored.device_url}; resume it the same way or use another --out")


def _now() -> str:
    return datetime.now(UTC).replace(microsecond=0).isoformat()


def missing_captures(folder: Path, plan: tuple[PlannedCapture, ...]) -> tuple[str, ...]:
    """The shapes of ``plan`` without an export in ``folder/captures`` yet."""
    captures = folder / CAPTURES
    return tuple(c.name for c in plan if c.kind == "shape"
                 and find_capture(captures, c.name) is None)


def run_measurement(spec: MeasurementSpec, *, prompt: Prompt | None = None,
                    progress: Progress | None = None,
                    device_options: dict[str, object] | None = None) -> MeasurementRun:
    """Run or resume a measurement (module docstring)."""
    kind = capture_kind(spec.capture)
    rig = SyntheticDic.parse(spec.capture) if kind == "synthetic" else None
    clock_kind = _choose_clock(spec, kind)
    if kind != "synthetic" and prompt is None:
        raise MeasurementError(f"--capture {kind}: the experimenter is prompted at each block "
                               "(and, with prompt, at each capture): no prompt was given")
    if not spec.device_url.startswith(("sim://", "serial://")):
        raise DeviceError(f"unknown device URL {spec.device_url!r}; expected "
                          "serial:///dev/ttyUSB0[,/dev/ttyUSB1] or sim://")
    protocol = load_measurement_protocol(spec.protocol)
    layout = protocol.layout()
    device_text = device_file_path(device_path(protocol.device, protocol.path)).read_text(
        encoding="utf-8")
    plan = plan_captures(protocol, layout)
    expected = _fingerprints(protocol, device_text, plan_sha256(plan))
    paths = MeasurementPaths(spec.out)
    store = SessionStore(paths, columns=MANIFEST_COLUMNS)
    try:
        store.acquire()
    except SessionError:
        raise SessionError(f"{spec.out}: the measurement is in use by another crs-study "
                           f"quality measure ({paths.lock})") from None
    try:
        return _run(spec, protocol, layout, plan, device_text, expected, store, kind, rig,
                    clock_kind, prompt, progress, device_options or {})
    finally:
        store.release()


def _run(spec: MeasurementSpec, protocol: MeasurementProtocol, layout: Layout,
         plan: tuple[PlannedCapture, ...], device_text: str, expected: dict,
         store: SessionStore, kind: str, rig: SyntheticDic | None, clock_kind: str,
         prompt: Prompt | None, progress: Progress | None,
         device_options: dict[str, object]) -> MeasurementRun:
    paths = store.paths
    stored = MeasurementRecord.read(paths.sidecar) if paths.sidecar.exists() else None
    if stored is not None:
        _check_resume(stored, expected, kind, clock_kind, spec.device_url, paths.sidecar)
        if stored.is_complete:
            store.verify_complete(stored.manifest_sha256)
            missing = missing_captures(spec.out, plan)
            return MeasurementRun("already-complete", spec.out, len(plan), len(plan), 0,
                                  missing, f"the measurement in {spec.out} is complete; "
                                  "nothing to do")
    store.check_resumable(stored)
    rows = store.recover_rows()
    for k, row in enumerate(rows):
        if row["capture"] != plan[k].name:
            raise SessionError(f"{paths.tsv}: row {k + 1} holds capture {row['capture']!r}, "
                               f"the plan says {plan[k].name!r}; the file does not belong to "
                               "this measurement")
    first = len(rows)
    record = _record(spec, protocol, device_text, expected, stored, kind, clock_kind,
                     len(plan), first)
    clock: Clock = VirtualClock() if clock_kind == "virtual" else RealClock()
    options = dict(device_options)
    if spec.device_url.startswith("sim://"):
        options.setdefault("faults_met", len(record.faults))
    device = open_device(spec.device_url, layout, clock, **options)
    wire = WireSlack.for_device(device)
    renderers = {c: Renderer(layout, c, wire=wire) for c in protocol.conditions}
    resume_at = float(rows[-1]["capture_end"]) if rows else 0.0
    store.create()
    state = {"record": record, "done": first}

    def save(status: str, final: bool = False) -> None:
        state["record"] = replace(state["record"], status=status,
                                  captures_completed=state["done"],
                                  manifest_sha256=store.trials_sha256,
                                  end_time=None if status == "running" else _now())
        if final:
            store.sync()
        store.write_sidecar(state["record"].to_dict(), final=final)

    def interrupted(cause: str, detail: str) -> None:
        entry = {"Time": _now(), "AtCapture": state["done"], "Cause": cause,
                 "Detail": detail.splitlines()[0] if detail else ""}
        state["record"] = replace(state["record"], interruptions=(
            *state["record"].interruptions, entry))
        try:
            save("interrupted", final=True)
        except DatasetError:
            pass  # the manifest is the authority; the record catches up on resume

    save("running", final=True)
    run = 0
    try:
        with terminate_as_interrupt(), device:
            device.neutral()
            clock.sleep(protocol.timing.settle_s)
            origin = clock.now() - resume_at
            if first and plan[first].kind == "shape" and kind != "synthetic":
                condition = plan[first].condition  # resumed inside a block: set it up again
                prompt(f"resuming at {plan[first].name} in block {condition}: "
                       f"{get_condition(condition).setup_prompt}; press Enter "
                       "when ready")
            for k in range(first, len(plan)):
                capture = plan[k]
                if capture.kind == "reference" and kind != "synthetic":
                    prompt(f"block {capture.condition}: "
                           f"{get_condition(capture.condition).setup_prompt}; "
                           "press Enter when ready")
                if progress:
                    progress(f"{capture.name} ({k + 1}/{len(plan)}): {capture.condition}"
                             + (f", l = {capture.diameter_mm:g} mm at ({capture.centre_mm[0]:.1f},"
                                f" {capture.centre_mm[1]:.1f}) mm" if capture.kind == "shape"
                                else ", the display neutral"))
                row, frame = _show(capture, device, clock, origin, renderers, protocol, kind,
                                   rig, prompt, spec.out, layout)
                store.append_frames(k, FRAME_COLUMNS, [frame])
                store.append_row(row)
                state["done"] = k + 1
                run += 1
                save("running")
        status = "complete"
    except KeyboardInterrupt as interrupt:
        interrupted("signal", describe(interrupt))
        status = "interrupted"
    except DeviceError as error:
        k = state["done"]
        state["record"] = replace(state["record"], faults=(
            *state["record"].faults, {"capture": k, "time": _now(), "message": str(error)}))
        interrupted("device-fault", str(error))
        raise DeviceError(f"device fault at capture {k + 1}/{len(plan)}: {error}; the "
                          "measurement is marked interrupted: run the same command to "
                          "resume") from None
    except BaseException as error:
        interrupted("error", f"{type(error).__name__}: {error}")
        raise
    if status == "complete":
        save("complete", final=True)
    missing = missing_captures(spec.out, plan)
    message = (f"{state['done']}/{len(plan)} captures shown; manifest {paths.tsv}"
               if status == "complete" else
               f"interrupted after {state['done']}/{len(plan)} captures: run the same "
               "command to resume")
    return MeasurementRun(status, spec.out, len(plan), state["done"], run, missing, message)


def _record(spec: MeasurementSpec, protocol: MeasurementProtocol, device_text: str,
            expected: dict, stored: MeasurementRecord | None, kind: str, clock_kind: str,
            planned: int, first: int) -> MeasurementRecord:
    if stored is None:
        return MeasurementRecord(
            protocol_name=protocol.name, protocol_text=protocol.text,
            protocol_sha256=protocol.sha256, protocol_path=str(protocol.path),
            device_file_text=device_text, device_file_sha256=expected["device_file_sha256"],
            device_url=spec.device_url, plan_sha256=expected["plan_sha256"],
            capture_mode=spec.capture, clock=clock_kind, software_version=__version__,
            start_time=_now(), end_time=None, status="running", captures_planned=planned,
            captures_completed=first, manifest_sha256=None)
    interruptions = stored.interruptions
    if stored.status == "running":  # the run before ended without a word: a crash
        interruptions += ({"Time": _now(), "AtCapture": first, "Cause": "crash",
                           "Detail": "found on resume: the record still said 'running' (the "
                                     "process was killed, the power cut or it crashed)"},)
    resumes = (*stored.resumes, {"Time": _now(), "AtCapture": first,
                                 "DeviceURL": spec.device_url,
                                 "SoftwareVersion": __version__})
    return replace(stored, device_url=spec.device_url, capture_mode=spec.capture,
                   interruptions=interruptions, resumes=resumes, status="running")


def _show(capture: PlannedCapture, device: Device, clock: Clock, origin: float,
          renderers: dict[str, Renderer], protocol: MeasurementProtocol, kind: str,
          rig: SyntheticDic | None, prompt: Prompt | None, out: Path, layout: Layout
          ) -> tuple[dict, str]:
    """Show one capture and hold it for its window; its manifest row and frame-log line."""
    if capture.kind == "reference":
        setpoints, clamped = layout.neutral_setpoints(), ()
        d_over_l = "n/a"
    else:
        rendering = renderers[capture.condition].render(
            Bump(capture.centre_mm, capture.diameter_mm, capture.height_mm))
        setpoints, clamped = rendering.setpoints, rendering.clamped
        d_over_l = layout.pitch_mm / capture.diameter_mm
    sent_at = clock.now() - origin
    report = device.send(setpoints)
    clock.sleep(protocol.timing.settle_s)
    start = clock.now() - origin
    utc = "n/a" if getattr(clock, "is_virtual", False) else _now()
    if kind == "prompt":
        prompt(f"{capture.name} on the display ({capture.condition}"
               + (")" if capture.kind == "reference" else
                  f", l = {capture.diameter_mm:g} mm at ({capture.centre_mm[0]:.1f}, "
                  f"{capture.centre_mm[1]:.1f}) mm)")
               + f": take the DIC capture, save its export as {capture.name}.csv, then press "
                 "Enter")
    else:
        clock.sleep(0.5 * protocol.timing.hold_s)
        if kind == "synthetic":
            captures = out / CAPTURES
            if capture.index == 0 or not (captures / "fiducials.csv").exists():
                rig.write_fiducials(captures, layout)
            shown = device.displayed_setpoints()
            rig.write_capture(captures, capture.name, layout,
                              protocol.models[capture.condition], shown, capture.index)
        clock.sleep(0.5 * protocol.timing.hold_s)
    device.heartbeat()  # every board read the frame: else the capture shows something else
    end = clock.now() - origin
    if end <= start:
        end = start
    row = {"capture_index": capture.index, "capture": capture.name, "kind": capture.kind,
           "condition": capture.condition,
           "diameter_mm": "n/a" if capture.kind == "reference" else capture.diameter_mm,
           "d_over_l": d_over_l,
           "x_mm": "n/a" if capture.kind == "reference" else capture.centre_mm[0],
           "y_mm": "n/a" if capture.kind == "reference" else capture.centre_mm[1],
           "height_mm": capture.height_mm, "sent_at": round(sent_at, 6),
           "capture_start": round(start, 6), "capture_end": round(end, 6),
           "capture_utc": utc, "clamped": " | ".join(clamped) if clamped else "n/a",
           "setpoints_mm": format_setpoints(setpoints)}
    frame = tsv_line([round(sent_at, 6), round(report.commanded_at, 6),
                      round(report.wire_done_at, 6), "/".join(map(str, report.bytes_sent)),
                      report.channels_sent, int(report.merged)]).rstrip("\n")
    return row, frame

