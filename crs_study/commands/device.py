"""Work with the display's controllers: check, identify, neutral pose, sweep, calibrate,
monitor a port; boards starts virtual ones on pseudo-terminals (no hardware needed).

Device URLs: ``serial://PORT[,PORT...]`` (one port per controller, in device-file order; a
PORT is a path like /dev/ttyUSB0 or any pyserial URL such as spy:///dev/ttyUSB0 or loop://)
or ``sim://[?options]`` (the simulated device). --deadband-us and --refresh-s apply to both;
--min-battery-mv, --battery-timeout-s and --no-battery-check to serial:// only (refused with
sim://). A ``lscsim://NAME`` port is a virtual board (a dry run of the serial path).

Ctrl-C, SIGTERM and SIGHUP end every action alike: the actuators go to the neutral pose, the
ports are released, and the command exits 130 (monitor, which is meant to be stopped that
way, reports what it saw and exits 0).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import serial

from crs_study.commands import HelpFormatter, add_device_options, device_options
from crs_study.commands import _device_boards as device_boards
from crs_study.commands._device_boards import describe_message
from crs_study.device import Device, calibration, open_device, serial_port
from crs_study.device.base import full_frame_rate_hz, full_frame_wire_time_s
from crs_study.device.calibration import calibration_table, previous_default_endpoints
from crs_study.device.decoder import FrameDecoder, Skipped
from crs_study.device.schedule import channel_balance
from crs_study.device.serial_device import DeviceWarning
from crs_study.device.serial_port import MAX_BAUD, MIN_BAUD, parse_serial_url
from crs_study.errors import DeviceError, DeviceFileError
from crs_study.geometry.layout import Layout, device_file_path, load_layout
from crs_study.paths import DEFAULT_PROTOCOL, shipped_file
from crs_study.protocol import load_protocol, wire_budget
from crs_study.signals import deferred, describe, terminate_as_interrupt

#: ``sweep`` limits: the LSC move time is 0..30000 ms (LSC protocol), one frame period a frame.
SWEEP_MIN_RATE_HZ = 1 / 30
SWEEP_MAX_RATE_HZ = 100.0
SWEEP_MAX_S = 600.0
#: ``monitor`` limits: --seconds at most a day (none: until Ctrl-C), --max-frames at most 1e9.
MONITOR_MAX_S = 86400.0
MONITOR_MAX_FRAMES = 10**9


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    def add(name: str, help_text: str, device: bool = True) -> argparse.ArgumentParser:
        sub = actions.add_parser(name, help=help_text, description=help_text,
                                 formatter_class=HelpFormatter)
        if device:
            sub.add_argument("--device", required=True, metavar="URL",
                             help="serial:///dev/ttyUSB0,/dev/ttyUSB1 or sim://")
            sub.add_argument("--layout", default="crs2d", metavar="NAME|FILE",
                             help="device file: crs2d, crs1d or a path")
            add_device_options(sub, battery_limits=True)
        return sub

    check = add("check", "open the ports, read batteries, show the channel map and wire budget")
    check.add_argument("--protocol", default=None, metavar="FILE",
                       help="plan this protocol's digit stimuli on the wire (default: the "
                            f"default protocol, {DEFAULT_PROTOCOL})")
    check.add_argument("--json", action="store_true", help="print one JSON object")

    add("neutral", "move every actuator to the neutral (safe) pose")

    sweep = add("sweep", "move each channel slowly through its range and back")
    sweep.add_argument("--channel", action="append", default=[], metavar="C:N",
                       help="only this channel, e.g. A:3 (repeatable; default all)")
    sweep.add_argument("--seconds", type=float, default=2.0, help="time per channel")
    sweep.add_argument("--frame-rate", type=float, default=10.0, help="frames per second")

    calibrate = add("calibrate", "find each channel's endpoints by hand; write a new device file")
    calibrate.add_argument("--output", required=True, metavar="FILE",
                           help="the calibrated copy of the device file (never the original)")
    calibrate.add_argument("--overwrite", action="store_true",
                           help="replace --output if it exists")
    calibrate.add_argument("--channel", action="append", default=[], metavar="C:N",
                           help="only this channel (repeatable; default all)")

    monitor = add("monitor", "decode and print the LSC frames a port carries", device=False)
    monitor.add_argument("--port", required=True, metavar="PORT",
                         help="a path or pyserial URL (a serial:// URL with one port works too)")
    monitor.add_argument("--direction", choices=("host", "board"), default="host",
                         help="host: commands to a board (tap the line to the board); "
                              "board: replies from a board")
    monitor.add_argument("--seconds", type=float, default=None,
                         help="stop after this long (default: until Ctrl-C)")
    monitor.add_argument("--max-frames", type=int, default=None, help="stop after this many")
    monitor.add_argument("--baud", type=int, default=9600)
    device_boards.add_actions(add, actions)


def run(args: argparse.Namespace) -> int:
    # SIGTERM and SIGHUP (a kill, a closed terminal) end an action as Ctrl-C does: the device
    # goes to neutral and the ports are released on the way out, never left mid-move
    try:
        with warnings.catch_warnings(record=True) as caught, terminate_as_interrupt():
            warnings.simplefilter("always", DeviceWarning)
            return _ACTIONS[args.action](args)
    finally:
        # shown once the recording has stopped (re-issued inside it, each warning was
        # recorded again, into the list being read: a loop that never ended)
        for warning in caught:
            if issubclass(warning.category, DeviceWarning):
                print(f"crs-study device: warning: {warning.message}", file=sys.stderr)
            else:
                warnings.warn_explicit(warning.message, warning.category,
                                       warning.filename, warning.lineno)


# ---------------------------------------------------------------------------------------------


def _open(args: argparse.Namespace, layout: Layout | None = None) -> Device:
    """The device of ``--device``, with the options given on the command line: every option
    for serial://; the dead-band and refresh (which the simulator models too) for sim://; an
    option the device cannot honour is refused, never ignored."""
    layout = layout or load_layout(args.layout)
    options = device_options(args, args.device)
    return open_device(args.device, layout, **options)


@contextmanager
def _session(device: Device) -> Iterator[Device]:
    """Open ``device``; on the way out (success, error, Ctrl-C, SIGTERM or SIGHUP) close it,
    which sends the neutral pose; a second interrupt waits until that is done. A neutral pose
    that could not be confirmed is never reported as success: it is a one-line DeviceError,
    or, when another error is already on its way, a warning."""
    device.open()
    try:
        yield device
    except BaseException:
        with deferred():
            faults = _close(device)
        for fault in faults:
            print(f"crs-study device: warning: {fault}", file=sys.stderr)
        raise
    with deferred():
        faults = _close(device)
    if faults:
        raise DeviceError(f"closing the device: {faults[0]}"
                          + (f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""))


def _close(device: Device) -> list[str]:
    """Close ``device``; the faults it recorded while doing so."""
    before = len(device.faults)
    device.close()
    return device.faults[before:]


def _check(args: argparse.Namespace) -> int:
    device = _open(args)
    layout = device.layout
    apart = device_boards.told_apart(args.device, layout, args.boards)  # before a servo moves
    if not apart.ok:
        raise DeviceError(f"--device {args.device}: {apart.how}")
    with _session(device):
        battery = device.battery_mv()
    balance = channel_balance(layout)
    report = {
        "device": args.device, "layout": layout.name,
        "battery_mv": dict(zip([c.name for c in layout.controllers], battery, strict=True)),
        "channels": {c.name: [f"{a.channel} {a.name}" for a in layout.actuators
                              if a.controller == c.name] for c in layout.controllers},
        "balance": balance.describe(), "balanced": balance.balanced,
        "channels_per_controller": balance.counts,
        "rewire": [{"from": a, "to": b, "channels": n} for a, b, n in balance.moves],
        "told_apart": apart.how,
        "full_frame_ms": full_frame_wire_time_s(layout) * 1e3,
        "full_frame_rate_hz": full_frame_rate_hz(layout),
    }
    # the wire budget of the protocol to be run; the default one unless told otherwise
    report["protocol_file"] = str(shipped_file(args.protocol or DEFAULT_PROTOCOL))
    report["protocol_is_default"] = args.protocol is None
    report["protocol"] = _protocol_budget(report["protocol_file"], layout, device.options)
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(f"device {args.device}: {layout.name}, opened and returned to neutral")
    for name, mv in report["battery_mv"].items():
        print(f"  controller {name}: battery " + ("unknown (no answer)" if mv is None
                                                   else f"{mv / 1000:.2f} V"))
    # the map in use: pinned by the device file, never moved by software (serial_device,
    # "Which channel goes on which controller")
    print(f"boards told apart {apart.how}" if apart.how.startswith("by ") else
          f"boards told apart: {apart.how}")
    print("channel map (pinned by the device file; each channel is a servo's wire on a board):")
    for name, channels in report["channels"].items():
        print(f"  {name}: " + ", ".join(channels))
    print(f"  {balance.describe()}")
    print(f"wire: a full frame takes {report['full_frame_ms']:.1f} ms on the busiest controller; "
          f"at most {report['full_frame_rate_hz']:.1f} frames/s with every channel changing")
    print(f"protocol {report['protocol_file']}"
          + (" (the default protocol; --protocol FILE plans another)"
             if report["protocol_is_default"] else "") + ": digit stimuli on the wire")
    for condition, p in report["protocol"].items():
        refresh = (f" ({p['rate_bound_hz']:.1f}/s with the full refresh every "
                   f"{p['refresh_s']:g} s)" if p["refresh_s"] else "")
        print(f"  {condition}: {p['frames']} frames at {p['frame_rate_hz']:g}/s, changed-only "
              f"bound {p['changed_only_rate_hz']:.1f}/s{refresh}, latency median "
              f"{p['latency_ms_median']:.1f} ms "
              f"(max {p['latency_ms_max']:.1f}), sending everything "
              f"{p['latency_full_ms_median']:.1f} ms")
    return 0


def _protocol_budget(path: str, layout, options) -> dict:
    """The protocol's stimuli on the wire, with the device's dead-band and refresh (each
    stimulus starts after an idle inter-trial interval: its first frame is full)."""
    budget = wire_budget(load_protocol(path), layout, deadband_us=options.deadband_us,
                         refresh_s=options.refresh_s)
    return {c.condition: {
        "frame_rate_hz": budget.frame_rate_hz, "frames": c.frames,
        "deadband_us": budget.deadband_us, "refresh_s": budget.refresh_s,
        "changed_only_rate_hz": c.changed_only_rate_hz, "rate_bound_hz": c.rate_bound_hz,
        "latency_ms_median": c.latency_ms_median, "latency_ms_max": c.latency_ms_max,
        "latency_full_ms_median": c.latency_full_ms_median,
    } for c in budget.conditions}


def _neutral(args: argparse.Namespace) -> int:
    with _session(_open(args)) as device:
        # where the actuators are is unknown (after a crash, anywhere): the slow neutral move
        # close() uses, not the runner's one-frame return to flat
        report = device.send(device.layout.neutral_setpoints(),
                             move_ms=device.options.neutral_move_ms)
        if hasattr(device, "wait_sent") and not device.wait_sent(2.0):
            raise DeviceError(f"--device {args.device}: the neutral pose was not written "
                              f"within 2 s")
    print(f"neutral pose sent: {sum(report.bytes_sent)} bytes, {report.channels_sent} channels")
    return 0


def _selected(layout, channels: list[str]) -> list[int]:
    refs = {f"{a.controller}:{a.channel}": a.index for a in layout.actuators}
    if not channels:
        return list(range(layout.n_actuators))
    missing = [c for c in channels if c not in refs]
    if missing:
        raise DeviceError(f"--channel: unknown channel(s) {', '.join(map(repr, missing))}; "
                          f"this device has {', '.join(refs)}")
    return [refs[c] for c in channels]


def _sweep(args: argparse.Namespace) -> int:
    if not (SWEEP_MIN_RATE_HZ <= args.frame_rate <= SWEEP_MAX_RATE_HZ):
        raise DeviceError(f"--frame-rate: expected {SWEEP_MIN_RATE_HZ:.3g}..{SWEEP_MAX_RATE_HZ:g} "
                          f"frames/s (a frame's move time is at most 30 s), got "
                          f"{args.frame_rate!r}")
    if not (math.isfinite(args.seconds) and 0 < args.seconds <= SWEEP_MAX_S):
        raise DeviceError(f"--seconds: expected a time per channel in (0, {SWEEP_MAX_S:g}] s, "
                          f"got {args.seconds!r}")
    device = _open(args)
    layout = device.layout
    chosen = _selected(layout, args.channel)
    # frames per channel, even, so that frame n/2 sits exactly at full travel (an odd count
    # turned back short of it: 3 frames reached 75 %)
    n = 2 * max(1, int(round(args.seconds * args.frame_rate / 2)))
    shape = 0.5 * (1 - np.cos(2 * np.pi * np.arange(n + 1) / n))  # 0 -> 1 -> 0, smooth
    period_ms = int(round(1000 / args.frame_rate))
    with _session(device):
        for index in chosen:
            actuator = layout.actuators[index]
            print(f"sweeping {actuator.controller}:{actuator.channel} {actuator.name} "
                  f"0 -> {actuator.calibration.travel_mm:g} -> 0 mm", flush=True)
            start = device.clock.now()
            for k, fraction in enumerate(shape):
                setpoints = layout.neutral_setpoints()
                setpoints[index] = fraction * actuator.calibration.travel_mm
                device.send(setpoints, move_ms=period_ms)
                device.clock.sleep_until(start + (k + 1) / args.frame_rate)
    print(f"sweep done: {len(chosen)} channel(s) through their range; the display is back in "
          "its neutral pose")
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.exists() and not args.overwrite:
        raise DeviceError(f"--output {out}: already exists; choose another file or --overwrite")
    # found out now, not after the experimenter has set every endpoint by hand
    if out.is_dir() or not out.parent.is_dir() or not os.access(out.parent, os.W_OK):
        raise DeviceError(f"--output {out}: expected a new file in a writable directory")
    if out.exists() and out.resolve() == device_file_path(args.layout).resolve():
        raise DeviceError(f"--output {out}: is the device file being calibrated; the "
                          f"calibration goes into a copy, never the original")
    if args.deadband_us is None:
        args.deadband_us = 0  # every 1 us step the experimenter asks for must reach the servo
    device = _open(args)
    if not hasattr(device, "send_pulses"):
        raise DeviceError(f"--device {args.device}: calibration needs a serial:// device")
    layout = device.layout
    chosen = _selected(layout, args.channel)
    print("For each channel: type + or - (10 us), ++ or -- (50 us), > or < (1 us), a pulse in "
          "us, 'ok' to keep the position, 'skip' to leave the channel as it is, 'quit' to stop "
          "(nothing is written).")
    endpoints: dict[str, tuple[float, float]] = {}
    with _session(device):  # on the way out, every channel goes to its (old) neutral
        neutral = device.pulse_map.neutral_pulses(layout)
        device.send_pulses(neutral, move_ms=300)
        for index in chosen:
            actuator = layout.actuators[index]
            key = f"{actuator.controller}:{actuator.channel}"
            found = []
            for label, mm_value in (("base (0 mm, fully retracted)", 0.0),
                                    (f"full travel ({actuator.calibration.travel_mm:g} mm)",
                                     actuator.calibration.travel_mm)):
                setpoints = layout.neutral_setpoints()
                setpoints[index] = mm_value
                pulse = int(device.pulse_map.to_pulses(setpoints)[index])
                pulse = _adjust(device, neutral, index, pulse, f"{key} {actuator.name}: {label}")
                if pulse is None:
                    break
                found.append(pulse)
            if len(found) == 2:
                if abs(found[1] - found[0]) < 10:
                    print(f"  {key}: endpoints {found[0]} and {found[1]} us are less than 10 us "
                          f"apart; not recorded")
                else:
                    endpoints[key] = (found[0], found[1])
                    print(f"  {key}: zero_us = {found[0]}, full_us = {found[1]}")
            device.send_pulses(neutral, move_ms=300)
    try:
        new = calibration.write_calibrated_copy(device_file_path(args.layout), out, endpoints,
                                    overwrite=args.overwrite)
    except (OSError, DeviceFileError) as exc:
        # the endpoints took the experimenter a while: print them rather than lose them
        print(calibration_table(endpoints, previous_default_endpoints(layout, endpoints)), end="")
        raise DeviceError(f"--output {out}: not written ({exc}); the endpoints found are "
                          f"printed above as a [calibration] table") from None
    print(f"wrote {out}: {len(endpoints)} channel(s) calibrated, device {new.name!r}")
    return 0


def _adjust(device: Device, neutral: np.ndarray, index: int, pulse: int, label: str
            ) -> int | None:
    """Let the experimenter move one channel until it sits where ``label`` says."""
    steps = {"+": 10, "-": -10, "++": 50, "--": -50, ">": 1, "<": -1}
    while True:
        pulse = min(max(pulse, 500), 2500)
        pulses = neutral.copy()
        pulses[index] = pulse
        device.send_pulses(pulses, move_ms=200)
        device.wait_sent(1.0)
        try:
            answer = input(f"{label}: {pulse} us > ").strip().lower()
        except EOFError:
            raise DeviceError("calibration: input ended before every channel was done; "
                              "nothing was written") from None
        if answer == "ok":
            return pulse
        if answer == "skip":
            return None
        if answer == "quit":
            raise DeviceError("calibration stopped by the experimenter; nothing was written")
        if answer in steps:
            pulse += steps[answer]
        elif answer.isdigit():
            pulse = int(answer)
        else:
            print("  expected + - ++ -- > < a pulse in us, ok, skip or quit")


def _monitor(args: argparse.Namespace) -> int:
    # refused before the port is opened, in one line (a negative or NaN --seconds used to end
    # at once, reporting success; a huge --baud overflowed inside pyserial)
    if args.seconds is not None and not (math.isfinite(args.seconds)
                                         and 0 < args.seconds <= MONITOR_MAX_S):
        raise DeviceError(f"--seconds: expected a time in (0, {MONITOR_MAX_S:g}] s (leave it "
                          f"out to run until Ctrl-C), got {args.seconds!r}")
    if args.max_frames is not None and not 1 <= args.max_frames <= MONITOR_MAX_FRAMES:
        raise DeviceError(f"--max-frames: expected 1..{MONITOR_MAX_FRAMES} frames, got "
                          f"{args.max_frames!r}")
    if not MIN_BAUD <= args.baud <= MAX_BAUD:
        raise DeviceError(f"--baud: expected {MIN_BAUD}..{MAX_BAUD} (the LSC boards use 9600), "
                          f"got {args.baud!r}")
    spec = args.port
    if spec.startswith("serial://"):
        specs = parse_serial_url(spec)
        if len(specs) != 1:
            raise DeviceError(f"--port {spec!r}: expected one port, got {len(specs)}")
        spec = specs[0]
    try:
        # looked up on its module: the tests stand a scripted port in for it there
        port = serial_port.serial_for_spec(spec, baudrate=args.baud, timeout=0.05,
                                           write_timeout=0.5)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"--port {spec}: cannot open: {exc}") from None
    decoder = FrameDecoder(args.direction)
    held: list = []
    frames = 0
    start = time.monotonic()
    try:
        while args.seconds is None or time.monotonic() - start < args.seconds:
            # every read returns within the port's 0.05 s timeout, so a silent port still
            # ends at --seconds and Ctrl-C lands between reads
            try:
                data = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError) as exc:
                raise DeviceError(f"--port {spec}: read failed: {exc}") from None
            # an empty read: the line was quiet for the read timeout; frames held back for
            # the bytes after them (a possible false header) are decided now
            events = [(f.offset, describe_message(f.message))
                      for f in (decoder.feed(data) if data else decoder.idle())]
            runs = _join([*held, *decoder.take_skipped()])
            # a run that reaches the end of what was read may go on in the next read
            held = [runs.pop()] if runs and runs[-1].offset + len(runs[-1].data) == \
                decoder.position else []
            events += [(s.offset, f"skipped {len(s.data)} byte(s) ({s.reason}): "
                        f"{s.data.hex(' ')}") for s in runs]
            for offset, text in sorted(events):
                print(f"{time.monotonic() - start:9.3f} s  @{offset:<7d} {text}", flush=True)
            frames += sum(1 for e in events if not e[1].startswith("skipped"))
            if args.max_frames is not None and frames >= args.max_frames:
                break
    except KeyboardInterrupt as interrupt:
        # Ctrl-C (or SIGTERM, SIGHUP) is how a monitor without --seconds is meant to end:
        # report, exit 0
        print(f"stopped ({describe(interrupt)})", flush=True)
    finally:
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass  # a vanished port may fail to close; the read error above says why
        last = decoder.flush()
        for f in last:
            print(f"end of stream: @{f.offset} {describe_message(f.message)}")
        frames += len(last)
        for s in _join([*held, *decoder.take_skipped()]):
            print(f"end of stream: skipped {len(s.data)} byte(s) ({s.reason}): "
                  f"{s.data.hex(' ')}")
    print(f"{frames} frame(s), {decoder.skipped_bytes} byte(s) skipped")
    return 0


def _join(runs: list) -> list:
    """Merge skipped runs that touch (a run cut in two by the read boundary)."""
    out: list = []
    for run in runs:
        if out and out[-1].offset + len(out[-1].data) == run.offset:
            out[-1] = Skipped(out[-1].offset, out[-1].data + run.data, out[-1].reason)
        else:
            out.append(run)
    return out


def _identify(args: argparse.Namespace) -> int:
    with _session(_open(args)) as device:
        return device_boards.identify(args, device)


_ACTIONS = {"check": _check, "neutral": _neutral, "sweep": _sweep, "calibrate": _calibrate,
            "monitor": _monitor, "boards": device_boards.boards, "identify": _identify}
