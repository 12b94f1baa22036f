"""``device boards`` (virtual boards on pseudo-terminals) and ``device identify`` (which board
is behind which port, confirmed by a person and remembered), and the line of ``device check``
that says how the boards were told apart.

``crs-study device boards`` starts the device file's boards as virtual LSC-24 boards on ptys,
prints their ports, the device URL and a tap per board, then shows what they receive, decoded,
until Ctrl-C: every device step of the README then runs on a laptop against that URL, and
``device monitor --port TAP`` decodes a board's line as a tap on real hardware would.

``crs-study device identify`` wiggles the first servo of each board in turn, on the port the
URL gives it, and asks the experimenter whether the board labelled with that name is the one
moving (y/n). Confirmed, the ports' identities (USB serial number, by-id path or socket, where
the hardware has one; see :mod:`crs_study.device.identity`) are remembered, and ``device
check`` compares them with the ports it is given from then on.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time

from crs_study.device import Device
from crs_study.device.identity import BoardRegister, PortIdentity, Verdict, port_identity
from crs_study.device.serial_port import parse_serial_url
from crs_study.device.virtual_boards import Heard, VirtualBoards
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout, load_layout
from crs_study.signals import describe

#: The identify wiggle: a swing of this fraction of the servo's travel, every this many s.
WIGGLE_FRACTION, WIGGLE_PERIOD_S = 0.5, 0.4
BOARDS_MAX_S = 7 * 86400.0


def add_actions(add, actions) -> None:
    """The ``boards`` and ``identify`` actions (``add`` makes an action's parser)."""
    boards = add("boards", "start the device file's boards as virtual boards on "
                 "pseudo-terminals (rehearse without hardware); Ctrl-C stops", device=False)
    boards.add_argument("--layout", default="crs2d", metavar="NAME|FILE",
                        help="device file: crs2d, crs1d or a path")
    boards.add_argument("--baud", type=int, default=9600, help="each board's wire (bits/s)")
    boards.add_argument("--seconds", type=float, default=None,
                        help="stop after this long (default: until Ctrl-C)")
    boards.add_argument("--quiet", action="store_true",
                        help="do not show the frames the boards receive")
    identify = add("identify", "wiggle each board's first servo; the experimenter confirms "
                   "which board moved; the boards' identities are remembered")
    for sub in (identify, actions.choices["check"]):
        sub.add_argument("--boards", default=None, metavar="FILE",
                         help="the register of confirmed boards (default: $CRS_STUDY_BOARDS "
                              "or ~/.crs-study/boards.json)")


def identities(url: str, layout: Layout) -> dict[str, PortIdentity]:
    """The identity of each controller's port of a ``serial://`` URL, in device-file order."""
    ports = parse_serial_url(url)
    names = [c.name for c in layout.controllers]
    if len(ports) != len(names):
        raise DeviceError(f"--device {url}: {len(ports)} port(s) for the {len(names)} "
                          f"controllers ({', '.join(names)}) of {layout.name}")
    return {name: port_identity(port) for name, port in zip(names, ports, strict=True)}


def told_apart(url: str, layout: Layout, register: str | None) -> Verdict:
    """How ``device check`` tells the boards apart (a swap is ``ok`` False)."""
    if url.startswith("sim://"):
        return Verdict(True, "simulated (sim://): the device file's boards by construction")
    if not url.startswith("serial://"):
        return Verdict(True, "unknown device URL")
    return BoardRegister(register).check(layout.name, identities(url, layout))


def boards(args: argparse.Namespace) -> int:
    if not 300 <= args.baud <= 10_000_000:
        raise DeviceError(f"--baud: expected 300..10000000 (the LSC boards use 9600), got "
                          f"{args.baud!r}")
    if args.seconds is not None and not (math.isfinite(args.seconds)
                                         and 0 < args.seconds <= BOARDS_MAX_S):
        raise DeviceError(f"--seconds: expected a time in (0, {BOARDS_MAX_S:g}] s (leave it "
                          f"out to run until Ctrl-C), got {args.seconds!r}")
    layout = load_layout(args.layout)
    start = time.monotonic()
    counts: dict[str, int] = {c.name: 0 for c in layout.controllers}
    with VirtualBoards(layout, baud=args.baud) as virtual:
        print(f"virtual boards of {layout.name} on pseudo-terminals, {args.baud} baud "
              "(no USB identity: told apart by path only):")
        for c, port, tap in zip(layout.controllers, virtual.ports, virtual.taps, strict=True):
            print(f"  {c.name}: {port}   tap: {tap}")
        print(f"device URL: {virtual.url}")
        print(f"  e.g. crs-study device check --device {virtual.url}")
        print(f"       crs-study device monitor --port {virtual.taps[0]}   (what "
              f"{layout.controllers[0].name} receives)")
        print("running until Ctrl-C" + (f" or {args.seconds:g} s" if args.seconds else "")
              + ("" if args.quiet else "; what the boards receive:"), flush=True)
        try:
            while args.seconds is None or time.monotonic() - start < args.seconds:
                for event in virtual.heard(timeout=0.1):
                    counts[event.board] += event.message is not None
                    if not args.quiet:
                        print(_heard_line(event, start), flush=True)
        except KeyboardInterrupt as interrupt:
            print(f"stopped ({describe(interrupt)})")
        bad = {p.board.name: p.board.bad_frames for p in virtual.ptys}
    print("received: " + ", ".join(f"{name} {n} frame(s) ({bad[name]} bad)"
                                   for name, n in counts.items()))
    return 0


def _heard_line(event: Heard, start: float) -> str:
    what = (describe_message(event.message) if event.message is not None
            else f"skipped {event.skipped} byte(s)")
    return f"{event.time - start:9.3f} s  {event.board}  {what}"


def identify(args: argparse.Namespace, device: Device) -> int:
    layout = device.layout
    if args.device.startswith("sim://"):
        print("sim://: simulated boards are the device file's by construction; nothing to "
              "identify")
        return 0
    ports = identities(args.device, layout)
    for c in layout.controllers:
        first = min((a for a in layout.actuators if a.controller == c.name),
                    key=lambda a: a.channel, default=None)
        if first is None:
            continue
        print(f"board {c.name} (port {ports[c.name].port}): its first servo, channel "
              f"{c.name}:{first.channel} ({first.name}), is wiggling now", flush=True)
        answer = _ask_while_wiggling(device, first.index, first.calibration.travel_mm,
                                     f"Is the board labelled {c.name} the one moving? [y/n] ")
        if answer != "y":
            others = [p.port for n, p in ports.items() if n != c.name]
            hint = (f"; if the other board moved, the ports are swapped: try --device "
                    f"serial://{','.join(reversed(list(p.port for p in ports.values())))}"
                    if len(ports) == 2 else f" (other ports: {', '.join(others)})")
            raise DeviceError(f"board {c.name} not confirmed on port {ports[c.name].port}"
                              f"{hint}; nothing was remembered")
    register = BoardRegister(args.boards)
    register.remember(layout.name, ports)
    print(f"confirmed: {', '.join(f'{n} on {p.port}' for n, p in ports.items())}; remembered "
          f"in {register.path}")
    for name, identity in ports.items():
        print(f"  {name}: {identity.describe()}")
    if any(p.key is None for p in ports.values()):
        print("  (these ports carry no hardware identity: device check cannot notice a swap "
              "by itself; run identify again after replugging)")
    return 0


def _ask_while_wiggling(device: Device, index: int, travel_mm: float, question: str) -> str:
    """Swing one actuator between 0 and half its travel until the experimenter answers."""
    stop = threading.Event()
    failed: list[BaseException] = []

    def wiggle() -> None:
        up = True
        while not stop.is_set():
            setpoints = device.layout.neutral_setpoints()
            setpoints[index] = WIGGLE_FRACTION * travel_mm if up else 0.0
            try:
                device.send(setpoints, move_ms=int(WIGGLE_PERIOD_S * 900))
            except DeviceError as error:
                failed.append(error)
                return
            up = not up
            stop.wait(WIGGLE_PERIOD_S)

    thread = threading.Thread(target=wiggle, name="identify-wiggle", daemon=True)
    thread.start()
    try:
        while True:
            try:
                answer = input(question).strip().lower()
            except EOFError:
                raise DeviceError("identify: input ended before the boards were confirmed; "
                                  "nothing was remembered") from None
            if answer in ("y", "yes", "n", "no"):
                return answer[0]
            print("  answer y or n", file=sys.stderr)
    finally:
        stop.set()
        thread.join(timeout=2.0)
        if failed:
            raise failed[0]
        device.send(device.layout.neutral_setpoints())


def describe_message(message) -> str:
    """One decoded LSC message in words (``device monitor`` and ``device boards``)."""
    name = type(message).__name__
    if hasattr(message, "positions"):
        servos = " ".join(f"{i}:{p}" for i, p in message.positions)
        extra = f" in {message.time_ms} ms" if hasattr(message, "time_ms") else ""
        return f"{name} [{len(message.positions)}]{extra}: {servos}"
    fields = {k: v for k, v in vars(message).items()}
    return name + (" " + " ".join(f"{k}={v}" for k, v in fields.items()) if fields else "")
