"""Rehearse a protocol on the simulated device with simulated participants, fast.

Participants are labelled sim01..simNN and counterbalanced by their number (participant i
gets counterbalance index i - 1). The clock is virtual, so a session of twenty minutes takes
seconds; every trial is stored exactly as in a real session (BIDS beh). Rerunning the same
command resumes unfinished sessions and leaves finished ones alone.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from crs_study._files import os_errors
from crs_study.commands.run import stderr_progress
from crs_study.errors import DatasetError
from crs_study.paths import resolve_protocol
from crs_study.protocol import emit_warnings, load_protocol
from crs_study.session.dry_runs import dry_run


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", metavar="PROTOCOL",
                        help="protocol file (TOML), or a shipped protocol's name (pilot, "
                        "digit_identification, ...)")
    parser.add_argument("--participants", type=int, required=True, metavar="N",
                        help="number of simulated participants")
    parser.add_argument("--out", required=True, type=Path, metavar="DATASET",
                        help="dataset directory (BIDS); created when missing")
    parser.add_argument("--jobs", type=int, default=1, metavar="J",
                        help="worker processes (sessions run in parallel)")
    parser.add_argument("--responder", default="observer", metavar="observer|random",
                        help="simulated participant")
    parser.add_argument("--device", default="sim://", metavar="URL",
                        help="simulated device URL, e.g. sim:// or sim://?options")
    parser.add_argument("--fsync", action="store_true",
                        help="fsync after every trial as a real session does (default: when "
                        "each session stops; a rerun regenerates anything a power cut loses)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON summary on stdout and no progress")


@os_errors(DatasetError)  # disk full, permission denied, a file where a folder should be: one line
def run(args: argparse.Namespace) -> int:
    protocol = resolve_protocol(args.protocol)
    emit_warnings(load_protocol(protocol))  # odd but legal values, once, up front
    results = dry_run(protocol, args.participants, args.out, jobs=args.jobs,
                      responder=args.responder, device_url=args.device,
                      progress=stderr_progress(not args.json), durable=args.fsync)
    trials = sum(r.trials_completed for r in results)
    session_s = sum(r.session_seconds for r in results)
    if args.json:
        print(json.dumps({
            "dataset": os.fspath(args.out), "participants": len(results), "trials": trials,
            "session_seconds": session_s,
            "sessions": [{"participant": r.participant, "status": r.status,
                          "trials_completed": r.trials_completed,
                          "late_frames": r.late_frames} for r in results]}))
    else:
        print(f"dry-run: {len(results)} participants, {trials} trials "
              f"({session_s / 60:.1f} min of simulated session time) in {args.out}")
    return 0 if all(r.status in ("complete", "already-complete") for r in results) else 130
