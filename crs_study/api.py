"""The functions of the Python API that join stages (``crs_study`` re-exports them).

The rest of the API is the stages' own functions, re-exported as they are by
:mod:`crs_study`: :func:`~crs_study.protocol.load_protocol`, :func:`~crs_study.session.dry_run`,
:func:`~crs_study.analysis.load_dataset` and :func:`~crs_study.analysis.analyze`. Here:

* :func:`make_plan`: one participant's trial plan, from any protocol source;
* :func:`validate`: a protocol checked, and its plan summarised (what ``crs-study validate``
  prints) as a :class:`ProtocolSummary`;
* :func:`run_session`: one participant's session, begun or resumed, from keyword arguments
  (``crs-study run``; :func:`crs_study.session.run_session` takes a
  :class:`~crs_study.session.SessionSpec`).

Every function takes a protocol as a file, a shipped protocol's name or a
:class:`~crs_study.protocol.Protocol` object (one changed with :func:`dataclasses.replace`
runs as :func:`~crs_study.protocol.load_protocol` settles it).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from crs_study.protocol import (
    Protocol,
    TrialPlan,
    WireBudget,
    analysis_plan_path,
    load_protocol,
    wire_budget,
)
from crs_study.protocol import make_plan as plan_of
from crs_study.protocol.plan import block_orders, expected_duration_s
from crs_study.session import SessionResult, SessionSpec
from crs_study.session import run_session as run_spec
from crs_study.session.spec import Progress
from crs_study.stimuli.stimulus import make_stimulus

ProtocolSource = str | os.PathLike[str] | Protocol

#: The columns of :meth:`ProtocolSummary.to_frame`.
SUMMARY_COLUMNS = ("condition", "practice_trials", "test_trials", "frames",
                   "mean_bytes_per_frame", "busiest_frame_wire_ms",
                   "busiest_frame_budget_percent", "changed_only_rate_hz", "latency_ms_median")


@dataclass(frozen=True, eq=False)
class ProtocolSummary:
    """A checked protocol and one participant's plan, summarised (:func:`validate`).

    ``protocol``, ``plan`` and ``wire`` (its :class:`~crs_study.protocol.WireBudget`) are
    the objects; :meth:`to_dict` the summary ``crs-study
    validate --json`` prints: ``protocol, sha256, study, trials, block_orders,
    expected_duration_s, frames_per_trial, stimulus_duration_s, levels, frame_rate_hz, wire,
    checks, warnings, analysis_plan, example_plan``; :meth:`to_frame` one row per condition
    (:data:`SUMMARY_COLUMNS`: its trials and its wire use, changed channels only).
    """

    protocol: Protocol
    plan: TrialPlan
    wire: WireBudget
    content: dict = field(repr=False)

    def to_dict(self, trials: bool = False) -> dict:
        """The summary; with ``trials`` also ``plan_trials``, every planned trial's fields."""
        content = dict(self.content)
        if trials:
            content["plan_trials"] = [asdict(t) for t in self.plan.trials]
        return json.loads(json.dumps(content, default=str))

    def to_json(self, trials: bool = False) -> str:
        """The summary as ``crs-study validate --json [--list]`` prints it."""
        return json.dumps(self.to_dict(trials), indent=2, sort_keys=True)

    def to_frame(self):
        """One row per condition (:data:`SUMMARY_COLUMNS`), a :class:`pandas.DataFrame`."""
        import pandas as pd  # only here: validate needs no pandas

        rows = [{"condition": c.condition, "practice_trials": self.plan.count("practice",
                                                                               c.condition),
                 "test_trials": self.plan.count("test", c.condition),
                 **{k: getattr(c, k) for k in SUMMARY_COLUMNS[3:]}}
                for c in self.wire.conditions]
        return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def make_plan(protocol: ProtocolSource, participant: str, session: int = 1,
              counterbalance: int = 0) -> TrialPlan:
    """The trial plan of ``participant``'s ``session`` at counterbalance index
    ``counterbalance`` (the order of arrival from 0), as a run of ``protocol`` plays it
    (deterministic: :mod:`crs_study.protocol.plan`)."""
    return plan_of(load_protocol(protocol), participant, session, counterbalance)


def adaptive_summary(spec) -> dict:
    """What ``validate`` says of an ``[adaptive]`` table: procedure, trials, level range."""
    details = {"procedure": spec.procedure, "parameter": spec.parameter,
               "trials_per_block": spec.trials, "min": spec.minimum, "max": spec.maximum,
               "scale": spec.scale, "grid": list(spec.grid()), "target_rate": spec.rate,
               "practice_level": spec.practice}
    if spec.staircase is not None:
        stair = spec.staircase
        details["staircase"] = {"rule": stair.rule, "start": stair.start,
                                "steps": list(stair.steps),
                                "easier_step_ratio": spec.easier_ratio,
                                "stop_reversals": stair.stop_reversals,
                                "estimate_reversals": stair.estimate_reversals}
    if spec.quest_plus is not None:
        quest = spec.quest_plus
        details["quest_plus"] = {"thresholds": quest.thresholds, "slopes": list(quest.slopes),
                                 "lapse_rates": list(quest.lapse_rates)}
    return details


