"""Send a finger trace to ``crs-study live`` as the VR scene would: demonstrations and tests
without a headset.

One source: --digit D (a finger writing digit D with the package's strokes, lifting between
strokes), --symbol S (symbol S of the stimulus set --set: the letters' strokes, a set file's),
--stroke (a straight stroke from --start to --end), --hold (a finger held still at
--centre for --seconds), or --replay FILE (the accepted packets of a ``crs-study live --record``
file at their recorded times, pauses over 2 s shortened; with --rate one every 1/rate s in
their order). --speed plays any of them faster or slower. --jitter-mm adds a tremor (Gaussian, per
packet, on x and y). Packets go at --rate a second (72: the Quest 2's frame rate), on an
absolute schedule, one new stream per run. Coordinates are mm from the display's centre.
"""

from __future__ import annotations

import argparse

from crs_study.commands import HelpFormatter
from crs_study.live.errors import LiveError
from crs_study.live.link import parse_address
from crs_study.live.record import read_trace
from crs_study.live.sender import send_trace
from crs_study.live.trace import (
    HEADSET_RATE_HZ,
    digit_trace,
    hold_trace,
    stroke_trace,
    symbol_trace,
)
from crs_study.signals import describe, terminate_as_interrupt
from crs_study.stimuli.sets import DEFAULT_SET


def _point(text: str) -> tuple[float, float]:
    import math

    parts = text.split(",")
    try:
        x, y = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in mm, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"expected finite X,Y in mm, got {text!r}")
    return x, y


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = HelpFormatter
    parser.add_argument("--to", default="127.0.0.1:5005", metavar="HOST:PORT",
                        help="where crs-study live listens")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--digit", type=int, metavar="D", help="write digit D (0-9)")
    source.add_argument("--symbol", metavar="S",
                        help="write symbol S of the stimulus set --set (e.g. --symbol S "
                             "--set letters)")
    source.add_argument("--stroke", action="store_true", help="one straight stroke")
    source.add_argument("--hold", action="store_true", help="a finger held still")
    source.add_argument("--replay", metavar="FILE", help="a crs-study live --record file")
    parser.add_argument("--rate", type=float, default=None,
                        help="packets a second (default 72; --replay: the recorded times, or "
                             "the recorded packets at this rate)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="play the trace this many times as fast (--replay --speed 2: "
                             "twice the recorded speed)")
    shape = parser.add_argument_group("the made-up traces")
    shape.add_argument("--set", default=None, metavar="NAME|FILE",
                       help="--symbol: a shipped stimulus set (digits, letters) or a set file")
    shape.add_argument("--speed-mm-s", type=float, default=30.0, help="finger speed")
    shape.add_argument("--height-mm", type=float, default=60.0,
                       help="--digit, --symbol: mean height (the width is 0.6 of it)")
    shape.add_argument("--press-mm", type=float, default=5.0,
                       help="press depth z_f: the bump's height")
    shape.add_argument("--centre", type=_point, default=(0.0, 0.0), metavar="X,Y",
                       help="--digit, --symbol, --hold: where (mm from the display's centre)")
    shape.add_argument("--start", type=_point, default=(-50.0, 0.0), metavar="X,Y",
                       help="--stroke: from")
    shape.add_argument("--end", type=_point, default=(50.0, 0.0), metavar="X,Y",
                       help="--stroke: to")
    shape.add_argument("--seconds", type=float, default=2.0, help="--hold: how long")
    shape.add_argument("--jitter-mm", type=float, default=0.0,
                       help="tremor: Gaussian SD added to x and y of every packet")
    shape.add_argument("--seed", type=int, default=0, help="seed of the tremor")
    parser.add_argument("--repeat", type=int, default=1, help="send the trace this many times")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args: argparse.Namespace) -> int:
    import json


    if args.set is not None and args.symbol is None:
        raise LiveError("--set: names the stimulus set of --symbol; give --symbol too")
    address = parse_address(args.to, "--to")
    rate = HEADSET_RATE_HZ if args.rate is None else args.rate
    if args.replay:
        trace = read_trace(args.replay, args.rate)
    elif args.digit is not None:
        trace = digit_trace(args.digit, args.height_mm, args.speed_mm_s, args.press_mm, rate,
                            args.centre)
    elif args.symbol is not None:
        trace = symbol_trace(args.symbol, args.set or DEFAULT_SET, args.height_mm, args.speed_mm_s,
                             args.press_mm, rate, args.centre)
    elif args.stroke:
        trace = stroke_trace(args.start, args.end, args.speed_mm_s, args.press_mm, rate)
    else:
        trace = hold_trace(args.centre, args.seconds, args.press_mm, rate)
    if args.jitter_mm:
        trace = trace.jittered(args.jitter_mm, args.seed)
    trace = trace.faster(args.speed)
    try:
        with terminate_as_interrupt():
            report = send_trace(trace, address, repeat=args.repeat)
    except KeyboardInterrupt as interrupt:
        print(f"crs-study live-send: stopped ({describe(interrupt)})")
        return 0
    if args.json:
        print(json.dumps({"trace": trace.name, **report.to_json()}))
    else:
        print(f"sent {report.packets} packets of {trace.name} to {args.to} in "
              f"{report.duration_s:.2f} s (stream {report.stream:08x}; {report.late} late, "
              f"latest {report.latest_s * 1e3:.1f} ms behind)")
    return 0
