"""The command line: every subcommand is listed, --help is fast, errors are one line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from crs_study.cli import build_parser, main

SUBCOMMANDS = ("demo", "init", "validate", "run", "dry-run", "analyze", "power", "consent",
               "device", "quality", "bench")


def test_every_subcommand_is_listed_in_order(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    listed = [line.split()[0] for line in text.splitlines()
              if line.startswith("    ") and not line.startswith("     ")]
    assert listed == list(SUBCOMMANDS)


def test_building_the_parser_loads_no_heavy_library():
    """`crs-study --help` and every command's start must not pay for scipy or matplotlib."""
    code = ("import sys; from crs_study.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('scipy', 'matplotlib', 'pandas', 'statsmodels') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_unknown_bench_area_is_one_line(capsys):
    assert main(["bench", "no-such-area"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown bench area 'no-such-area'" in err[0]


def test_every_subcommand_has_help(capsys):
    parser = build_parser()
    for name in SUBCOMMANDS:
        with pytest.raises(SystemExit) as exit_info:
            parser.parse_args([name, "--help"])
        assert exit_info.value.code == 0
        assert "usage: crs-study " + name in capsys.readouterr().out
