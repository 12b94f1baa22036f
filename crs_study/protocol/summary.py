"""A checked protocol and one participant's plan, summarised as typed data.

:func:`summarise` counts what a session of the protocol holds (trials per condition and per
level, blocks, breaks, prompts), which block order each counterbalance index gets, how long
a session takes, the frames and duration of every stimulus and the wire use, into a
:class:`ProtocolSummary`. ``crs-study validate`` prints it as text
(:mod:`crs_study.commands.validate`) or as JSON (:meth:`ProtocolSummary.to_dict`, whose
keys and values are documented there).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.protocol.model import Protocol, analysis_plan_path
from crs_study.protocol.plan import TrialPlan, block_orders, expected_duration_s
from crs_study.protocol.wire import WireBudget, wire_budget
from crs_study.stimuli.stimulus import Stimulus, make_stimulus

#: The columns of :meth:`ProtocolSummary.to_frame`.
SUMMARY_COLUMNS = ("condition", "practice_trials", "test_trials", "frames",
                   "mean_bytes_per_frame", "busiest_frame_wire_ms",
                   "busiest_frame_budget_percent", "changed_only_rate_hz", "latency_ms_median")


@dataclass(frozen=True)
class FrameRange:
    """The fewest, most and mean frames of a stimulus over a set of stimuli."""

    min: int
    max: int
    mean: float

    @classmethod
    def of(cls, counts: list[int]) -> FrameRange:
        return cls(min(counts), max(counts), float(np.mean(counts)))


@dataclass(frozen=True)
class ConditionTrials:
    """The practice and test trials of one condition (at one level, or over all)."""

    condition: str
    practice: int
    test: int


@dataclass(frozen=True)
class LevelSummary:
    """One level of a ``[levels]`` or ``[adaptive]`` protocol: its trials per condition
    (None where a procedure chooses the level during the session) and its frames per trial."""

    value: float
    trials: tuple[ConditionTrials, ...] | None
    frames_per_trial: FrameRange


@dataclass(frozen=True, eq=False)
class ProtocolSummary:
    """A checked protocol and one participant's plan, summarised (:func:`summarise`).

    ``protocol``, ``plan`` and ``wire`` (its :class:`~crs_study.protocol.WireBudget`) are the
    objects; the counts are fields (``trials`` per condition, ``levels``, ``block_orders`` by
    counterbalance index modulo the scheme's cycle, ``expected_duration_s``, the stimuli by
    ``(symbol, level)``) or properties of them. :meth:`to_dict` is the summary ``crs-study
    validate --json`` prints: ``protocol, sha256, study, stimulus_set, trials, block_orders,
    expected_duration_s, frames_per_trial, stimulus_duration_s, levels, adaptive,
    frame_rate_hz, wire, checks, warnings, analysis_plan, example_plan``; :meth:`to_frame`
    one row per condition (:data:`SUMMARY_COLUMNS`: its trials and its wire use, changed
    channels only).
    """

    protocol: Protocol
    plan: TrialPlan
    wire: WireBudget
    participant: str
    session: int
    counterbalance: int
    trials: tuple[ConditionTrials, ...]
    block_orders: tuple[tuple[str, ...], ...]
    expected_duration_s: float
    stimuli: dict[tuple[object, float | None], Stimulus]
    levels: tuple[LevelSummary, ...]
    analysis_plan_found: bool

    @property
    def breaks(self) -> int:
        return sum(t.break_before for t in self.plan.trials)

    @property
    def experimenter_prompts(self) -> int:
        return sum(t.prompt_before is not None for t in self.plan.trials)

    @property
    def frames(self) -> dict[str, int]:
        """Frames of each stimulus, by its label (``7``, or ``7@0.8`` at a level)."""
        return {_label(d, v): s.n_frames for (d, v), s in self.stimuli.items()}

    @property
    def frames_per_trial(self) -> FrameRange:
        return FrameRange.of(list(self.frames.values()))

    def to_dict(self, trials: bool = False) -> dict:
        """The summary; with ``trials`` also ``plan_trials``, every planned trial's fields."""
        protocol, plan, wire, shown = self.protocol, self.plan, self.wire, \
            self.protocol.symbol_set
        frames = self.frames
        content = {
            "protocol": str(protocol.path),
            "sha256": protocol.sha256,
            "study": {"id": protocol.study_id, "version": protocol.version,
                      "title": protocol.title, "device": protocol.layout().name},
            "stimulus_set": {"name": shown.name, "task": shown.task, "column": shown.column,
                             "symbols": [str(d) for d in protocol.symbols],
                             "keys": list(protocol.responses.keys),
                             "chance_rate": protocol.chance_rate},
            "trials": {"total": len(plan), "practice": plan.count("practice"),
                       "test": plan.count("test"),
                       "per_condition": _per_condition(self.trials),
                       "blocks": len(plan.block_conditions), "breaks": self.breaks,
                       "experimenter_prompts": self.experimenter_prompts},
            "block_orders": {"counterbalancing": protocol.design.counterbalancing,
                             "cycle": len(self.block_orders),
                             "by_counterbalance": [{"k_mod_cycle": k, "order": list(o)}
                                                   for k, o in enumerate(self.block_orders)],
                             "orders": [list(o) for o in sorted(set(self.block_orders))]},
            "expected_duration_s": self.expected_duration_s,
            "frames_per_trial": {**asdict(self.frames_per_trial),
                                 f"per_{shown.column}": frames},
            "stimulus_duration_s": {_label(d, v): s.duration_s
                                    for (d, v), s in self.stimuli.items()},
            "levels": self._levels_dict(),
            "adaptive": None if protocol.adaptive is None else
            adaptive_summary(protocol.adaptive),
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
                              "found": self.analysis_plan_found},
            "example_plan": {"participant": self.participant, "session": self.session,
                             "counterbalance": self.counterbalance, "seed": plan.seed,
                             "blocks": list(plan.block_conditions)},
        }
        if trials:
            content["plan_trials"] = [asdict(t) for t in plan.trials]
        return json.loads(json.dumps(content, default=str))

    def _levels_dict(self) -> dict | None:
        levels = self.protocol.levels
        if levels is None:
            return None
        return {"parameter": levels.parameter, "column": levels.column, "units": levels.units,
                "values": list(levels.values), "width_to_height": levels.width_to_height,
                "per_level": {f"{lv.value:g}": {
                    "per_condition": None if lv.trials is None else _per_condition(lv.trials),
                    "frames_per_trial": asdict(lv.frames_per_trial)} for lv in self.levels}}

    def to_json(self, trials: bool = False) -> str:
        """The summary as ``crs-study validate --json [--list]`` prints it."""
        return json.dumps(self.to_dict(trials), indent=2, sort_keys=True)

    def to_frame(self):
        """One row per condition (:data:`SUMMARY_COLUMNS`), a :class:`pandas.DataFrame`."""
        import pandas as pd  # only here: validate needs no pandas

        counts = {t.condition: t for t in self.trials}
        rows = [{"condition": c.condition, "practice_trials": counts[c.condition].practice,
                 "test_trials": counts[c.condition].test,
                 **{k: getattr(c, k) for k in SUMMARY_COLUMNS[3:]}}
                for c in self.wire.conditions]
        return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def summarise(protocol: Protocol, plan: TrialPlan, participant: str, session: int,
              counterbalance: int) -> ProtocolSummary:
    """The :class:`ProtocolSummary` of a checked ``protocol`` and the ``plan`` of
    ``participant``'s ``session`` at counterbalance index ``counterbalance``."""
    layout = protocol.layout()
    stimuli = {(d, v): make_stimulus(protocol, layout, d, v) for v in protocol.level_values
               for d in protocol.symbols}

    def counts(level: float | None = None) -> tuple[ConditionTrials, ...]:
        return tuple(ConditionTrials(c, plan.count("practice", c, level),
                                     plan.count("test", c, level))
                     for c in protocol.conditions)

    levels: tuple[LevelSummary, ...] = ()
    if protocol.levels is not None:
        levels = tuple(LevelSummary(
            v, None if protocol.adaptive is not None else counts(v),  # chosen live
            FrameRange.of([stimuli[(d, v)].n_frames for d in protocol.symbols]))
            for v in protocol.levels.values)
    return ProtocolSummary(
        protocol, plan, wire_budget(protocol, layout), participant, session, counterbalance,
        counts(), tuple(block_orders(protocol)), expected_duration_s(protocol, plan, layout),
        stimuli, levels, analysis_plan_path(protocol) is not None)


def adaptive_summary(spec: AdaptiveSpec) -> dict:
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


def _label(symbol: object, level: float | None) -> str:
    return str(symbol) if level is None else f"{symbol}@{level:g}"


def _per_condition(trials: tuple[ConditionTrials, ...]) -> dict:
    return {t.condition: {"practice": t.practice, "test": t.test} for t in trials}
