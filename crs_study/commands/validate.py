"""Check a protocol strictly and print its plan: trials, expected duration, frames, wire use.

Every key is checked (unknown keys, types, ranges: one-line errors naming file, line, key and
value; every error one reading can find is listed, one a line:
:mod:`crs_study.protocol.problems`), then the stimulus against the device: inside the
display, within the pixels' travel and the CRS limits, the frame rate within the wire. Wire
use is reported two ways: full frames (every channel of every controller in every frame, the
bound the check uses) and changed-only frames (channels whose pulse width changes on the
rendered frames, first frame from neutral excluded from the busiest;
:func:`crs_study.device.schedule.wire_plan`). A protocol with ``[levels]`` also gets its
levels and, per level, the trials of each condition and the frames per trial; frames and wire
use are then over every (symbol, level) stimulus.
"""

from __future__ import annotations

import argparse
import sys

from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.api import ProtocolSummary, validate
from crs_study.errors import ProtocolProblems
from crs_study.protocol.lock import kept_shipped_id

#: The exit status of an invalid protocol (the command line's one for a known error).
EXIT_INVALID = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", metavar="PROTOCOL", help="protocol file (TOML)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--participant", default="example", metavar="ID",
                        help="participant label for --list (the plan depends on it)")
    parser.add_argument("--session", type=int, default=1, metavar="N", help="session number")
    parser.add_argument("--counterbalance", type=int, default=0, metavar="K",
                        help="counterbalance index (order of arrival, from 0)")
    parser.add_argument("--list", action="store_true", help="also list every planned trial")


def run(args: argparse.Namespace) -> int:
    try:
        summary = validate(args.protocol, participant=args.participant, session=args.session,
                           counterbalance=args.counterbalance)  # a path, or a shipped name
    except ProtocolProblems as problems:  # every one found, one line each
        for problem in problems.problems:
            print(f"crs-study validate: error: {problem}", file=sys.stderr)
        print(f"crs-study validate: {len(problems.problems)} errors in {problems.source}",
              file=sys.stderr)
        return EXIT_INVALID
    kept = kept_shipped_id(summary.protocol)
    if kept is not None:
        print(f"crs-study validate: warning: study id {summary.protocol.study_id!r} is the "
              f"shipped {kept} protocol's: give the copy an id of its own ([study] id), since "
              "the id seeds every session's trial order", file=sys.stderr)
    if args.json:
        print(summary.to_json(trials=args.list))
        return 0
    print(_text(summary))
    if args.list:
        with_levels = summary.protocol.levels is not None
        print()
        print(f"index type     block condition   rep {summary.protocol.symbol_set.column:>5s} "
              + ("   level " if with_levels else "") + "feedback break prompt")
        for t in summary.plan.trials:
            level = f"{t.level:8g} " if with_levels else ""
            print(f"{t.index:5d} {t.trial_type:8s} {t.block:5d} {t.condition:11s} "
                  f"{t.repetition:3d} {t.symbol!s:>5s} {level}{'yes' if t.feedback else 'no':8s} "
                  f"{'yes' if t.break_before else '':5s} {t.prompt_before or ''}")
    return 0


def _adaptive_lines(spec: AdaptiveSpec | None) -> list[str]:
    """The procedure and its level range (an ``[adaptive]`` protocol)."""
    if spec is None:
        return []
    lines = [f"adaptive: {spec.procedure} chooses {spec.parameter} in each block "
             f"({spec.trials} test trials), {spec.minimum:g} to {spec.maximum:g} on a "
             f"{spec.scale} scale ({len(spec.grid())} levels, each checked below); threshold "
             f"at {spec.rate:.4g} correct; practice at {spec.practice:g}"]
    if spec.staircase is not None:
        st = spec.staircase
        stop = f", or at {st.stop_reversals} reversals" if st.stop_reversals else ""
        lines.append(f"  staircase {st.rule} from {st.start:g}, steps {list(st.steps)} "
                     f"levels (easier step x {spec.easier_ratio:.4g}); stops after "
                     f"{spec.trials} trials{stop}; estimate: mean of the last "
                     f"{st.estimate_reversals} reversals")
    if spec.quest_plus is not None:
        q = spec.quest_plus
        lines.append(f"  QUEST+ (questplus): {q.thresholds} thresholds, slopes "
                     f"{list(q.slopes)}, lapse rates {list(q.lapse_rates)}; next level by "
                     "minimum expected entropy")
    return lines


