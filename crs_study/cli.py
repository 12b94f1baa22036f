"""The ``crs-study`` command line: a thin layer of argparse subcommands over the library.

Each subcommand lives in its own module under :mod:`crs_study.commands` and provides

``NAME``
    the subcommand's name (``"demo"``, ``"run"``, ...);
``HELP``
    one line for ``crs-study --help``;
``add_arguments(parser)``
    adds its options to an :class:`argparse.ArgumentParser`;
``run(args) -> int``
    does the work and returns the exit status.

Known failures (:class:`~crs_study.errors.CrsStudyError`) print one line on stderr and exit 2;
``--debug`` shows the traceback instead. Modules import heavy libraries inside ``run`` so that
``crs-study --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import warnings
from collections.abc import Sequence
from types import ModuleType

from crs_study import __version__
from crs_study.commands import HelpFormatter
from crs_study.errors import CrsStudyError, CrsStudyWarning

#: Exit status for a known error (bad input, device fault, refused consent, ...).
EXIT_KNOWN_ERROR = 2
#: Exit status after Ctrl-C, as shells expect (128 + SIGINT).
EXIT_INTERRUPTED = 130

# Order in which subcommands are listed in --help: the main job first, then the pipeline.
_PREFERRED_ORDER = (
    "demo", "init", "validate", "run", "dry-run", "analyze", "power", "consent", "device",
    "quality", "bench",
)


def _command_modules() -> list[ModuleType]:
    import crs_study.commands as package

    modules = [
        importlib.import_module(f"{package.__name__}.{info.name}")
        for info in pkgutil.iter_modules(package.__path__)
        if not info.name.startswith("_")
    ]
    rank = {name: i for i, name in enumerate(_PREFERRED_ORDER)}
    return sorted(modules, key=lambda m: (rank.get(m.NAME, len(rank)), m.NAME))


def build_parser() -> argparse.ArgumentParser:
    """The full parser, with one subparser per module in :mod:`crs_study.commands`."""
    parser = argparse.ArgumentParser(
        prog="crs-study",
        description="Psychophysics experiments on the continuity reinforcement skeleton "
        "(CRS) haptic display: protocols, sessions, simulated dry-runs and analysis.",
    )
    parser.add_argument("--version", action="version", version=f"crs-study {__version__}")
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback for known errors"
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _command_modules():
        sub = subparsers.add_parser(
            module.NAME,
            help=module.HELP,
            description=module.__doc__,
            formatter_class=HelpFormatter,
        )
        module.add_arguments(sub)
        sub.set_defaults(_run=module.run)
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
    finally:
        warnings.showwarning = default_show


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
