"""``crs-study quality measure`` and ``crs-study quality analyze``: the device as measured.

``measure PROTOCOL --device URL --out MEAS`` runs (or resumes) a measurement session: the
protocol's target waveforms held on the display one capture window each, a durable manifest
of what was shown when (:func:`crs_study.session.measurement.run_measurement`). With
``--capture synthetic`` (the default on ``sim://``) a DIC stand-in writes the captures, and
the measurement is analysed at once; with ``prompt`` (the default on a real device) the
experimenter takes each DIC capture and presses Enter; with ``timed`` each shape is held
``hold_s``.

``analyze MEAS`` imports the DIC exports (``MEAS/captures/<capture>.csv`` and
``fiducials.csv``), registers them to the display by the pixel fiducials, measures D_P and D_S
as the paper defines them with bootstrap intervals over shapes beside the model's prediction
and the paper's lines, gives a verdict per condition and a per-pixel residual map naming a
mis-calibrated servo (:func:`crs_study.quality.measured_analysis.analyze_measurement`), and
writes report.md, results.json, shapes.csv and figures/ to ``MEAS/derivatives`` (or --out).
``--write-calibration FILE`` writes a copy of the device file with the named servos'
endpoints corrected, for ``crs-study device calibrate --layout FILE`` to start from.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from pathlib import Path

from crs_study.commands import HelpFormatter, add_device_options, device_options
from crs_study.device.calibration import write_calibrated_copy
from crs_study.errors import DeviceFileError, MeasurementError
from crs_study.quality.manifest import DERIVATIVES
from crs_study.quality.measured_analysis import analyze_measurement, load_measurement
from crs_study.quality.measured_report import write_report
from crs_study.quality.measured_result import MeasuredQuality
from crs_study.session.measurement import MeasurementSpec, run_measurement

#: ``crs-study quality``'s actions: name -> one line of help.
ACTIONS = {
    "measure": "show a measurement protocol's waveforms for DIC captures (a durable session)",
    "analyze": "D_P and D_S of a measurement's DIC captures against the model and the paper",
}


def add_actions(actions: argparse._SubParsersAction) -> None:
    measure = actions.add_parser("measure", help=ACTIONS["measure"],
                                 description=ACTIONS["measure"], formatter_class=HelpFormatter)
    measure.add_argument("protocol", metavar="PROTOCOL",
                         help="a measurement protocol file, or a shipped one: crs1d, crs2d")
    measure.add_argument("--device", default="sim://", metavar="URL",
                         help="serial:///dev/ttyUSB0,/dev/ttyUSB1 or sim://")
    measure.add_argument("--out", required=True, type=Path, metavar="MEAS",
                         help="the measurement's folder (run the same command to resume)")
    measure.add_argument("--capture", default=None, metavar="MODE",
                         help="prompt (the experimenter presses Enter after each DIC "
                              "capture), timed (each shape held hold_s) or "
                              "synthetic[?options] (a DIC stand-in, sim:// only; options in "
                              "crs_study/quality/dic_standin.py); default: synthetic on "
                              "sim://, prompt otherwise")
    measure.add_argument("--clock", default="auto", choices=("auto", "real", "virtual"),
                         help="virtual: simulated time (sim://, not prompt)")
    measure.add_argument("--no-analysis", action="store_true",
                         help="do not analyse a complete measurement at once")
    measure.add_argument("--json", action="store_true",
                         help="print one JSON object: the run and, analysed, the results")
    add_device_options(measure)

    analyze = actions.add_parser("analyze", help=ACTIONS["analyze"],
                                 description=ACTIONS["analyze"], formatter_class=HelpFormatter)
    analyze.add_argument("measurement", type=Path, metavar="MEAS",
                         help="a measurement folder (crs-study quality measure --out)")
    analyze.add_argument("--captures", type=Path, default=None, metavar="DIR",
                         help="the DIC exports' folder (default MEAS/captures)")
    analyze.add_argument("--fiducials", type=Path, default=None, metavar="FILE",
                         help="the pixel fiducials (default fiducials.csv among the captures)")
    analyze.add_argument("--units", default="mm",
                         help="length unit of export columns whose header names none")
    analyze.add_argument("--out", type=Path, default=None, metavar="DIR",
                         help="where the report goes (default MEAS/derivatives)")
    analyze.add_argument("--write-calibration", type=Path, default=None, metavar="FILE",
                         help="write a copy of the device file with the named servos' "
                              "endpoints corrected (never the original)")
    analyze.add_argument("--overwrite", action="store_true",
                         help="replace --write-calibration's file if it exists")
    analyze.add_argument("--json", action="store_true",
                         help="print results.json instead of the summary")


def run(args: argparse.Namespace) -> int:
    return _measure(args) if args.action == "measure" else _analyze(args)


def _prompt(message: str) -> None:
    """Say what to do on stderr; wait for Enter (end of input: the experimenter stopped)."""
    print(f"crs-study quality measure: {message}", file=sys.stderr, flush=True)
    if sys.stdin.readline() == "":
        raise KeyboardInterrupt


def _measure(args: argparse.Namespace) -> int:
    capture = args.capture or ("synthetic" if args.device.startswith("sim://") else "prompt")
    spec = MeasurementSpec(args.protocol, args.out, args.device, capture, args.clock)
    progress = None if args.json else (lambda line: print(line, file=sys.stderr))
    outcome = run_measurement(spec, prompt=_prompt, progress=progress,
                              device_options=device_options(args, args.device))
    report = {"measurement": outcome.to_dict()}
    if not args.json:
        print(f"measurement {outcome.status}: {outcome.message}")
    if outcome.status == "interrupted":
        if args.json:
            print(json.dumps(report))
        return 130
    if outcome.missing:
        if not args.json:
            print(f"{len(outcome.missing)} capture(s) have no export yet in "
                  f"{args.out / 'captures'} (first {outcome.missing[0]}): save each DIC "
                  "export as <capture>.csv with fiducials.csv beside them, then run "
                  f"crs-study quality analyze {args.out}")
    elif not args.no_analysis:
        result, files = _analysis(args.out, None, None, "mm", None)
        report["results"] = result.to_dict()
        if not args.json:
            _summary(result, files)
    if args.json:
        print(json.dumps(report))
    return 0


def _analysis(folder: Path, captures: Path | None, fiducials: Path | None, units: str,
              out: Path | None) -> tuple[MeasuredQuality, dict[str, Path]]:
    result = analyze_measurement(folder, captures=captures, fiducials=fiducials, units=units)
    files = write_report(result, out if out is not None else folder / DERIVATIVES)
    return result, files


def _summary(result: MeasuredQuality, files: dict[str, Path]) -> None:
    print(result.headline())
    reg = result.registration
    print(f"registration: {reg.mode}, {len(reg.pixels)} fiducials, {reg.rms_mm:.3f} mm RMS "
          f"(at most {reg.max_mm:.3f} mm, pixel {reg.worst_pixel})")
    for name in ("report", "results", "chart", "residual_map"):
        print(f"{name + ':':14s}{files[name]}")


def _analyze(args: argparse.Namespace) -> int:
    result, files = _analysis(args.measurement, args.captures, args.fiducials, args.units,
                              args.out)
    if args.write_calibration is not None:
        written = _write_calibration(args.measurement, result, args.write_calibration,
                                     args.overwrite)
    if args.json:
        print(result.to_json(), end="")
    else:
        _summary(result, files)
        if args.write_calibration is not None:
            print(written)
    return 0


def _write_calibration(folder: Path, result: MeasuredQuality, destination: Path,
                       overwrite: bool) -> str:
    """A copy of the measured device file with the named servos' endpoints corrected."""
    record, _, layout = load_measurement(folder)
    endpoints = result.residual_map.corrected_endpoints(layout)
    if not endpoints:
        return "no servo named: no calibration written"
    if destination.exists() and not overwrite:
        raise MeasurementError(f"--write-calibration {destination}: already exists; choose "
                               "another file or --overwrite")
    source = destination.with_name(f".{destination.name}.measured.toml")
    try:
        source.write_text(record.device_file_text, encoding="utf-8")
        # the file's own overrides stay: every channel off its most common pair
        pairs = {f"{a.controller}:{a.channel}": (a.calibration.zero_us, a.calibration.full_us)
                 for a in layout.actuators}
        usual = Counter(pairs.values()).most_common(1)[0][0]
        previous = {channel: pair for channel, pair in pairs.items() if pair != usual}
        write_calibrated_copy(source, destination, {**previous, **endpoints},
                              overwrite=overwrite)
    except (OSError, DeviceFileError) as exc:
        raise MeasurementError(f"--write-calibration {destination}: not written ({exc})") \
            from None
    finally:
        if source.exists():
            os.unlink(source)
    changes = ", ".join(f"{k}: zero_us = {v[0]:g}, full_us = {v[1]:g}"
                        for k, v in endpoints.items())
    return (f"wrote {destination}: {changes}; review it with crs-study device calibrate "
            f"--layout {destination} --channel {next(iter(endpoints))}")
