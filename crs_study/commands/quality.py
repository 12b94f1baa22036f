"""Display quality: D_P and D_S against d/l for every display model and lattice.

Computes the paper's peak position distortion D_P and shape distortion D_S (Wang, Meng and
Chen, "Continuity Reinforcement Skeleton for Pixel-based Haptic Display", Eqs. 1, 2, 5, 6) on
periodic 1D, square and hexagonal patches at the shipped devices' pitch, writes a chart
(quality.png) with the paper's theory lines overlaid and a table (quality.csv, quality.md) to
--out, and prints a summary; with --json it prints one row per line: {"layout", "model",
"d_over_l", "D_P", "D_S"}. Points are cached on disk (keyed by the source of the models), so a
repeated run is quick; points that cannot be computed (a model without that lattice, a
collapsing beam) are listed with the reason.

``--speed-accuracy`` answers the other question, which model to use: each display model's
median time per surface against its error versus the FE reference on CRS bumps (crs1d,
crs2d), as a table and a chart (speed_accuracy.png, speed_accuracy.md in --out); which model
to use for what is in :mod:`crs_study.benchmarks.display`.

The device as measured: ``crs-study quality measure PROTOCOL --out MEAS`` shows a measurement
protocol's target waveforms for DIC captures, and ``crs-study quality analyze MEAS`` compares
the captures' D_P and D_S with the model's (``crs-study quality measure --help``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from crs_study._files import check_writable, os_errors, sha256_bytes
from crs_study.benchmarks.display import (
    format_table,
    plot_speed_accuracy,
    speed_accuracy_rows,
)
from crs_study.commands import _quality_measure
from crs_study.display import MODELS
from crs_study.errors import CrsStudyError, DisplayModelError
from crs_study.geometry.layout import device_file_path, load_layout
from crs_study.quality.criteria import MAX_D_OVER_L, MIN_D_OVER_L
from crs_study.quality.lattices import lattice_of
from crs_study.quality.report import failure_lines, plot_quality, summary_lines, to_csv, to_markdown
from crs_study.quality.sweep import (
    DEFAULT_D_OVER_L,
    DEFAULT_MODELS,
    Settings,
    default_cache_dir,
    sweep,
)

#: Upper bounds of the numerical options: beyond them the cost (memory ~ resolution^2 per
#: surface in 2D) outgrows any gain in accuracy (resolution 100000 was killed out of memory).
MAX_ORDER, MAX_RESOLUTION, MAX_JOBS = 32, 96, 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Defaults are resolved in run(): importing the quality package here would load scipy
    # for every crs-study command.
    parser.add_argument("--json", action="store_true",
                        help="print one JSON row per point instead of the summary")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for quality.png, quality.csv, quality.md "
                             "(default ./quality; with --json none unless given)")
    parser.add_argument("--models", nargs="+", default=None, metavar="MODEL",
                        help="display models to evaluate (default: nearest linear spline beam)")
    parser.add_argument("--layouts", nargs="+", default=None,
                        choices=["1d", "square", "hex"],
                        help="lattices (default: 1d square hex; with --device, its own)")
    parser.add_argument("--device", default=None, metavar="NAME|FILE",
                        help="device file whose pitch, beam section, clamp margin and skin the "
                             "periodic patches take (default: the shipped crs1d for 1d, crs2d "
                             "for square and hex)")
    parser.add_argument("--d-over-l", nargs="+", type=float, default=None, metavar="X",
                        help="pixel pitch over bump diameter "
                             "(default: 0.1 0.15 0.2 0.25 0.3 1/3 0.4 0.5)")
    parser.add_argument("--speed-accuracy", action="store_true",
                        help="instead of D_P/D_S: time each display model's surface against its "
                             "error versus the FE reference (crs1d, crs2d; CRS bumps) and write "
                             "speed_accuracy.png and speed_accuracy.md to --out (default "
                             "./quality); with --json print the rows. The same rows are the "
                             "figures of `crs-study bench display`")
    group = parser.add_argument_group("numerics")
    group.add_argument("--order", type=int, default=4,
                       help=f"Gauss order per panel of the peak-position cell "
                            f"(2..{MAX_ORDER})")
    group.add_argument("--resolution", type=int, default=12,
                       help=f"quadrature nodes per pitch for the shape integral "
                            f"(4..{MAX_RESOLUTION})")
    group.add_argument("--jobs", type=int, default=None,
                       help=f"worker processes, 1..{MAX_JOBS} (default: the CPUs, at most 4)")
    group.add_argument("--cache-dir", type=Path, default=None,
                       help="cache folder (default $XDG_CACHE_HOME/crs-study/quality)")
    group.add_argument("--no-cache", action="store_true", help="recompute every point")
    actions = parser.add_subparsers(dest="action", metavar="ACTION")
    _quality_measure.add_actions(actions)


@os_errors(CrsStudyError)  # an unwritable --out or --cache-dir: one line, not a traceback
def run(args: argparse.Namespace) -> int:
    if getattr(args, "action", None):  # measure, analyze: the device as measured
        return _quality_measure.run(args)
    args.models = args.models or list(DEFAULT_MODELS)
    args.d_over_l = args.d_over_l or list(DEFAULT_D_OVER_L)
    if args.speed_accuracy:
        return _speed_accuracy(args)
    device = _device_settings(args)
    unknown = [m for m in args.models if m not in MODELS]
    if unknown:
        raise DisplayModelError(f"--models: unknown display model {unknown[0]!r}; "
                                f"known: {', '.join(sorted(MODELS))}")
    upper = max(MAX_D_OVER_L[lat] for lat in args.layouts)
    bad = [x for x in args.d_over_l if not MIN_D_OVER_L <= x <= upper]
    if bad:
        raise DisplayModelError(f"--d-over-l: expected values in [{MIN_D_OVER_L}, {upper:.4f}], "
                                f"got {bad[0]!r}")
    for option, value, low, high in (("--order", args.order, 2, MAX_ORDER),
                                     ("--resolution", args.resolution, 4, MAX_RESOLUTION),
                                     ("--jobs", args.jobs, 1, MAX_JOBS)):
        if value is not None and not low <= value <= high:
            raise DisplayModelError(f"{option}: expected a whole number in {low}..{high}, "
                                    f"got {value!r}")
    cache = None if args.no_cache else (args.cache_dir or default_cache_dir())
    jobs = args.jobs or min(4, os.cpu_count() or 1)
    out = args.out if args.out is not None else (None if args.json else Path("quality"))
    if out is not None:   # before the sweep's minutes, not after them
        check_writable(out, DisplayModelError)
    # points beyond a lattice's own covering limit are reported, not computed
    points = sweep(args.models, args.layouts, args.d_over_l,
                   Settings(order=args.order, resolution=args.resolution, **device),
                   cache_dir=cache, jobs=jobs)

    written = _write(points, out) if out is not None else []
    if args.json:
        for p in points:
            if p.D_P is not None:
                print(json.dumps(p.row()))
        for line in failure_lines(points):
            print(f"quality: {line}", file=sys.stderr)
        return 0
    print("\n".join(summary_lines(points)))
    for path in written:
        print(f"wrote {path}")
    return 0


def _device_settings(args: argparse.Namespace) -> dict:
    """``--device``: its lattice is the only one computed; the file's sha256 keys the cache."""
    if args.device is None:
        args.layouts = args.layouts or ["1d", "square", "hex"]
        return {}
    layout = load_layout(args.device)  # a malformed file: one line naming key and value
    own = lattice_of(layout)
    if args.layouts not in (None, [own]):
        raise DisplayModelError(f"--layouts {' '.join(args.layouts)}: the device "
                                f"{layout.name!r} is a {own} lattice; drop --layouts or give "
                                f"--layouts {own}")
    args.layouts = [own]
    path = device_file_path(args.device)
    return {"device": str(path.resolve()), "device_sha256": sha256_bytes(path.read_bytes())}


def _write(points: list, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    chart = out / "quality.png"
    axes = plot_quality(points)
    axes.flat[0].figure.savefig(chart, dpi=120)
    csv_path, md_path = out / "quality.csv", out / "quality.md"
    csv_path.write_text(to_csv(points), encoding="utf-8")
    md_path.write_text(to_markdown(points), encoding="utf-8")
    return [chart, csv_path, md_path]


def _speed_accuracy(args: argparse.Namespace) -> int:
    """Time per surface against error versus the reference, chart and table."""
    out = args.out if args.out is not None else (None if args.json else Path("quality"))
    if out is not None:
        check_writable(out, DisplayModelError)
    rows = speed_accuracy_rows(quick=True)
    written = []
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        ax = plot_speed_accuracy(rows)
        chart = out / "speed_accuracy.png"
        ax.figure.savefig(chart, dpi=120, bbox_inches="tight")
        table = out / "speed_accuracy.md"
        table.write_text(format_table(rows, markdown=True) + "\n", encoding="utf-8")
        written = [chart, table]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(format_table(rows))
    for path in written:
        print(f"wrote {path}")
    return 0
