"""Copy the shipped protocols, analysis plans and consent forms into DIR, to edit them.

Makes DIR/protocols, DIR/analysis and DIR/consent (each with its README), the layout of the
crs-study repository. Files already there with the same content are left alone; if any file
there differs from the shipped one, nothing is copied. Shipped protocols can also be used by
name without copying: crs-study dry-run pilot --participants 2 --out rehearsal.
"""

from __future__ import annotations

import argparse
import os

from crs_study.paths import copy_defaults


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("directory", metavar="DIR",
                        help="folder to copy into (created when missing)")


def run(args: argparse.Namespace) -> int:
    copied = copy_defaults(args.directory)
    for item in copied:
        print(f"{'copied' if item.written else 'unchanged'}  {os.fspath(item.path)}")
    written = sum(item.written for item in copied)
    protocol = os.path.join(args.directory, "protocols", "pilot.toml")
    print(f"init: {written} of {len(copied)} files copied into {args.directory}; edit them, "
          f"then check one with: crs-study validate {protocol}")
    return 0
