"""Drive the display live from finger packets over UDP: the bump of Eq. 7 under the finger.

A VR scene (the paper's Unity scene; a Unity C# sender is in crs_study/live/README.md) or
``crs-study live-send`` sends the fingertip's position relative to the display's centre, one
36-byte packet per headset frame. The newest packet wins: frames go at the rate the wire
allows, each carrying the newest position; stale, malformed and other senders' packets are
counted and dropped; a finger outside the recognition area (the pixels' hull) flattens the
display. Setpoints pass the same renderer limits and calibrated ranges as a session.

No packet for --silence-s: the display goes flat (and with --exit-on-silence the command
ends). Ctrl-C, SIGTERM, SIGHUP, --seconds or --max-packets end it: neutral pose, ports
released, a summary, exit 0. A device fault ends it the same way and exits 2.

On a terminal a live view shows packets received and dropped, the frame rate and latency
percentiles (arrival -> last byte on the wire -> servos in place, timed by the virtual boards
on sim://, by the write policy's model on real boards). --record FILE keeps every packet and
frame as JSON lines; crs-study live-send --replay FILE sends it again.
"""

from __future__ import annotations

import argparse
import atexit
import signal
import sys
import threading

from crs_study.commands import HelpFormatter, add_device_options, device_options
from crs_study.device import open_device
from crs_study.errors import DeviceError
from crs_study.geometry.layout import load_layout
from crs_study.live.predict import PredictConfig
from crs_study.live.session import LiveConfig, LiveSession
from crs_study.live.view import TerminalView, screen
from crs_study.rendering.conditions import CONDITIONS
from crs_study.signals import PAUSE_SIGNALS, handling


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--listen", default="127.0.0.1:5005", metavar="HOST:PORT",
                        help="UDP address to receive finger packets on (0.0.0.0:PORT lets "
                             "any machine on the network move the display)")
    parser.add_argument("--device", required=True, metavar="URL",
                        help="sim://[?options] or serial:///dev/ttyUSB0,/dev/ttyUSB1")
    parser.add_argument("--layout", default="crs2d", metavar="NAME|FILE",
                        help="device file: crs2d, crs1d or a path")
    parser.add_argument("--condition", default="crs", choices=tuple(CONDITIONS),
                        help="how the bump is rendered (a registered display condition)")
    shape = parser.add_argument_group("the bump and the area")
    shape.add_argument("--diameter-mm", type=float, default=90.0,
                       help="bump diameter (Eq. 7; the paper's 90 mm)")
    shape.add_argument("--max-height-mm", type=float, default=None,
                       help="largest bump height (press depth beyond it is capped; default: "
                            "the pixels' travel)")
    shape.add_argument("--area-margin-mm", type=float, default=0.0,
                       help="grow the recognition area (the pixels' hull) by this much")
    timing = parser.add_argument_group("timing and stopping")
    timing.add_argument("--silence-s", type=float, default=0.5,
                        help="flatten the display after this long without a packet")
    timing.add_argument("--exit-on-silence", action="store_true",
                        help="end the session (neutral, ports released) instead of flattening")
    timing.add_argument("--move-ms", type=int, default=0,
                        help="SERVO_MOVE time of each frame (0: as fast as the servos go)")
    timing.add_argument("--predict", default="one-euro", choices=("one-euro", "off"),
                        help="render each frame for where the finger will be when its servos "
                             "are in place (a 1€-filtered constant-velocity prediction, step "
                             "<= 6 mm; the default), or off: the newest packet as it came")
    timing.add_argument("--seconds", type=float, default=None,
                        help="stop after this long (default: until Ctrl-C)")
    timing.add_argument("--max-packets", type=int, default=None,
                        help="stop after this many datagrams")
    add_device_options(parser)
    out = parser.add_argument_group("output")
    out.add_argument("--record", default=None, metavar="FILE",
                     help="write every packet and frame as JSON lines (a new file)")
    out.add_argument("--json", action="store_true", help="print the result as one JSON object")
    out.add_argument("--no-view", action="store_true", help="no live view on a terminal")
    parser.formatter_class = HelpFormatter


def run(args: argparse.Namespace) -> int:
    _ignore_stop_signals_at_exit()
    config = LiveConfig(
        listen=args.listen, condition=args.condition, diameter_mm=args.diameter_mm,
        max_height_mm=args.max_height_mm, area_margin_mm=args.area_margin_mm,
        silence_s=args.silence_s, exit_on_silence=args.exit_on_silence, move_ms=args.move_ms,
        duration_s=args.seconds, max_packets=args.max_packets, record=args.record,
        predict=PredictConfig(method=args.predict))
    layout = load_layout(args.layout)
    options = device_options(args, args.device)
    if args.device.startswith("sim://"):
        options["record"] = True  # the virtual boards' record times the frames
    device = open_device(args.device, layout, **options)
    live_view = sys.stdout.isatty() and not (args.no_view or args.json)
    session = LiveSession(device, config, view=TerminalView() if live_view else _Announce())
    # the session handles stop signals while it runs; before and after, one has nothing to
    # stop (after: the display is neutral, the ports released) and cannot cut the report short
    with handling(lambda signum, frame: None, PAUSE_SIGNALS):
        result = session.run()
        _report(args, session, result, live_view)
    return 0


def _report(args: argparse.Namespace, session: LiveSession, result, live_view: bool) -> None:
    import json

    if args.json:
        print(json.dumps(result.to_json(), indent=1))
    else:
        if not live_view:  # on a terminal the view's last screen is already there
            print("\n".join(screen(session)))
        print(f"stopped: {result.stopped_by}; display neutral, ports released"
              + (f"; recorded to {args.record}" if args.record else ""))
    faults = list(result.faults)
    if not result.ok:  # the first fault is the error; any others are warnings
        first = faults.pop(0) if faults else "device fault"
    for fault in faults:
        print(f"crs-study live: warning: {fault}", file=sys.stderr)
    if not result.ok:
        raise DeviceError(first)


def _ignore_stop_signals_at_exit() -> None:
    """Once the command is over, Ctrl-C, SIGTERM and SIGHUP are ignored until the process ends.

    While the interpreter tears down (a second or so with numpy and scipy loaded) Python puts
    the default actions back, so a second Ctrl-C there killed the process by SIGINT after it
    had stopped cleanly and printed its result. An ignored signal stays ignored through that.
    Registered with :mod:`atexit`, so a caller that runs the command in its own process (a
    notebook, a test) keeps its handlers until it exits itself.
    """
    if threading.current_thread() is threading.main_thread():
        atexit.unregister(_ignore_stop_signals)  # once, however often the command runs
        atexit.register(_ignore_stop_signals)


def _ignore_stop_signals() -> None:
    for signum in PAUSE_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


class _Announce:
    """Where no live view is drawn: one line on stderr once the port is open."""

    def __init__(self) -> None:
        self.done = False

    def __call__(self, session) -> None:
        if not self.done:
            print(f"crs-study live: listening on {session.listen_address}, device "
                  f"{getattr(session.device, 'url', '')} (Ctrl-C stops)", file=sys.stderr,
                  flush=True)
            self.done = True