def validate(protocol: ProtocolSource, *, participant: str = "example", session: int = 1,
             counterbalance: int = 0) -> ProtocolSummary:
    """Check a protocol strictly (every key, then against its device) and summarise the plan
    of ``participant``: trials, blocks and their orders, expected duration, frames, wire use.

    Raises :class:`~crs_study.errors.ProtocolError` (one line: file, line, key, value) for
    the first problem.
    """
    protocol = load_protocol(protocol)
    layout = protocol.layout()
    plan = plan_of(protocol, participant, session, counterbalance)
    levels = protocol.level_values
    stimuli = {(d, v): make_stimulus(protocol, layout, d, v) for v in levels
               for d in protocol.symbols}
    shown = protocol.symbol_set

    def label(d: object, v: float | None) -> str:
        return str(d) if v is None else f"{d}@{v:g}"

    def frame_range(values: list[int]) -> dict:
        return {"min": min(values), "max": max(values), "mean": float(np.mean(values))}

    frames = {label(d, v): s.n_frames for (d, v), s in stimuli.items()}
    wire = wire_budget(protocol, layout)
    by_index = block_orders(protocol)
    level_summary = None
    if protocol.levels is not None:
        level_summary = {
            "parameter": protocol.levels.parameter, "column": protocol.levels.column,
            "units": protocol.levels.units, "values": list(protocol.levels.values),
            "width_to_height": protocol.levels.width_to_height,
            "per_level": {f"{v:g}": {
                "per_condition": None if protocol.adaptive is not None else  # chosen live
                {c: {"practice": plan.count("practice", c, v), "test": plan.count("test", c, v)}
                 for c in protocol.conditions},
                "frames_per_trial": frame_range([stimuli[(d, v)].n_frames
                                                 for d in protocol.symbols])}
                for v in protocol.levels.values},
        }
    content = {
        "protocol": str(protocol.path),
        "sha256": protocol.sha256,
        "study": {"id": protocol.study_id, "version": protocol.version,
                  "title": protocol.title, "device": layout.name},
        "stimulus_set": {"name": shown.name, "task": shown.task, "column": shown.column,
                         "symbols": [str(d) for d in protocol.symbols],
                         "keys": list(protocol.responses.keys),
                         "chance_rate": protocol.chance_rate},
        "trials": {"total": len(plan), "practice": plan.count("practice"),
                   "test": plan.count("test"),
                   "per_condition": {c: {"practice": plan.count("practice", c),
                                         "test": plan.count("test", c)}
                                     for c in protocol.conditions},
                   "blocks": len(plan.block_conditions),
                   "breaks": sum(t.break_before for t in plan.trials),
                   "experimenter_prompts": sum(t.prompt_before is not None
                                               for t in plan.trials)},
        "block_orders": {"counterbalancing": protocol.design.counterbalancing,
                         "cycle": len(by_index),
                         "by_counterbalance": [{"k_mod_cycle": k, "order": list(o)}
                                               for k, o in enumerate(by_index)],
                         "orders": [list(o) for o in sorted(set(by_index))]},
        "expected_duration_s": expected_duration_s(protocol, plan, layout),
        "frames_per_trial": {**frame_range(list(frames.values())), f"per_{shown.column}": frames},
        "stimulus_duration_s": {label(d, v): s.duration_s for (d, v), s in stimuli.items()},
        "levels": level_summary,
        "adaptive": None if protocol.adaptive is None else adaptive_summary(protocol.adaptive),
        "frame_rate_hz": protocol.frame_rate_hz,
        "wire": {
            "full_frame_bytes": wire.full_frame_bytes,
            "full_frame_busiest_controller_ms": wire.full_frame_busiest_controller_ms,
            "full_frame_budget_percent": wire.full_frame_budget_percent,
            "full_frame_max_rate_hz": wire.full_frame_max_rate_hz,
            "changed_only": {c.condition: {
                "mean_bytes_per_frame": c.mean_bytes_per_frame,
                "busiest_frame_wire_ms": c.busiest_frame_wire_ms,
                "busiest_frame_budget_percent": c.busiest_frame_budget_percent,
                "max_rate_hz": c.changed_only_rate_hz,
                "median_latency_ms": c.latency_ms_median,
            } for c in wire.conditions},
        },
        "checks": list(protocol.checks),
        "warnings": list(protocol.warnings),
        "analysis_plan": {"path": protocol.analysis_plan,
                          "found": analysis_plan_path(protocol) is not None},
        "example_plan": {"participant": participant, "session": session,
                         "counterbalance": counterbalance, "seed": plan.seed,
                         "blocks": list(plan.block_conditions)},
    }
    return ProtocolSummary(protocol, plan, wire, content)


def run_session(protocol: ProtocolSource, participant: str, out: str | os.PathLike[str], *,
                device_url: str = "sim://", session: int = 1, responder: str = "keypad",
                clock: str = "auto", counterbalance: int | None = None,
                consent_register: str | os.PathLike[str] | None = None,
                progress: Progress | None = None) -> SessionResult:
    """Run (or resume) one participant's session and store it in the dataset ``out``.

    Parameters
    ----------
    protocol : a protocol file, a shipped protocol's name or a ``Protocol`` object.
    participant : the participant's label (letters and digits; never a name).
    out : the dataset folder (BIDS); made when missing.
    device_url : ``sim://[?options]`` or ``serial:///dev/ttyUSB0,/dev/ttyUSB1``.
    session : the session number (a completed session is never rewritten).
    responder : ``keypad`` (a person at the terminal), ``scripted:FILE``, ``observer`` or
        ``random`` (simulated participants).
    clock : ``real``, ``virtual`` or ``auto`` (virtual for ``sim://`` with a simulated
        responder).
    counterbalance : the counterbalance index (default: the order of arrival).
    consent_register : the consent register: a person's label needs a consent record on
        every device, ``sim://`` included (only a ``sim...`` label with a simulated
        responder on ``sim://`` needs none).
    progress : called with one line of progress at a time.

    Returns
    -------
    SessionResult
        ``status`` ``complete``, ``interrupted`` (Ctrl-C: run again to resume) or
        ``already-complete``.
    """
    spec = SessionSpec(protocol, participant, Path(out), device_url, session, responder, clock,
                       counterbalance, None if consent_register is None
                       else Path(consent_register))
    return run_spec(spec, progress=progress)
