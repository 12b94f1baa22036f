"""Check a protocol strictly and print its plan: trials, expected duration, frames, wire use.

Every key is checked (unknown keys, types, ranges: one-line errors naming file, line, key and
value), then the stimulus against the device: inside the display, within the pixels' travel
and the CRS limits, the frame rate within the wire. Wire use is reported two ways: full
frames (every channel of every controller in every frame, the bound the check uses) and
changed-only frames (channels whose pulse width changes on the rendered frames, first frame
from neutral excluded from the busiest; :func:`crs_study.device.schedule.wire_plan`).
A protocol with ``[levels]`` also gets its levels and, per level, the trials of each condition
and the frames per trial; frames and wire use are then over every (symbol, level) stimulus.
"""

from __future__ import annotations

import argparse

from crs_study.api import validate


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
    summary = validate(args.protocol, participant=args.participant, session=args.session,
                       counterbalance=args.counterbalance)  # a path, or a shipped name
    if args.json:
        print(summary.to_json(trials=args.list))
        return 0
    print(_text(summary.to_dict()))
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


def _adaptive_lines(a: dict | None) -> list[str]:
    """The procedure and its level range (an ``[adaptive]`` protocol)."""
    if not a:
        return []
    lines = [f"adaptive: {a['procedure']} chooses {a['parameter']} in each block "
             f"({a['trials_per_block']} test trials), {a['min']:g} to {a['max']:g} on a "
             f"{a['scale']} scale ({len(a['grid'])} levels, each checked below); threshold "
             f"at {a['target_rate']:.4g} correct; practice at {a['practice_level']:g}"]
    if "staircase" in a:
        st = a["staircase"]
        stop = f", or at {st['stop_reversals']} reversals" if st["stop_reversals"] else ""
        lines.append(f"  staircase {st['rule']} from {st['start']:g}, steps {st['steps']} "
                     f"levels (easier step x {st['easier_step_ratio']:.4g}); stops after "
                     f"{a['trials_per_block']} trials{stop}; estimate: mean of the last "
                     f"{st['estimate_reversals']} reversals")
    if "quest_plus" in a:
        q = a["quest_plus"]
        lines.append(f"  QUEST+ (questplus): {q['thresholds']} thresholds, slopes "
                     f"{q['slopes']}, lapse rates {q['lapse_rates']}; next level by minimum "
                     "expected entropy")
    return lines


def _text(s: dict) -> str:
    minutes = s["expected_duration_s"] / 60
    t = s["trials"]
    lines = [
        f"{s['protocol']}: valid ({s['study']['id']} {s['study']['version']}, "
        f"device {s['study']['device']}, sha256 {s['sha256'][:12]})",
        f"trials: {t['total']} ({t['practice']} practice, {t['test']} test) in {t['blocks']} "
        f"blocks, {t['breaks']} breaks, {t['experimenter_prompts']} experimenter prompts",
    ]
    for condition, c in t["per_condition"].items():
        lines.append(f"  {condition}: {c['practice']} practice, {c['test']} test")
    shown = s["stimulus_set"]
    lines.append(f"stimulus set {shown['name']} (task {shown['task']}): "
                 f"{len(shown['symbols'])} symbols shown ({', '.join(shown['symbols'])}), keys "
                 f"{' '.join(shown['keys'])}; chance {100 * shown['chance_rate']:.1f} %")
    levels = s.get("levels")
    if levels:
        values = ", ".join(f"{v:g}" for v in levels["values"])
        shape = (f"; width = {levels['width_to_height']:g} x height"
                 if levels["width_to_height"] else "")
        lines.append(f"levels: {levels['parameter']} = {values} ({levels['units']}; dataset "
                     f"column {levels['column']}{shape})")
        lines += _adaptive_lines(s.get("adaptive"))
        for value, entry in levels["per_level"].items():
            counts = "" if entry["per_condition"] is None else ", ".join(
                f"{c} {n['practice']} practice + {n['test']} test"
                for c, n in entry["per_condition"].items()) + "; "
            fr = entry["frames_per_trial"]
            lines.append(f"  {levels['parameter']} = {value}: {counts}frames per trial "
                         f"{fr['min']} to {fr['max']} (mean {fr['mean']:.1f})")
    lines += _block_order_lines(s["block_orders"])
    f = s["frames_per_trial"]
    lines.append(f"frames per trial: {f['min']} to {f['max']} (mean {f['mean']:.1f}) at "
                 f"{s['frame_rate_hz']:g} frames/s")
    lines.append(f"expected duration: {minutes:.1f} min (stimuli, expected responses, "
                 "inter-trial intervals and breaks; not the experimenter's block changes)")
    w = s["wire"]
    lines.append(f"wire, full frames: {w['full_frame_bytes']} bytes/frame over all controllers, "
                 f"busiest controller {w['full_frame_busiest_controller_ms']:.1f} ms = "
                 f"{w['full_frame_budget_percent']:.0f} % of the frame period "
                 f"(max {w['full_frame_max_rate_hz']:.2f} frames/s)")
    for condition, c in w["changed_only"].items():
        lines.append(f"wire, changed channels only, {condition}: "
                     f"{c['mean_bytes_per_frame']:.1f} bytes/frame on average, busiest frame "
                     f"{c['busiest_frame_wire_ms']:.1f} ms = "
                     f"{c['busiest_frame_budget_percent']:.0f} % of the period (max "
                     f"{c['max_rate_hz']:.1f} frames/s between full refreshes), median "
                     f"latency {c['median_latency_ms']:.0f} ms (refreshes included)")
    lines.append("checks passed:")
    lines += [f"  ok  {c}" for c in s["checks"]]
    if s["warnings"]:
        lines.append("warnings (odd but legal values; see protocols/README.md, \"Warnings\"):")
        lines += [f"  warning  {w}" for w in s["warnings"]]
    plan = s["analysis_plan"]
    state = "found" if plan["found"] else "NOT FOUND: declare it before the first real session"
    lines.append(f"analysis plan {plan['path']}: {state}")
    return "\n".join(lines)


def _block_order_lines(orders: dict) -> list[str]:
    """Which participant gets which block order: counterbalance index k (the order of arrival
    in the dataset from 0, or ``run --counterbalance K``) modulo the scheme's cycle P."""
    cycle = orders["cycle"]
    rows = orders["by_counterbalance"]
    head = (f"block orders ({orders['counterbalancing']}) by counterbalance index k (order of "
            "arrival from 0, or --counterbalance K):")
    if cycle == 1:
        return [head, f"  every k: {' '.join(rows[0]['order'])}"]
    lines = [head]
    for row in rows:
        i = row["k_mod_cycle"]
        examples = ", ".join(str(i + j * cycle) for j in range(3))
        lines.append(f"  k mod {cycle} = {i} (k = {examples}, ...): {' '.join(row['order'])}")
    return lines
