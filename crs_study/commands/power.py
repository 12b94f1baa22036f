"""How many participants a protocol needs: the analysis plan's primary test (the GLMM's
likelihood-ratio test, exactly as analyze runs it) applied to many simulated studies of the
protocol's design. The effect comes from the simulated observer's predicted accuracy of every
stimulus on the simulated device (default), from a pilot dataset's GLMM fit (--pilot), or
from real dry-runs (--fidelity full, slow: for checking a few points). Prints one line
("80 % power at N = ..."), writes power.json and power.png. Runs on all local cores, or on a
Dask cluster with --scheduler tcp://HOST:8786; the answer for a --seed is the same on any.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from crs_study._files import check_writable
from crs_study.errors import CrsStudyError
from crs_study.power_analysis import PowerError, power
from crs_study.power_analysis.api import check_options
from crs_study.power_analysis.backends import check_address


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Numbers are read as text and checked by the library, so a bad value is one line
    # naming the option (argparse's own message adds a usage block).
    parser.add_argument("protocol", metavar="PROTOCOL",
                        help="protocol file (TOML), or a shipped protocol's name")
    effect = parser.add_argument_group("where the effect comes from")
    effect.add_argument("--pilot", metavar="DATASET", default=None,
                        help="pilot dataset: its GLMM fit generates the studies, extended to "
                             "more participants as simr's extend (default: the simulated "
                             "observer's predicted accuracies)")
    effect.add_argument("--effect-scale", metavar="F", default="1",
                        help="multiply the condition effect (pilot effects are optimistic: "
                             "e.g. 0.8)")
    effect.add_argument("--participant-sd", metavar="SD", default=None,
                        help="between-participant SD on the logit scale (default: the "
                             "observer's calibration, or the pilot's estimate)")
    effect.add_argument("--participant-slope-sd", metavar="SD", default=None,
                        help="how much participants differ in the condition effect: the SD "
                             "of its random slope on the logit scale (default: the "
                             "observer's calibration, or the pilot's estimate)")
    effect.add_argument("--fidelity", metavar="model|full", default="model",
                        help="model: trials drawn from the model; full: every study is real "
                             "dry-runs (slow)")
    effect.add_argument("--draws", metavar="N", default=None,
                        help="observer noise draws per stimulus for its predicted accuracy "
                             "(default 200)")
    curve = parser.add_argument_group("the curve")
    curve.add_argument("--participants", metavar="A:B[:STEP]", default="auto",
                       help="participant counts (a range, a number, or a comma list; "
                            "default: chosen from the effect so the curve crosses --target)")
    curve.add_argument("--repetitions", metavar="A:B[:STEP]", default=None,
                       help="repetitions per symbol and condition (default: the "
                            "protocol's)")
    curve.add_argument("--studies", metavar="N", default="1000",
                       help="simulated studies per point")
    curve.add_argument("--target", metavar="POWER", default="0.8", help="power sought")
    curve.add_argument("--seed", metavar="N", default="20260116",
                       help="seed of the run (the same answer on any backend)")
    curve.add_argument("--plan", metavar="FILE", default=None,
                       help="analysis plan (default: the protocol's, as analyze picks it)"
                            "%(default).0s")
    where = parser.add_argument_group("where it runs")
    where.add_argument("--jobs", metavar="J", default=str(os.cpu_count() or 1),
                       help="local worker processes (default: every core)")
    where.add_argument("--scheduler", metavar="tcp://HOST:8786", default=None,
                       help="run on a Dask distributed cluster instead (workers need "
                            "crs-study installed)")
    output = parser.add_argument_group("output")
    output.add_argument("--out", metavar="DIR", default=None,
                        help="where power.json and power.png go (default: "
                             "power_<protocol name> in the current folder, numbered -2, -3, "
                             "... when an earlier run is there); a folder holding an earlier "
                             "run's power.json is refused")
    output.add_argument("--json", action="store_true",
                        help="print power.json on stdout instead of the line; no progress")


def _number(text: str | None, option: str, kind: type, minimum: float | None = None):

    if text is None:
        return None
    try:
        value = kind(text)
    except ValueError:
        what = "a whole number" if kind is int else "a number"
        raise PowerError(f"{option}: expected {what}, got {text!r}") from None
    if minimum is not None and value < minimum:
        raise PowerError(f"{option}: expected at least {minimum:g}, got {text!r}")
    return value


class ProgressBar:
    """``[#####.....]  45 %  450/1000 studies, 12 s left`` on stderr, updated in place on a
    terminal (a line per tenth elsewhere)."""

    def __init__(self, what: str, stream=None):
        self.what = what
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.shown = -1

    def __call__(self, done: int, total: int, seconds: float) -> None:
        fraction = done / total if total else 1.0
        tenth = int(10 * fraction)
        if not self.tty and tenth == self.shown and done < total:
            return
        self.shown = tenth
        left = seconds / done * (total - done) if done else float("nan")
        bar = "#" * int(30 * fraction) + "." * (30 - int(30 * fraction))
        text = (f"[{bar}] {100 * fraction:3.0f} %  {done}/{total} {self.what}, "
                + (f"{left:.0f} s left" if done < total else f"{seconds:.0f} s"))
        self.stream.write(("\r" + text + "\x1b[K") if self.tty else text + "\n")
        if self.tty and done >= total:
            self.stream.write("\n")
        self.stream.flush()


def fresh_folder(base: Path) -> Path:
    """``base``, or ``base-2``, ``base-3``, ... : the first that holds no earlier run."""
    candidate, number = base, 2
    while candidate.exists():
        candidate = base.with_name(f"{base.name}-{number}")
        number += 1
    return candidate


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:

    options = {
        "effect_scale": _number(args.effect_scale, "--effect-scale", float, 0),
        "participant_sd": _number(args.participant_sd, "--participant-sd", float, 0),
        "participant_slope_sd": _number(args.participant_slope_sd, "--participant-slope-sd",
                                        float, 0),
        "studies": _number(args.studies, "--studies", int, 2),
        "target": _number(args.target, "--target", float),
        "seed": _number(args.seed, "--seed", int, 0),
        "jobs": _number(args.jobs, "--jobs", int, 1),
        "draws": _number(args.draws, "--draws", int, 2),
    }
    check_options(args.participants, args.repetitions, options["studies"], options["seed"],
                  options["target"], args.fidelity, options["jobs"], options["effect_scale"],
                  options["participant_sd"], options["participant_slope_sd"], options["draws"])
    out = Path(args.out) if args.out else fresh_folder(Path(f"power_{Path(args.protocol).stem}"))
    if out.exists() and not out.is_dir():
        raise PowerError(f"--out: {out} is a file, not a folder")
    if (out / "power.json").exists():
        raise PowerError(f"--out: {out} holds an earlier run's power.json; choose another "
                         "folder (or leave out --out for a new numbered one)")
    if args.pilot is not None and not Path(args.pilot).is_dir():
        raise PowerError(f"--pilot: {args.pilot} is not a dataset folder")
    if args.scheduler is not None:
        check_address(args.scheduler)
    check_writable(out, PowerError)  # before the curve is computed, not after
    progress = None if args.json else ProgressBar("studies")
    started = time.perf_counter()
    try:
        result = power(args.protocol, pilot=args.pilot, participants=args.participants,
                       repetitions=args.repetitions, fidelity=args.fidelity, plan=args.plan,
                       scheduler=args.scheduler, progress=progress,
                       notify=None if args.json else _say, **options)
    except CrsStudyError:
        raise
    json_path, png_path = result.save(out)
    if args.json:
        print(result.to_json(), end="")
        return 0
    print(result.headline())
    print(f"results: {json_path}")
    print(f"chart:   {png_path}")
    print(f"({time.perf_counter() - started:.0f} s on {result.backend})", file=sys.stderr)
    return 0
