"""The ``crs-study`` command line: a thin layer of argparse subcommands over the library.

Each subcommand lives in its own module under :mod:`crs_study.commands` (``dry-run`` in
``dry_run.py``) and provides

``add_arguments(parser)``
    adds its options to an :class:`argparse.ArgumentParser`;
``run(args) -> int``
    does the work and returns the exit status;

its docstring is the subcommand's description. :data:`COMMANDS` names the subcommands, in the
order ``crs-study --help`` lists them, with their one-line help.

Known failures (:class:`~crs_study.errors.CrsStudyError`) print one line on stderr and exit 2;
``--debug`` shows the traceback instead.

Start-up: a command's module imports the library it runs at its top (numpy, scipy, pandas,
matplotlib, as its work needs), so building the parser imports none of them.
:class:`CommandParser` imports a command's module only when that command is chosen (to parse
its options, or to show its ``--help``), as pip does with its commands; ``crs-study --help``
imports none, and ``crs-study validate`` only what validating needs.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from collections.abc import Sequence

from crs_study import __version__
from crs_study.commands import HelpFormatter
from crs_study.errors import CrsStudyError, CrsStudyWarning

#: Exit status for a known error (bad input, device fault, refused consent, ...).
EXIT_KNOWN_ERROR = 2
#: Exit status after Ctrl-C, as shells expect (128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Exit status when the reader of stdout went away (128 + SIGPIPE, as a shell reports it).
EXIT_BROKEN_PIPE = 141

#: The subcommands, in the order ``crs-study --help`` lists them (the main job first, then the
#: pipeline): name -> one line of help. The module of ``name`` is ``crs_study.commands.<name>``
#: with ``-`` as ``_``.
COMMANDS: dict[str, str] = {
    "demo": "dry-run the default protocol with simulated participants, analyse, print the "
            "headline",
    "init": "copy the shipped protocols, analysis plans and consent forms into a folder to edit",
    "validate": "check a protocol and print its plan (trials, duration, frames, wire use)",
    "lock": "lock a protocol's analysis plan before the first participant (a file to "
            "publish)",
    "run": "run or resume a participant session on a device",
    "dry-run": "rehearse a protocol: simulated device, simulated participants, virtual clock",
    "analyze": "analyse datasets: accuracy, GLMM, secondary tests, confusions, speed-accuracy, "
               "report",
    "power": "how many participants: power of the primary test by simulation, as a curve",
    "consent": "record consent, list records, withdraw a participant (removes their data)",
    "device": "check the controllers, neutral pose, sweep, calibrate endpoints, monitor a port",
    "live": "drive the display live from finger packets over UDP (the paper's VR link)",
    "live-send": "send a finger trace (a digit, a stroke, a held finger, a recording) to crs-study "
                 "live",
    "quality": "display quality D_P and D_S against d/l per model and lattice (chart, table, "
               "--json)",
    "bench": "measure speed and accuracy figures against in-run baselines",
}


def command_module(name: str) -> str:
    """The module of subcommand ``name``: ``crs_study.commands.dry_run`` for ``dry-run``."""
    return f"crs_study.commands.{name.replace('-', '_')}"


class CommandParser(argparse.ArgumentParser):
    """A subcommand's parser, completed from its module when the subcommand is chosen.

    argparse hands a chosen subcommand's arguments to its parser's :meth:`parse_known_args`;
    the module (its ``add_arguments``, ``run`` and docstring) is imported there, once, so only
    the chosen command pays for the libraries it imports. A command's own subcommands
    (``consent record``) are parsers of this class too (argparse makes them of the class of
    their parent), with no ``command``: plain parsers.
    """

    def __init__(self, *args, command: str | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.command = command
        self._completed = command is None

    def complete(self) -> None:
        """Import the subcommand's module and add its options (once)."""
        if self._completed:
            return
        # The one place the CLI imports its commands: each is loaded when chosen (module
        # docstring), so building the parser stays free of numpy, scipy and matplotlib.
        module = importlib.import_module(command_module(self.command))
        self.description = module.__doc__
        module.add_arguments(self)
        self.set_defaults(_run=module.run)
        self._completed = True

    def parse_known_args(self, args=None, namespace=None):
        self.complete()
        return super().parse_known_args(args, namespace)

    def error(self, message: str):  # type: ignore[override]
        """A bad option is one line, like every other error (argparse prints the usage
        first, ten lines for some commands): ``crs-study run: error: ... (see crs-study run
        --help)``."""
        self.exit(EXIT_KNOWN_ERROR, f"{self.prog}: error: {message} (see {self.prog} "
                  "--help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The full parser: one subparser per entry of :data:`COMMANDS`, completed when chosen."""
    parser = CommandParser(
        prog="crs-study",
        description="Psychophysics experiments on the continuity reinforcement skeleton "
        "(CRS) haptic display: protocols, sessions, simulated dry-runs and analysis.",
    )
    parser.add_argument("--version", action="version", version=f"crs-study {__version__}")
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback for known errors"
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND",
                                       parser_class=CommandParser)
    for name, help_text in COMMANDS.items():
        subparsers.add_parser(name, help=help_text, command=name, formatter_class=HelpFormatter)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``crs-study`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return EXIT_KNOWN_ERROR
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, CrsStudyWarning):
            print(f"crs-study {args.command}: warning: {message}", file=sys.stderr)
        else:
            default_show(message, category, filename, lineno, file, line)

    default_show = warnings.showwarning
    warnings.showwarning = show
    try:
        return int(args._run(args) or 0)
    except CrsStudyError as error:
        if args.debug:
            raise
        print(f"crs-study {args.command}: error: {error}", file=sys.stderr)
        return EXIT_KNOWN_ERROR
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"crs-study {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # the reader went away (`crs-study validate ... | head`): stop quietly, as cat or git
        # do; stdout goes to /dev/null so the interpreter's last flush cannot fail again
        # (the recipe of the Python docs, signal module: "Note on SIGPIPE")
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    finally:
        warnings.showwarning = default_show


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
