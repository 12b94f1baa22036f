"""Rehearse a protocol on the simulated device with simulated participants, fast.

Participants are labelled sim01..simNN and counterbalanced by their number (participant i
gets counterbalance index i - 1). The clock is virtual, so a session of twenty minutes takes
seconds; every trial is stored exactly as in a real session (BIDS beh). Rerunning the same
command resumes unfinished sessions and leaves finished ones alone.
"""

from __future__ import annotations

import argparse

from crs_study._files import os_errors
from crs_study.commands.run import stderr_progress
from crs_study.dataset import dataset_dir
from crs_study.errors import DatasetError
from crs_study.protocol import emit_warnings, load_protocol
from crs_study.session import dry_run
from crs_study.session.dry_runs import check_participant_count


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", metavar="PROTOCOL",
                        help="protocol file (TOML), or a shipped protocol's name (pilot, "
                        "digit_identification, ...)")
    parser.add_argument("--participants", type=int, required=True, metavar="N",
                        help="number of simulated participants")
    parser.add_argument("--out", required=True, metavar="DATASET",
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
    out = dataset_dir(args.out)  # before any work: --out '' is not the current folder
    check_participant_count(args.participants)
    protocol = load_protocol(args.protocol)  # a path or a shipped name, checked once
    emit_warnings(protocol)  # odd but legal values, once, up front
    result = dry_run(protocol, args.participants, out, jobs=args.jobs,
                     responder=args.responder, device_url=args.device,
                     progress=stderr_progress(not args.json), durable=args.fsync)
    if args.json:
        print(result.to_json())
    else:
        print(summary_line(result, args.out))
    return 0 if result.finished else 130


def summary_line(result, out: object) -> str:
    """What the dry-run did: sessions already complete are named as such (a rerun of a
    finished dry-run ran nothing; "0.0 min of simulated session time" said so badly)."""
    already = sum(1 for r in result if r.status == "already-complete")
    if already == len(result):
        return (f"dry-run: {len(result)} participants, {result.trials} trials in {out}, all "
                "already complete: nothing to run")
    ran = sum(r.trials_run for r in result)
    done = f"; {already} already complete" if already else ""
    return (f"dry-run: {len(result)} participants, {result.trials} trials in {out}: {ran} "
            f"trials run now ({result.session_seconds / 60:.1f} min of simulated session "
            f"time){done}")
