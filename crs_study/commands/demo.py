"""The main job on embedded defaults: rehearse the default protocol and analyse it.

Dry-runs the shipped digit_identification protocol with simulated participants (perceptual
observers) on the simulated device and a virtual clock, analyses the dataset, and prints the
headline (accuracy per condition with confidence intervals, the test, the chart) and where the
dataset, the report and every chart were written. A new output directory is made every time
(``~/crs-study-demo/demo-<time>``: a folder of its own under the home folder, never inside a
source checkout, where ``git clean`` would delete it); nothing is overwritten.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import datetime
from pathlib import Path

from crs_study._files import os_errors
from crs_study.analysis import analyze
from crs_study.commands.analyze import StepProgress, print_warnings
from crs_study.commands.run import stderr_progress
from crs_study.errors import DatasetError, SessionError
from crs_study.paths import DEFAULT_PROTOCOL
from crs_study.power_analysis.backends import open_backend
from crs_study.protocol import emit_warnings, load_protocol
from crs_study.session import dry_run

#: Twenty simulated participants: the shipped plan's own rule then takes the chi2 LR p of the
#: maximal model (the parametric bootstrap is its rule below twenty, where chi2 is liberal),
#: the p lme4 gives for the same fits, in seconds; at twelve the demo's effect drew all
#: 1000 bootstrap replicates, minutes on a laptop.
DEMO_PARTICIPANTS = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="dataset directory (default: ~/crs-study-demo/demo-<time>, "
                        "outside any source checkout); must not exist yet")
    parser.add_argument("--participants", type=int, default=DEMO_PARTICIPANTS, metavar="N",
                        help="simulated participants")
    parser.add_argument("--protocol", default=DEFAULT_PROTOCOL, metavar="PROTOCOL",
                        help="protocol file, or a shipped protocol's name")
    parser.add_argument("--responder", default="observer", metavar="observer|random",
                        help="simulated participant")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), metavar="J",
                        help="worker processes (the dry-run's sessions and the primary test's "
                             "bootstrap)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON summary on stdout and no progress")


#: Where the demo writes by default: a named folder under the home folder (a checkout's
#: ``git clean -fdx`` deletes every untracked file inside it, a dataset among them).
DEMO_FOLDER = "crs-study-demo"


def fresh_directory(base: Path | None = None) -> Path:
    """``~/crs-study-demo/demo-<time>``, with a suffix if that exists already."""
    base = base or Path.home() / DEMO_FOLDER
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    candidate = base / f"demo-{stamp}"
    number = 2
    while candidate.exists():
        candidate = base / f"demo-{stamp}-{number}"
        number += 1
    return candidate


@os_errors(DatasetError)  # disk full, permission denied, a file where a folder should be: one line
def run(args: argparse.Namespace) -> int:
    out = args.out or fresh_directory()
    if args.out is None and not args.json:
        print(f"demo: writing to {os.fspath(out)} (a folder of its own, outside any source "
              "checkout, where git clean would delete it; --out DIR chooses another)",
              file=sys.stderr)
    if out.exists() and any(out.iterdir()):
        raise SessionError(f"--out {os.fspath(out)!r} exists and is not empty; the demo never "
                           "overwrites: choose a new directory")
    protocol = load_protocol(args.protocol)  # a path or a shipped name, checked once
    emit_warnings(protocol)  # odd but legal values of a --protocol given
    rehearsal = dry_run(protocol, args.participants, out, jobs=args.jobs,
                        responder=args.responder, progress=stderr_progress(not args.json))
    with open_backend(args.jobs) as backend:   # the bootstrap's replicates on every job
        progress = StepProgress(enabled=not args.json)
        try:   # the report in the derivatives
            analysis = analyze(out, map_tasks=lambda f, tasks: backend.map(
                f, tasks, progress.units), progress=progress)
        finally:
            progress.close()
    summary: dict = {"dataset": os.fspath(out), "participants": len(rehearsal),
                     "trials": rehearsal.trials, "headline": analysis.headline,
                     "report": os.fspath(analysis.report_path),
                     "results": os.fspath(analysis.results_path)}
    charts = {p.stem: os.fspath(p) for p in analysis.charts}
    if charts:
        summary["charts"] = charts
    if args.json:
        print(json.dumps(summary))
        return 0
    print(f"demo: {summary['participants']} simulated participants, {summary['trials']} trials, "
          f"dataset in {summary['dataset']}")
    print(summary["headline"], flush=True)
    print_warnings(analysis, "demo")
    sys.stderr.flush()
    print(f"report: {summary['report']}")
    print(f"results: {summary['results']}")
    for name, path in charts.items():     # every chart written, in the report's order
        print(f"chart ({name.replace('_', ' ')}): {path}")
    return 0
