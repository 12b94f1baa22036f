"""Analyse stored datasets: accuracy with Wilson intervals, the GLMM of correct ~ condition,
secondary tests, confusions and information transfer, speed against accuracy, psychometric
functions when a level varies. Writes results.json, a report and PNG charts; prints the
headline. The analysis plan is --plan, else the one the protocol declares, else
analysis/digit_identification.toml. See analysis/README.md.

--check RESULTS reanalyses and compares with an earlier results.json instead of writing:
"the same numbers" (exit 0) or every value that differs (exit 1).

When the protocol was locked before its first participant (crs-study lock), the plan is
checked against the lock the sessions recorded (or --lock FILE, a published lock): the output
says "plan locked on DATE, unchanged" or lists every deviation, which are also warnings.

On a terminal the step under way is shown on one line, updated in place (the bootstrap's
units of work counted, the seconds it has run), and cleared at the end; then the headline,
then the warnings grouped by what they concern, then where the files are.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time

from crs_study._files import check_writable, os_errors
from crs_study.analysis import analyze
from crs_study.analysis.reproduce import DEFAULT_RTOL, check_tolerance, read_results
from crs_study.dataset import dataset_dir
from crs_study.errors import AnalysisError
from crs_study.power_analysis.backends import open_backend


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # "%(default).0s" prints nothing: it stops argparse appending "(default: None)".
    parser.add_argument("datasets", nargs="+", metavar="DATASET",
                        help="dataset directory (BIDS); several are analysed together")
    parser.add_argument("--plan", metavar="FILE", default=None,
                        help="analysis plan (default: the protocol's analysis_plan, else "
                             "analysis/digit_identification.toml)%(default).0s")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="output directory (default: DATASET/derivatives/crs-study)"
                             "%(default).0s")
    parser.add_argument("--lock", metavar="FILE", default=None,
                        help="check the plan against this plan lock (default: the lock the "
                             "sessions recorded; crs-study lock writes one)")
    parser.add_argument("--check", metavar="RESULTS", default=None,
                        help="compare with an earlier results.json instead of writing: exit 0 "
                             "when every number agrees, 1 when one differs%(default).0s")
    parser.add_argument("--check-rtol", metavar="R", type=float, default=DEFAULT_RTOL,
                        help="--check: relative tolerance of a number (default %(default)g)")
    parser.add_argument("--json", action="store_true",
                        help="print results.json on stdout instead of the headline")
    parser.add_argument("--jobs", metavar="N", type=int, default=os.cpu_count() or 1,
                        help="worker processes for the primary test's parametric bootstrap "
                             "(default: every core, %(default)s here; 1: this process)")
    parser.add_argument("--strict", action="store_true",
                        help="a failed checksum or metadata check is an error, not a warning (an "
                             "interrupted session is analysed as it stands either way)")
    sources = parser.add_argument_group(
        "simulated and human sessions",
        "a dataset holding both is refused unless one of these says what to analyse")
    sources.add_argument("--include-simulated", action="store_true",
                         help="pool simulated sessions (observer/random responder or a sim:// "
                              "device) with human ones")
    sources.add_argument("--responder", action="append", metavar="NAME", default=None,
                         help="analyse only sessions of this responder (keypad, scripted, "
                              "observer, random); repeatable%(default).0s")


class StepProgress:
    """The step under way, on one line of a terminal, redrawn in place each second
    (``analyze: primary test, bootstrap 3/20 units, 14 s``) and cleared by :meth:`close`;
    nothing off a terminal (logs keep the output alone)."""

    def __init__(self, stream=None, enabled: bool = True):
        self.stream = stream or sys.stderr
        self.enabled = enabled and self.stream.isatty()
        self.step, self.detail, self.started = "", "", time.monotonic()
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        if self.enabled:
            threading.Thread(target=self._tick, daemon=True).start()

    def __call__(self, step: str) -> None:
        with self.lock:
            self.step, self.detail = step, ""
        self._draw()

    def units(self, done: int, total: int, seconds: float) -> None:
        """A bootstrap's progress (``backend.map``'s callback)."""
        with self.lock:
            self.detail = f"bootstrap {done}/{total} units"
        self._draw()

    def _tick(self) -> None:
        while not self.stopped.wait(1.0):
            self._draw()

    def _draw(self) -> None:
        if not self.enabled:
            return
        with self.lock:
            what = ", ".join(t for t in (self.step, self.detail) if t)
            seconds = time.monotonic() - self.started
            self.stream.write(f"\ranalyze: {what}, {seconds:.0f} s\x1b[K")
            self.stream.flush()

    def close(self) -> None:
        self.stopped.set()
        if self.enabled:
            with self.lock:
                self.stream.write("\r\x1b[K")
                self.stream.flush()


def print_warnings(analysis, command: str = "analyze") -> None:
    """The warnings after the headline, grouped by what they concern, one line each."""
    for group, warnings in analysis.warning_groups().items():
        for warning in warnings:
            loud = "TAMPERED" in warning or "tampering" in warning
            print(f"crs-study {command}: {'WARNING' if loud else 'warning'}: [{group}] "
                  f"{warning}", file=sys.stderr)


@os_errors(AnalysisError)  # disk full, permission denied, a file where a folder should be: one line
def run(args: argparse.Namespace) -> int:
    if args.out is not None:
        dataset_dir(args.out)  # --out '' is a one-line error, not the current folder
        if args.check is None:
            check_writable(args.out, AnalysisError)   # before the work, not after it
    if args.check is not None:
        if args.out is not None:
            raise AnalysisError("--check writes nothing: leave out --out")
        check_tolerance(args.check_rtol)
        earlier = read_results(args.check)  # before the work: a wrong path fails at once
    progress = StepProgress(enabled=not args.json)
    try:
        with open_backend(args.jobs) as backend:   # a bad --jobs is a one-line error
            result = analyze(args.datasets, args.plan, args.out, strict=args.strict,
                             include_simulated=args.include_simulated,
                             responders=args.responder, write=args.check is None,
                             map_tasks=lambda f, tasks: backend.map(f, tasks, progress.units),
                             progress=progress, lock=args.lock)
    finally:
        progress.close()
    if args.check is not None:
        print_warnings(result)
        verdict = result.compare(earlier, args.check_rtol)
        print(json.dumps(verdict.to_dict()) if args.json else verdict.describe())
        return 0 if verdict.same else 1
    if args.json:
        print_warnings(result)
        print(result.to_json(), end="")  # results.json as written
        return 0
    print(result.headline)      # the answer first, then what to know about it
    print(result.plan_lock.sentence(), flush=True)
    print_warnings(result)
    sys.stderr.flush()
    print(f"report:  {result.report_path}")
    print(f"results: {result.results_path}")
    return 0
