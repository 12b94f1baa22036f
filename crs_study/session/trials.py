"""The trial loop: one trial's stimulus on the device, the response, the stored row.

One trial (all times on the session's :class:`~crs_study.clock.Clock`):

1. a prompt to the experimenter at a block start or a break (mount or remove the skeleton);
   simulated responders continue at once, the keypad waits for Space or Enter;
2. the stimulus: the pre-rendered frames of the (symbol, condition) pair are commanded at the
   protocol's frame rate, each at its due time ``onset + frame_times[k]`` (``sleep_until``); a
   frame commanded more than one period after its due time counts as late; the displayed
   setpoints are sampled one period after each frame (what the skin meets) for the responder;
   at the offset, the end of the last frame's period (``onset + n / f``), the display returns
   to the neutral (flat) pose;
3. the response (:class:`~crs_study.session.responders.base.Responder`), with the protocol's
   time limit from stimulus offset (a pause in place during the stimulus or the response,
   :class:`~crs_study.session.responders.base.PauseInPlace`, leaves the trial unstored: the
   runner plays it again);
4. the heartbeat, asked right after the stimulus and checked after the response
   (:meth:`~crs_study.device.Device.heartbeat_ask`): every board must answer, else
   the trial is not stored (a :class:`~crs_study.errors.DeviceError`: the session stops
   safely, and the trial is rerun on resume with ``device_fault = 1``), since a board that
   stopped reading may have shown none of it;
5. the trial's frame log and its row are stored durably (:mod:`crs_study.dataset`), then the
   sidecar; feedback after practice trials; the inter-trial interval.

Before the stimulus the session lock file notes the trial as begun
(:meth:`~crs_study.dataset.SessionStore.mark_started`), so a resume after a crash knows
whether the participant felt part of it (its rerun's row then says ``rerun = 1``).

The frames come from the one cache of rendered frames
(:func:`crs_study.rendering.frames.render_frames`); :class:`TrialFrames` adds only the
renderer of each condition and the frame log's text of each stimulus.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from crs_study.clock import Clock
from crs_study.dataset.session_store import UNDURABLE_SIDECAR_EVERY
from crs_study.device import Device, FrameReport
from crs_study.errors import SessionError
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import PlannedTrial
from crs_study.rendering.feed_cap import DEFAULT_WIRE, WireSlack
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.session.adaptive import is_adaptive, row_fields
from crs_study.session.prompts import BREAK_PROMPT
from crs_study.session.responders.base import PauseInPlace, Responder, StimulusRecord
from crs_study.session.state import SessionState, save
from crs_study.signals import deferred
from crs_study.stimuli.stimulus import make_stimulus
from crs_study.stimuli.strokes import Symbol

#: Without per-trial durability (dry-runs) the sidecar is rewritten every this many trials
#: (and when the session stops); the trial file is the authority on what is done.
DRY_RUN_SIDECAR_EVERY = UNDURABLE_SIDECAR_EVERY
FRAME_LOG_COLUMNS = ("kind", "frame", "due", "commanded_at", "wire_done_at", "bytes",
                     "channels", "merged")


def ceil_ms(seconds: float) -> float:
    """The next whole millisecond at or after ``seconds`` (exactly ``k / 1000``)."""
    return math.ceil(round(seconds * 1000.0, 6)) / 1000.0


class TrialFrames:
    """The frames of each (symbol, condition, level) of a protocol on a device; ``level`` is
    None for protocols without ``[levels]``. Rendering and its cache are
    :func:`~crs_study.rendering.frames.render_frames`'; here are the renderer of each
    condition and the frames' text for the frame log."""

    def __init__(self, protocol: Protocol, layout: Layout, wire: WireSlack = DEFAULT_WIRE
                 ) -> None:
        self.protocol = protocol
        self.layout = layout
        self.wire = wire  # the device's write policy: the feed cap leaves room for it
        self._renderers: dict[str, Renderer] = {}
        self._text: dict[tuple[Symbol, str, float | None], list[str]] = {}

    def get(self, symbol: Symbol, condition: str, level: float | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
        """``(frame_times (n,), setpoints (n, n_actuators))``, both read-only."""
        stimulus = make_stimulus(self.protocol, self.layout, symbol, level)
        if condition not in self._renderers:
            self._renderers[condition] = Renderer(self.layout, condition, wire=self.wire)
        frames = render_frames(stimulus, self._renderers[condition])
        times = stimulus.frame_times
        if frames.ndim != 2 or len(frames) != len(times) or len(times) == 0:
            raise SessionError(f"stimulus of {symbol!r} ({condition}): {len(times)} "
                               f"frame times but frames of shape {frames.shape}")
        return times, frames

    def setpoint_text(self, symbol: Symbol, condition: str, level: float | None = None
                      ) -> list[str]:
        """The frames' setpoints as tab-separated text (mm, 4 decimals), for the frame log."""
        key = (symbol, condition, level)
        if key not in self._text:
            _, frames = self.get(symbol, condition, level)
            self._text[key] = ["\t".join(f"{v:.4f}" for v in row) for row in frames.tolist()]
        return self._text[key]


_trial_frames: dict[tuple[str, str, WireSlack], TrialFrames] = {}


def trial_frames(protocol: Protocol, layout: Layout, wire: WireSlack = DEFAULT_WIRE
                 ) -> TrialFrames:
    """One :class:`TrialFrames` per protocol, device file and write policy's slack per process
    (shared by dry-run participants). ``wire``: the device's
    (:meth:`~crs_study.rendering.feed_cap.WireSlack.for_device`)."""
    key = (protocol.sha256, layout.source, wire)
    if key not in _trial_frames:
        _trial_frames[key] = TrialFrames(protocol, layout, wire)
    return _trial_frames[key]


def symbol_choices(protocol: Protocol) -> tuple[Symbol, ...]:
    """The symbols a response may name: those the protocol shows."""
    return tuple(protocol.symbols)


@dataclass
class Shown:
    """What one stimulus presentation did on the device."""

    onset: float
    offset: float
    reports: list[FrameReport]
    displayed: np.ndarray
    late: int
    neutral_due: float
    neutral: FrameReport


def present(device: Device, clock: Clock, frame_times: np.ndarray, frames: np.ndarray,
            period: float, poll: Callable[[], None] | None = None) -> Shown:
    """Command the frames at ``onset + frame_times[k]``, then neutral at the offset.

    ``poll`` is called before each frame (the keypad's q, Escape and p act during the
    stimulus): whatever it raises, the display goes neutral first."""
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
        if poll is not None:
            try:
                poll()
            except BaseException:
                device.neutral()  # flat before anything else is done
                raise
        reports.append(device.send(frames[i]))
    offset = onset + float(frame_times[-1]) + period  # end of the last frame's period
    clock.sleep_until(offset)
    displayed[n - 1] = device.displayed_setpoints(clock.now())
    neutral_due = clock.now()
    neutral = device.neutral()  # the display goes flat at the stimulus offset
    return Shown(onset, offset, reports, displayed, late, neutral_due, neutral)


def replay(state: SessionState, device: Device, clock: Clock, frames: TrialFrames) -> None:
    """Bring a fresh simulated device to where an uninterrupted run had it (virtual clock).

    The stored trials' frames are commanded again at their original session times (no
    responder, nothing written), so the device's history (wire timing, refresh phase, servo
    positions) and therefore every later trial are exactly those of an uninterrupted run.
    """
    period = 1.0 / float(state.protocol.frame_rate_hz)
    for row in state.rows:
        trial = state.plan.trials[int(row["trial_index"])]
        level = trial.level
        if state.adaptive is not None and trial.trial_type == "test":  # chosen when shown
            level = float(row[state.protocol.levels.column])
        frame_times, setpoints = frames.get(trial.symbol, trial.condition, level)
        present(device, clock, frame_times, setpoints, period)
        device.heartbeat()  # asked after the stimulus, as the trial did
        clock.sleep_until(float(row["trial_end"]))


def frame_line(kind: str, frame: int, due: float, report: FrameReport, origin: float,
               setpoints: str) -> str:
    """One frame-log line (without the trial column): times in session seconds."""
    return (f"{kind}\t{frame}\t{due - origin:.6f}\t{report.commanded_at - origin:.6f}\t"
            f"{report.wire_done_at - origin:.6f}\t{','.join(map(str, report.bytes_sent))}\t"
            f"{report.channels_sent}\t{int(report.merged)}\t{setpoints}")


def run_trial(state: SessionState, device: Device, responder: Responder, clock: Clock,
              origin: float, frames: TrialFrames, trial: PlannedTrial) -> None:
    """Play ``trial``, collect its response and store it durably (the module docstring).

    In an adaptive protocol ``trial`` carries the level its block's procedure chose
    (:func:`crs_study.session.adaptive.choose`); the response is given to the procedure and
    its new state goes into the row (:data:`crs_study.dataset.schema.ADAPTIVE_COLUMNS`)."""
    protocol = state.protocol
    if trial.prompt_before or trial.break_before:
        text = trial.prompt_before or BREAK_PROMPT
        if trial.break_before:  # the rest it is meant to be: the keypad counts it down
            responder.prompt(text, clock, rest_s=float(protocol.design.break_duration_s))
        else:
            responder.prompt(text, clock)
    if trial.break_before and not responder.needs_real_clock:  # a person rests until ready
        clock.sleep(float(protocol.design.break_duration_s))
    level = trial.level
    frame_times, setpoints = frames.get(trial.symbol, trial.condition, level)
    period = 1.0 / float(protocol.frame_rate_hz)
    responder.begin_trial(trial, clock.now(), clock)
    state.store.mark_started(trial.index)
    state.started = trial.index
    shown = present(device, clock, frame_times, setpoints, period, responder.poll)
    asked = device.heartbeat_ask()  # after the last frame; answered while the person responds
    onset, offset, reports = shown.onset, shown.offset, shown.reports
    record = StimulusRecord(state.layout, trial.condition, frame_times + period, shown.displayed,
                            symbol_choices(protocol), onset, offset)
    try:
        response = responder.respond(trial, record, clock, protocol.time_limit_s)
    except PauseInPlace:
        device.heartbeat_check(asked)  # the answer taken, so the next trial's is its own
        raise
    duration = offset - onset
    rt = float(response.response_time_s)
    correct = None if response.symbol is None else int(response.symbol == trial.symbol)
    trial_end = ceil_ms(clock.now() - origin + float(protocol.inter_trial_interval_s))
    device.heartbeat_check(asked)  # every board read the whole trial, or it is not stored
    latencies = [r.wire_done_at - (onset + frame_times[i]) for i, r in enumerate(reports)]
    n = len(frame_times)
    row = {
        "trial_index": trial.index, "trial_type": trial.trial_type, "block": trial.block,
        "condition": trial.condition, "repetition": trial.repetition,
        protocol.symbol_set.column: trial.symbol,
        "response": response.symbol, "correct": correct, "response_time": rt,
        "response_time_from_offset": rt - duration, "onset": onset - origin,
        "stimulus_duration": duration, "timed_out": int(response.symbol is None),
        "device_fault": int(trial.index in state.faults),
        "rerun": int(trial.index in state.cut), "frames": n,
        "late_frames": shown.late, "median_wire_latency": float(np.median(latencies)),
        "responder": responder.name, "trial_end": trial_end,
    }
    if protocol.levels is not None:
        row[protocol.levels.column] = level
    if state.adaptive is not None:
        update = state.adaptive.update(trial.block, correct) \
            if is_adaptive(trial, state.adaptive) else None
        row.update(row_fields(update))
    text = frames.setpoint_text(trial.symbol, trial.condition, level)
    log = [frame_line("stimulus", i, onset + frame_times[i], r, origin, text[i])
           for i, r in enumerate(reports)]
    flat = "\t".join(f"{v:.4f}" for v in state.layout.neutral_setpoints().tolist())
    log.append(frame_line("neutral", n, shown.neutral_due, shown.neutral, origin, flat))
    columns = FRAME_LOG_COLUMNS + tuple(f"a{j:02d}" for j in range(setpoints.shape[1]))
    with deferred():  # stored whole: frames, row, rows in memory, sidecar
        state.store.append_frames(trial.index, columns, log)
        state.store.append_row(row)
        state.rows.append({k: str(v) for k, v in row.items()})
        if state.adaptive is not None:
            state.adaptive_sha256 = state.adaptive.fingerprint()
        state.started = None
        state.late_frames += shown.late
        if state.spec.durable or len(state.rows) % DRY_RUN_SIDECAR_EVERY == 0:
            save(state, "running")
    if trial.feedback:
        responder.feedback(trial, response, bool(correct))
    responder.end_trial()
    clock.sleep_until(origin + trial_end)
