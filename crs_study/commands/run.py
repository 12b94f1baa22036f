"""Run (or resume) one participant session of a protocol on a device.

Every trial is stored durably before the next begins. After an interruption (Ctrl-C, a power
cut, a device fault) run the same command again: the session resumes at the next unfinished
trial of the same plan. A completed session is never overwritten: pass --session N for
another session. A session under a person's label needs a consent record first (crs-study
consent record) on every device, sim:// included; only a simulated participant (a sim...
label answered by a simulated responder on sim://) needs none.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from crs_study._files import os_errors
from crs_study.commands import add_device_options, device_options
from crs_study.dataset import dataset_dir
from crs_study.errors import ConfigError, DatasetError
from crs_study.protocol import emit_warnings, load_protocol
from crs_study.session.responders import make_responder
from crs_study.session.runner import run_session, seed_check
from crs_study.session.screen import TerminalScreen
from crs_study.session.spec import SessionSpec

EXIT_INTERRUPTED = 130


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", metavar="PROTOCOL",
                        help="protocol file (TOML), or a shipped protocol's name (pilot, "
                        "digit_identification, ...)")
    parser.add_argument("--participant", required=True, metavar="ID",
                        help="participant label (letters and digits; never a name)")
    parser.add_argument("--device", required=True, metavar="URL",
                        help="serial:///dev/ttyUSB0,/dev/ttyUSB1 or sim://")
    parser.add_argument("--out", required=True, metavar="DATASET",
                        help="dataset directory (BIDS); created when missing")
    parser.add_argument("--session", type=int, default=1, metavar="N",
                        help="session number (a completed session is never overwritten)")
    parser.add_argument("--responder", default="keypad",
                        metavar="keypad|scripted:FILE|random|observer",
                        help="who answers: a person at the terminal, a script, or a simulation")
    parser.add_argument("--clock", choices=("real", "virtual", "auto"), default="auto",
                        help="auto: virtual for sim:// with a simulated responder, else real")
    parser.add_argument("--counterbalance", type=int, default=None, metavar="K",
                        help="counterbalance index (default: the participant's order of arrival "
                        "in the dataset)")
    parser.add_argument("--consent-register", type=Path, default=None, metavar="DIR",
                        help="consent register (default: $CRS_STUDY_CONSENT_DIR or "
                        "~/.crs-study/consent); needed for a person's label on every device, "
                        "sim:// included; only simulated participants (sim... labels, a "
                        "simulated responder, sim://) skip it")
    parser.add_argument("--seed-check", action="store_true",
                        help="print the seed and plan hash, compare with a stored session, "
                        "write nothing")
    parser.add_argument("--experimenter-view", type=Path, default=None, metavar="PATH",
                        help="keypad sessions: show the experimenter's view (status, state, "
                        "what to do) on PATH, a second terminal such as /dev/pts/4 or a log "
                        "file, and only the participant's view here (default: both here)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON summary on stdout and no progress")
    add_device_options(parser)


def spec_from_args(args: argparse.Namespace):
    return SessionSpec(
        protocol=Path(args.protocol), participant=args.participant,
        dataset=dataset_dir(args.out),
        device_url=args.device, session=args.session, responder=args.responder,
        clock=args.clock, counterbalance=args.counterbalance,
        consent_register=args.consent_register,
    )


def stderr_progress(enabled: bool):
    """A progress callback writing one updating line on stderr (None when disabled)."""
    if not enabled:
        return None
    tty = sys.stderr.isatty()

    def show(text: str) -> None:
        if tty:
            sys.stderr.write("\r" + text + "\x1b[K")
        else:
            sys.stderr.write(text + "\n")
        sys.stderr.flush()

    return show


@contextlib.contextmanager
def experimenter_view(path: Path | None) -> Iterator[TextIO | None]:
    """The experimenter's stream: ``path`` opened for appending (a terminal or a log), or None
    (the view shares the participant's terminal)."""
    if path is None:
        yield None
        return
    try:
        stream = open(path, "a", encoding="utf-8")  # noqa: SIM115 - closed below
    except OSError as error:
        raise ConfigError(f"--experimenter-view {path}: cannot open it for writing "
                          f"({error.strerror or error})") from None
    with stream:
        yield stream


@os_errors(DatasetError)  # disk full, permission denied, a file where a folder should be: one line
def run(args: argparse.Namespace) -> int:
    spec = spec_from_args(args)
    if args.seed_check:
        report = seed_check(spec)
        if args.json:
            print(json.dumps(report))
        else:
            for key, value in report.items():
                print(f"{key}: {value}")
        return 0
    # odd but legal values, before anything runs
    protocol = load_protocol(spec.protocol)
    emit_warnings(protocol)
    options = device_options(args, spec.device_url)
    if spec.responder == "keypad":  # the screen shows where the session stands
        with experimenter_view(args.experimenter_view) as view:
            keypad = make_responder("keypad", seed=0, protocol=protocol,
                                    screen=TerminalScreen(sys.stderr, view))
            result = run_session(spec, responder=keypad, device_options=options)
    else:
        if args.experimenter_view is not None:
            raise ConfigError("--experimenter-view is for --responder keypad (a person at the "
                              "terminal)")
        show = stderr_progress(not args.json)
        result = run_session(spec, progress=show, device_options=options)
        if show and sys.stderr.isatty():
            sys.stderr.write("\n")
    if args.json:
        print(json.dumps({
            "status": result.status, "participant": result.participant,
            "session": result.session, "trials_planned": result.trials_planned,
            "trials_completed": result.trials_completed, "trials_run": result.trials_run,
            "late_frames": result.late_frames, "session_seconds": result.session_seconds,
            "wall_seconds": result.wall_seconds, "tsv": os.fspath(result.tsv),
            "sidecar": os.fspath(result.sidecar)}))
    if result.status == "interrupted":
        print(f"crs-study run: paused at trial {result.trials_completed + 1}/"
              f"{result.trials_planned}; the session is marked interrupted: run the same "
              "command to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not args.json:
        print(result.message)
    return 0
