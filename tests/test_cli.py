"""The command line: every subcommand is listed, --help is fast, errors are one line."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys

import pytest

import crs_study.commands as commands
from crs_study.cli import COMMANDS, build_parser, command_module, main

SUBCOMMANDS = ("demo", "init", "validate", "lock", "run", "dry-run", "analyze", "power", "consent",
               "device", "live", "live-send", "quality", "bench")


def test_every_subcommand_is_listed_in_order(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    listed = [line.split()[0] for line in text.splitlines()
              if line.startswith("    ") and not line.startswith("     ")]
    assert listed == list(SUBCOMMANDS)


def loaded_after(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of ``modules`` a fresh interpreter has imported after running ``code``."""
    probe = f"import sys; {code}; print(sorted(m for m in {modules!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True).stdout.strip()
    return ast.literal_eval(out)


def test_building_the_parser_loads_no_heavy_library():
    """`crs-study --help` and every command's start must not pay for scipy or matplotlib."""
    assert loaded_after("from crs_study.cli import build_parser; build_parser()",
                        ("scipy", "matplotlib", "pandas", "statsmodels")) == []


def test_a_session_and_a_withdrawal_load_no_pandas():
    """`crs-study run`, `dry-run` and `consent` start without pandas (half a second of CPU
    at every start; only the tables of a notebook need it)."""
    code = "; ".join(f"import crs_study.commands.{name}"
                     for name in ("run", "dry_run", "consent", "validate"))
    assert loaded_after(code, ("pandas", "matplotlib", "statsmodels")) == []


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


def test_every_command_module_is_a_listed_subcommand():
    """COMMANDS names each subcommand once; its module is found from the name, so a module
    the table lacks would be unreachable, and a name without a module would fail at use."""
    files = {info.name for info in pkgutil.iter_modules(commands.__path__)
             if not info.name.startswith("_")}
    assert {command_module(name).rsplit(".", 1)[1] for name in COMMANDS} == files


def test_only_the_chosen_command_is_imported():
    """Building the parser imports no command module; choosing one imports that one only."""
    code = ("import sys; from crs_study.cli import build_parser; parser = build_parser(); "
            "print(sorted(m for m in sys.modules if m.startswith('crs_study.commands.'))); "
            "parser.parse_args(['init', 'somewhere']); "
            "print(sorted(m for m in sys.modules if m.startswith('crs_study.commands.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out == ["[]", "['crs_study.commands.init']"]


def test_reading_a_protocol_loads_neither_scipy_stats_nor_questplus():
    """Protocols name their adaptive procedure, so every command that reads one imports the
    adaptive package; scipy.stats and questplus (~0.9 s together) load only when a staircase
    interval or a QUEST+ track is computed (``validate --help`` took 1.8 s, 0.9 s now)."""
    assert loaded_after("import crs_study; crs_study.load_protocol('pilot'); "
                        "crs_study.load_protocol('digit_size_adaptive')",
                        ("scipy.stats", "questplus")) == []