def _text(s: ProtocolSummary) -> str:
    protocol, plan, wire = s.protocol, s.plan, s.wire
    minutes = s.expected_duration_s / 60
    lines = [
        f"{protocol.path}: valid ({protocol.study_id} {protocol.version}, "
        f"device {protocol.layout().name}, sha256 {protocol.sha256[:12]})",
        f"trials: {len(plan)} ({plan.count('practice')} practice, {plan.count('test')} test) "
        f"in {len(plan.block_conditions)} blocks, {s.breaks} breaks, "
        f"{s.experimenter_prompts} experimenter prompts",
    ]
    lines += [f"  {c.condition}: {c.practice} practice, {c.test} test" for c in s.trials]
    shown = protocol.symbol_set
    symbols = [str(d) for d in protocol.symbols]
    lines.append(f"stimulus set {shown.name} (task {shown.task}): "
                 f"{len(symbols)} symbols shown ({', '.join(symbols)}), keys "
                 f"{' '.join(protocol.responses.keys)}; chance "
                 f"{100 * protocol.chance_rate:.1f} %")
    levels = protocol.levels
    if levels is not None:
        values = ", ".join(f"{v:g}" for v in levels.values)
        shape = (f"; width = {levels.width_to_height:g} x height"
                 if levels.width_to_height else "")
        lines.append(f"levels: {levels.parameter} = {values} ({levels.units}; dataset "
                     f"column {levels.column}{shape})")
        lines += _adaptive_lines(protocol.adaptive)
        for level in s.levels:
            counts = "" if level.trials is None else ", ".join(
                f"{c.condition} {c.practice} practice + {c.test} test"
                for c in level.trials) + "; "
            fr = level.frames_per_trial
            lines.append(f"  {levels.parameter} = {level.value:g}: {counts}frames per trial "
                         f"{fr.min} to {fr.max} (mean {fr.mean:.1f})")
    lines += _block_order_lines(protocol.design.counterbalancing, s.block_orders)
    f = s.frames_per_trial
    lines.append(f"frames per trial: {f.min} to {f.max} (mean {f.mean:.1f}) at "
                 f"{protocol.frame_rate_hz:g} frames/s")
    lines.append(f"expected duration: {minutes:.1f} min (stimuli, expected responses, "
                 "inter-trial intervals and breaks; not the experimenter's block changes)")
    lines.append(f"wire, full frames: {wire.full_frame_bytes} bytes/frame over all "
                 f"controllers, busiest controller {wire.full_frame_busiest_controller_ms:.1f} "
                 f"ms = {wire.full_frame_budget_percent:.0f} % of the frame period "
                 f"(max {wire.full_frame_max_rate_hz:.2f} frames/s)")
    for c in wire.conditions:
        lines.append(f"wire, changed channels only, {c.condition}: "
                     f"{c.mean_bytes_per_frame:.1f} bytes/frame on average, busiest frame "
                     f"{c.busiest_frame_wire_ms:.1f} ms = "
                     f"{c.busiest_frame_budget_percent:.0f} % of the period (max "
                     f"{c.changed_only_rate_hz:.1f} frames/s between full refreshes), median "
                     f"latency {c.latency_ms_median:.0f} ms (refreshes included)")
    lines.append("checks passed:")
    lines += [f"  ok  {c}" for c in protocol.checks]
    if protocol.warnings:
        lines.append("warnings (odd but legal values; see protocols/README.md, \"Warnings\"):")
        lines += [f"  warning  {w}" for w in protocol.warnings]
    state = "found" if s.analysis_plan_found else \
        "NOT FOUND: declare it before the first real session"
    lines.append(f"analysis plan {protocol.analysis_plan}: {state}")
    return "\n".join(lines)


def _block_order_lines(counterbalancing: str, orders: tuple[tuple[str, ...], ...]
                       ) -> list[str]:
    """Which participant gets which block order: counterbalance index k (the order of arrival
    in the dataset from 0, or ``run --counterbalance K``) modulo the scheme's cycle P."""
    cycle = len(orders)
    head = (f"block orders ({counterbalancing}) by counterbalance index k (order of "
            "arrival from 0, or --counterbalance K):")
    if cycle == 1:
        return [head, f"  every k: {' '.join(orders[0])}"]
    lines = [head]
    for i, order in enumerate(orders):
        examples = ", ".join(str(i + j * cycle) for j in range(3))
        lines.append(f"  k mod {cycle} = {i} (k = {examples}, ...): {' '.join(order)}")
    return lines
