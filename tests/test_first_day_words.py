"""Messages and words a first day met: one line each, the same name for one thing,
help that cites nothing a user lacks, summaries that say what happened."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

import crs_study
from crs_study.cli import COMMANDS, build_parser, main

CLI = [sys.executable, "-m", "crs_study"]


def help_of(argv: list[str]) -> str:
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args([*argv, "--help"])
    return ""


@pytest.mark.parametrize("command", list(COMMANDS))
def test_help_cites_no_file_a_user_lacks(command, capsys):
    help_of([command])
    text = capsys.readouterr().out
    for action in ("check", "sweep", "identify", "boards", "monitor") if command == "device" \
            else ():
        help_of([command, action])
        text += capsys.readouterr().out
    assert not re.search(r"crs-paper\.md|hardware\.md|DESIGN\.md|issue \d", text), text


def test_device_module_docstrings_cite_no_file_a_user_lacks():
    import pkgutil

    import crs_study.device as device

    for info in pkgutil.iter_modules(device.__path__):
        module = __import__(f"crs_study.device.{info.name}", fromlist=["x"])
        text = (module.__doc__ or "") + "".join(
            (getattr(v, "__doc__", "") or "") for v in vars(module).values()
            if getattr(v, "__module__", None) == module.__name__)
        assert not re.search(r"hardware\.md|crs-paper\.md", text), info.name


def test_a_device_warning_is_one_line(tmp_path):
    """`crs-study run` on a device whose boards do not answer the battery request."""
    done = subprocess.run([*CLI, "run", "pilot", "--participant", "sim1", "--device",
                           "sim://?garbage_rate=1", "--out", str(tmp_path / "ds"),
                           "--responder", "random", "--json"],
                          capture_output=True, text=True, timeout=300)
    warned = [line for line in done.stderr.splitlines() if "battery unknown" in line]
    assert warned and all(w.startswith("crs-study run: warning: ") for w in warned), \
        done.stderr
    assert "DeviceWarning" not in done.stderr and "self.open()" not in done.stderr


def test_consent_register_has_one_name(tmp_path, capsys):
    for argv in (["run", "pilot"], ["consent", "list"], ["consent", "record"]):
        help_of(argv)
        assert "--consent-register" in capsys.readouterr().out, argv
    register = tmp_path / "register"
    assert main(["consent", "record", "--consent-register", str(register), "--participant",
                 "p1", "--form", "consent_form", "--experimenter", "AB"]) == 0
    assert main(["consent", "list", "--register", str(register)]) == 0  # the old name too
    assert "p1" in capsys.readouterr().out


@pytest.mark.parametrize("make, what", [
    (lambda p: p.write_text("x"), "is a file, not a folder"),
    (lambda p: None, "no such folder")])
def test_consent_list_on_a_file_or_a_missing_folder_says_so(tmp_path, capsys, make, what):
    target = tmp_path / "register"
    make(target)
    assert main(["consent", "list", "--consent-register", str(target)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and what in err


def test_dry_run_out_on_a_symlink_loop_says_what_is_wrong(tmp_path, capsys):
    (tmp_path / "loop").symlink_to("loop")
    assert main(["dry-run", "pilot", "--participants", "1", "--out",
                 str(tmp_path / "loop")]) == 2
    err = capsys.readouterr().err
    assert "symbolic link that leads nowhere" in err and "File exists" not in err


def test_a_finished_dry_run_rerun_says_nothing_was_run(tmp_path, capsys):
    argv = ["dry-run", "pilot", "--participants", "1", "--out", str(tmp_path / "ds")]
    assert main(argv) == 0
    first = capsys.readouterr().out
    assert "trials run now" in first and "min of simulated session time" in first
    assert main(argv) == 0
    again = capsys.readouterr().out.strip()
    assert again.endswith("nothing to run") and "0.0 min" not in again
    data = crs_study.analyze(tmp_path / "ds", write=False)
    # the report's words: participant, not the column participant_id
    assert not any("participant_id" in w for w in data.warnings), data.warnings


def test_sweep_says_it_is_done(capsys):
    assert main(["device", "sweep", "--device", "sim://", "--layout", "crs1d", "--channel",
                 "A:1", "--seconds", "0.2"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("sweep done: 1 channel")
