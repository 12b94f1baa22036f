"""The commands run, dry-run and demo; Ctrl-C and SIGTERM as safe pauses; a session through
pseudo-terminals with virtual LSC-24 boards on the other side (the real serial path)."""

from __future__ import annotations

import csv
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _session_helpers import record_consent, start_command, tiny_protocol, wait_for_stderr

from crs_study.cli import main
from crs_study.commands.demo import fresh_directory


@pytest.fixture(autouse=True)
def _consented():
    """p01: people's labels, gated by consent on every device, sim:// too."""
    record_consent("p01")


TSV = "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.tsv"
SIDECAR = "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.json"


def run_args(protocol, dataset, *extra):
    return ["run", str(protocol), "--participant", "p01", "--device", "sim://", "--out",
            str(dataset), "--responder", "random", *extra]


def test_run_then_rerun_a_complete_session(tmp_path, capsys):
    protocol = tiny_protocol(tmp_path)
    assert main(run_args(protocol, tmp_path / "ds")) == 0
    out, err = capsys.readouterr()
    assert out.startswith("session 1 of participant p01: 8/8 trials in ")
    assert "trial 8/8" in err  # progress on stderr
    before = (tmp_path / "ds" / TSV).read_bytes()
    assert main(run_args(protocol, tmp_path / "ds")) == 0
    out, _ = capsys.readouterr()
    assert "is complete (8 trials)" in out and "nothing to do" in out
    assert (tmp_path / "ds" / TSV).read_bytes() == before


def test_run_json_is_quiet(tmp_path, capsys):
    assert main(run_args(tiny_protocol(tmp_path), tmp_path / "ds", "--json")) == 0
    out, err = capsys.readouterr()
    summary = json.loads(out)
    assert summary["status"] == "complete" and summary["trials_completed"] == 8
    assert summary["session_seconds"] > 8 and err == ""


def test_seed_check_writes_nothing(tmp_path, capsys):
    protocol = tiny_protocol(tmp_path)
    assert main(run_args(protocol, tmp_path / "ds", "--seed-check", "--json")) == 0
    report = json.loads(capsys.readouterr().out)
    from crs_study.protocol.plan import plan_seed

    assert report["seed"] == plan_seed("tiny", "1.0.0", "p01", 1)
    assert report["stored"] == "none" and report["trials"] == 8
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("change, message", [
    (["--participant", "p_01"], "participant label 'p_01' is not valid"),
    (["--responder", "psychic"], "unknown responder 'psychic'"),
    (["--device", "usb://x"], "unknown device URL 'usb://x'"),
    (["--session", "0"], "session must be a whole number >= 1, got 0"),
    (["--counterbalance", "-1"], "counterbalance index must be >= 0, got -1"),
])
def test_bad_input_is_one_line(tmp_path, capsys, change, message):
    assert main(run_args(tiny_protocol(tmp_path), tmp_path / "ds", *change)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_missing_protocol(tmp_path, capsys):
    assert main(run_args(tmp_path / "none.toml", tmp_path / "ds")) == 2
    assert "no such protocol file" in capsys.readouterr().err


_start = start_command
_wait_for = wait_for_stderr


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=["ctrl-c", "sigterm", "sighup"])
def test_ctrl_c_is_a_safe_pause(tmp_path, signum):
    """A real-clock session paused by Ctrl-C, SIGTERM or SIGHUP (a closed terminal or SSH):
    exit 130, neutral, resumable; resumed (after Ctrl-C) on the same real clock, as a
    resume must be, with nothing lost or twice."""
    # Inter-trial intervals of 2 s keep the three trials after "trial 2/4" running for over
    # ten seconds, so a loaded machine cannot finish the session before the signal lands.
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=2.0)
    dataset = tmp_path / "ds"
    process = _start(run_args(protocol, dataset, "--clock", "real"), tmp_path)
    try:
        _wait_for(process, "trial 2/4")
        process.send_signal(signum)
        _, err = process.communicate(timeout=30)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 130, err
    assert "paused at trial 2/4" in err and "run the same command to resume" in err
    meta = json.loads((dataset / SIDECAR).read_text())
    assert meta["Status"] == "interrupted" and meta["TrialsCompleted"] == 1
    if signum != signal.SIGINT:
        return
    assert main(run_args(protocol, dataset, "--clock", "virtual")) == 2  # not another clock
    assert main(run_args(protocol, dataset, "--clock", "real", "--json")) == 0
    with open(dataset / TSV, newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    assert [int(r["trial_index"]) for r in rows] == list(range(4))
    resumes = json.loads((dataset / SIDECAR).read_text())["Resumes"]
    assert [r["AtTrial"] for r in resumes] == [1]


def test_ctrl_c_reaches_started_processes_when_the_suite_runs_in_the_background():
    """``pytest ... &`` in a shell script: the shell starts pytest with SIGINT ignored (POSIX,
    asynchronous commands without job control), which every process it starts inherited, so
    a Ctrl-C test's session ran to its end and exited 0. The probe of
    ``test_sigint_probe.py``, run that way in an xdist worker, as the suite runs."""
    probe = Path(__file__).resolve().with_name("test_sigint_probe.py")
    test = f"{probe}::test_a_started_process_takes_ctrl_c_as_from_a_terminal"
    pytest_command = shlex.join([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                 "-n", "1", test])
    script = f"{pytest_command} & wait $!"
    done = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parent.parent, check=False)
    assert done.returncode == 0 and "1 passed" in done.stdout, done.stdout + done.stderr


