"""Measure performance: every figure is a ratio against a baseline measured in the same run.

Areas are the modules of crs_study.benchmarks (render, display, device, runner, analysis, ...).
Timings are medians of repeats; the machine is printed with the figures.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import pkgutil
import platform

import crs_study.benchmarks as benchmarks
from crs_study.errors import ConfigError


def _areas() -> dict[str, object]:
    """Every module of :mod:`crs_study.benchmarks` by its ``AREA`` (a new file is a new area)."""
    modules = [importlib.import_module(f"{benchmarks.__name__}.{m.name}")
               for m in pkgutil.iter_modules(benchmarks.__path__) if not m.name.startswith("_")]
    return {m.AREA: m for m in modules}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("areas", nargs="*", metavar="AREA",
                        help="areas to run (default: all); see --list")
    parser.add_argument("--list", action="store_true", help="list the areas and exit")
    parser.add_argument("--quick", action="store_true", help="fewer repeats (for tests)")
    parser.add_argument("--json", action="store_true", help="print figures as JSON lines")
    parser.add_argument("--trace", action="append", default=[], metavar="FILE",
                        help="live: also measure the position error on this recording "
                             "(crs-study live --record FILE); repeatable")


def run(args: argparse.Namespace) -> int:
    areas = _areas()
    if args.list:
        for name, module in sorted(areas.items()):
            print(f"{name:12s} {module.DESCRIPTION}")
        return 0
    unknown = [a for a in args.areas if a not in areas]
    if unknown:
        raise ConfigError(f"unknown bench area {unknown[0]!r}; known: {', '.join(sorted(areas))}")
    chosen = args.areas or sorted(areas)
    machine = f"{platform.python_implementation()} {platform.python_version()}, " \
              f"{os.cpu_count()} cpus, {platform.machine()}"
    if not args.json:
        print(f"crs-study bench on {machine}")
    failed = 0
    for name in chosen:
        extra = {"traces": args.trace} if args.trace and name == "live" else {}
        for fig in areas[name].run(quick=args.quick, **extra):
            failed += fig.passed is False
            if args.json:
                print(json.dumps(fig.to_dict()), flush=True)
                continue
            verdict = "" if fig.passed is None else ("  ok" if fig.passed else "  MISSED")
            print(f"{fig.area:9s} {fig.name:48s} {fig.value:12.4g} {fig.unit:6s} "
                  f"ratio {fig.ratio:10.4g} vs {fig.baseline_name} ({fig.baseline:.4g})"
                  f"  {fig.target}{verdict}", flush=True)
    return 1 if failed else 0