@pytest.mark.slow
def test_dry_run_and_rerun(tmp_path, capsys):
    protocol = tiny_protocol(tmp_path)
    args = ["dry-run", str(protocol), "--participants", "3", "--out", str(tmp_path / "ds"),
            "--responder", "random", "--jobs", "2"]
    assert main(args + ["--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["trials"] == 24 and [s["status"] for s in summary["sessions"]] == \
        ["complete"] * 3
    participants = (tmp_path / "ds/participants.tsv").read_text().splitlines()
    assert participants[1:] == ["sub-sim01\t0", "sub-sim02\t1", "sub-sim03\t2"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "3 participants, 24 trials" in out and "already-complete" in err


@pytest.mark.slow
def test_demo_writes_a_new_directory_and_reports(tmp_path, capsys):
    out_dir = tmp_path / "demo"
    args = ["demo", "--protocol", str(tiny_protocol(tmp_path, repetitions=2)),
            "--participants", "2", "--out", str(out_dir), "--responder", "random"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert f"dataset in {out_dir}" in out
    assert "report:" in out or "analysis unavailable" in err
    assert (out_dir / "participants.tsv").exists()
    assert main(args) == 2
    assert "exists and is not empty; the demo never overwrites" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "dry-run"])
def test_odd_protocol_values_are_printed_as_warnings_before_the_session(tmp_path, capsys,
                                                                        command):
    """STYLE rule 5: an odd but legal value is a one-line warning on stderr, once, and the
    session runs."""
    import warnings

    from crs_study.errors import CrsStudyWarning

    protocol = tiny_protocol(tmp_path, iti=0.0)
    args = {"run": run_args(protocol, tmp_path / "ds", "--json"),
            "dry-run": ["dry-run", str(protocol), "--participants", "2", "--out",
                        str(tmp_path / "ds"), "--responder", "random", "--json"]}[command]
    with warnings.catch_warnings():
        warnings.simplefilter("always", CrsStudyWarning)  # the suite makes warnings errors
        assert main(args) == 0
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"crs-study {command}: warning: {protocol}:")
    assert "design.inter_trial_interval_s: 0.0 s: the next digit starts" in err[0]



@pytest.mark.slow
def test_the_demo_writes_outside_the_checkout_and_lists_every_chart(tmp_path):
    """Run as README orders it, from inside a source checkout: the demo writes under the
    home folder (a checkout's git clean would delete its dataset), says where and why, and
    names every chart it wrote (it listed 2 of 5)."""
    import subprocess
    import sys

    checkout = tmp_path / "checkout"
    checkout.mkdir()
    subprocess.run(["git", "init", "-q", str(checkout)], check=True)
    home = tmp_path / "home"
    home.mkdir()
    protocol = tiny_protocol(tmp_path, repetitions=2)
    env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, "-m", "crs_study", "demo", "--protocol",
                           str(protocol), "--participants", "2", "--responder", "random",
                           "--jobs", "1"], cwd=checkout, env=env, capture_output=True,
                          text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(p.name for p in checkout.iterdir()) == [".git"]   # nothing in the checkout
    (dataset,) = (home / "crs-study-demo").iterdir()
    assert f"demo: writing to {dataset} (a folder of its own, outside any source checkout" \
        in done.stderr
    figures = sorted((dataset / "derivatives" / "crs-study" / "figures").glob("*.png"))
    listed = sorted(line.split(": ", 1)[1] for line in done.stdout.splitlines()
                    if line.startswith("chart ("))
    assert len(figures) >= 5 and listed == [str(p) for p in figures]
    lines = done.stdout.splitlines()
    assert lines[1].startswith("pixel-only") or lines[1].startswith("crs")   # the headline


def test_fresh_directories_never_collide(tmp_path):
    first = fresh_directory(tmp_path)
    first.mkdir(parents=True)
    second = fresh_directory(tmp_path)
    assert second != first and second.parent == first.parent == tmp_path
    assert first.name.startswith("demo-")


@pytest.mark.slow
def test_a_session_through_ptys_with_virtual_boards(tmp_path, capsys):
    """The real serial path: SerialDevice on two pseudo-terminals, virtual LSC-24 boards on the
    master side at 9600 baud, a real clock, consent checked, every trial stored."""
    from crs_study.consent import Register, read_form
    from crs_study.device.virtual_controller import VirtualController
    from crs_study.device.virtual_pty import VirtualControllerPty
    from crs_study.paths import shipped_file

    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.2)
    register = tmp_path / "register"
    Register(register).record(read_form(shipped_file("consent/consent_form.md")), "AB", "p01")
    script = tmp_path / "answers.txt"
    script.write_text("1\t0.1\n" * 4)
    start = time.monotonic()
    with VirtualControllerPty(VirtualController("A", record=True, t0=start), baud=9600) as a, \
            VirtualControllerPty(VirtualController("B", record=True, t0=start), baud=9600) as b:
        code = main(["run", str(protocol), "--participant", "p01", "--device",
                     f"serial://{a.port},{b.port}", "--out", str(tmp_path / "ds"),
                     "--responder", f"scripted:{script}", "--clock", "real",
                     "--consent-register", str(register), "--json"])
        assert code == 0, capsys.readouterr().err
        summary = json.loads(capsys.readouterr().out)
        assert a.board.bad_frames == 0 and b.board.bad_frames == 0
        assert a.bytes_received > 0 and b.bytes_received > 0
    assert summary["trials_completed"] == 4 and summary["status"] == "complete"
    with open(tmp_path / "ds" / TSV, newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    for row in rows:
        assert row["response"] == "1" and row["correct"] == str(int(row["digit"] == "1"))
        # 9600 baud: a changed-only frame's last byte leaves within two full frames (133 ms)
        assert 0 < float(row["median_wire_latency"]) < 0.14
        assert int(row["late_frames"]) <= int(row["frames"]) // 4
    meta = json.loads((tmp_path / "ds" / SIDECAR).read_text())
    assert meta["Clock"] == "real" and meta["DeviceURL"].startswith("serial://")
    assert os.path.basename(meta["ProtocolPath"]) == "tiny.toml"


@pytest.mark.parametrize("command", ["run", "dry-run", "demo"])
def test_an_unwritable_dataset_is_one_line(tmp_path, capsys, command):
    """--out under a file used to end in a traceback (NotADirectoryError from mkdir)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "ds"
    args = {"run": run_args(tiny_protocol(tmp_path), out),
            "dry-run": ["dry-run", str(tiny_protocol(tmp_path)), "--participants", "1",
                        "--out", str(out), "--responder", "random"],
            "demo": ["demo", "--out", str(out)]}[command]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert f"crs-study {command}: error: {out}" in err and "Not a directory" in err
    assert blocker.read_text() == ""
