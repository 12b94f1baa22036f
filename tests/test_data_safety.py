"""Never lose, leak or mix a participant's data. Each test replays one failure the
adversarial sweep found, as a new user's shell session would meet it: the ``crs-study``
command in a real process on real files (in-process only where no process matters), and
each failed before the fix it names."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _cli import crs_study
from _session_helpers import (
    PauseAt,
    quick_analysis_protocol,
    record_consent,
    start_command,
    tiny_protocol,
    wait_for_stderr,
)

from crs_study.cli import main
from crs_study.consent import Register
from crs_study.dataset import Dataset, SessionPaths
from crs_study.errors import ConsentError, DatasetError, DeviceError
from crs_study.protocol.plan import plan_seed
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec


def run_args(protocol: Path, dataset: Path, participant: str, *extra: str) -> list[str]:
    return ["run", str(protocol), "--participant", participant, "--device", "sim://",
            "--responder", "random", "--out", str(dataset), *extra]


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.endswith(".lock")}


# -- 1. withdrawal removes exactly what BIDS names for the participant ------------------------

def test_withdrawing_01_never_touches_files_that_merely_mention_01(tmp_path, capsys):
    protocol, dataset = tiny_protocol(tmp_path), tmp_path / "ds1"
    for label in ("01", "02", "03"):
        record_consent(label)
        assert main(run_args(protocol, dataset, label, "--json")) == 0
    other = dataset / "derivatives/otherpipe/sub-02/beh"
    other.mkdir(parents=True)
    (other / "sub-02_desc-summary.json").write_text('{"GeneratedOn": "2026-01-05"}')
    (dataset / "derivatives/README.md").write_text("Made 2026-01-05 for sub-01 .. sub-03\n")
    (dataset / "derivatives/otherpipe/sub-01").mkdir()
    (dataset / "derivatives/otherpipe/sub-01/sub-01_desc-summary.json").write_text("{}")
    before = tree(dataset)
    capsys.readouterr()

    # --dry-run lists the paths and rows and removes nothing
    assert main(["consent", "withdraw", "--participant", "01", "--dataset", str(dataset),
                 "--dry-run"]) == 0
    listed = capsys.readouterr().out
    assert tree(dataset) == before
    assert "remove sub-01" in listed and "remove sourcedata/sub-01" in listed
    assert "remove derivatives/otherpipe/sub-01" in listed
    assert "rows of sub-01 from participants.tsv" in listed and "nothing was removed" in listed
    assert "sub-02" not in listed.replace("sub-01", "") and "README" not in listed

    assert main(["consent", "withdraw", "--participant", "01", "--dataset", str(dataset)]) == 0
    done = capsys.readouterr().out
    assert done.index("will remove:") < done.index("withdrawn 01 from")  # listed first
    after = tree(dataset)
    kept = {k: v for k, v in before.items() if "sub-01" not in k and k != "participants.tsv"}
    assert {k: v for k, v in after.items() if k != "participants.tsv"} == kept
    assert "derivatives/otherpipe/sub-02/beh/sub-02_desc-summary.json" in after
    assert "derivatives/README.md" in after
    assert Dataset(dataset).participants() == {"02": 1, "03": 2}


# -- 2. withdrawal during a running session --------------------------------------------------

_start = start_command
_wait_for = wait_for_stderr


@pytest.mark.slow
@pytest.mark.parametrize("how", ["register-only", "dataset-wait"])
def test_a_withdrawal_stops_the_running_session_at_the_next_trial(tmp_path, how):
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=1.5)
    dataset = tmp_path / "ds"
    record_consent("pro1")
    process = _start(run_args(protocol, dataset, "pro1", "--clock", "real"), tmp_path)
    try:
        _wait_for(process, "trial 2/4")
        extra = ["--register-only"] if how == "register-only" else \
            ["--dataset", str(dataset), "--wait", "60"]
        withdrawal = crs_study("consent", "withdraw", "--participant", "pro1", *extra)
        _, err = process.communicate(timeout=30)
    finally:
        process.kill()
        process.wait()
    assert withdrawal.returncode == 0, withdrawal.stderr
    assert process.returncode == 2, err
    assert "withdrew consent" in err and "stopped before trial" in err
    if how == "register-only":  # the data stay until withdrawn; the session stopped short
        sidecar = SessionPaths(dataset, "pro1", 1).sidecar
        meta = json.loads(sidecar.read_text())
        assert meta["Status"] == "interrupted" and meta["TrialsCompleted"] < 4
        assert meta["Interruptions"][-1]["Cause"] == "consent-withdrawn"
    else:
        assert "waiting up to 60 s" in withdrawal.stdout
        assert not (dataset / "sub-pro1").exists()
        assert "pro1" not in (dataset / "participants.tsv").read_text()


@pytest.mark.parametrize("time_value", [None, "", 5, "not a time"])
def test_a_withdrawal_without_a_readable_time_still_closes_the_gate(tmp_path, time_value):
    record_consent("p5")
    register = Register(None)
    with open(register.path, "a") as handle:
        handle.write(json.dumps({"event": "withdrawal", "participant": "p5",
                                 "time": time_value}) + "\n")
    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "p5", tmp_path / "ds", "sim://", 1, "random", "virtual")
    with pytest.raises(ConsentError, match="'p5' withdrew consent on an unknown time"):
        run_session(spec)
    assert not (tmp_path / "ds").exists()


# -- 3. sim:// does not bypass consent ---------------------------------------------------------

def test_sim_does_not_run_a_withdrawn_person(tmp_path):
    protocol, dataset = tiny_protocol(tmp_path), tmp_path / "ds"
    record_consent("p7k2m9q")
    done = crs_study("consent", "withdraw", "--participant", "p7k2m9q", "--register-only")
    assert done.returncode == 0, done.stderr
    refused = crs_study("run", protocol, "--participant", "p7k2m9q", "--device", "sim://",
                        "--responder", "observer", "--out", dataset)
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "withdrew consent" in refused.stderr
    assert not (dataset / "sub-p7k2m9q").exists()
    # without any record, a person's label is refused on sim:// too
    unknown = crs_study(*run_args(protocol, dataset, "p9"))
    assert unknown.returncode == 2 and "no consent record for participant 'p9'" in unknown.stderr


def test_simulated_labels_are_their_own_space(tmp_path):
    protocol, dataset = tiny_protocol(tmp_path), tmp_path / "ds"
    person = crs_study("consent", "record", "--participant", "sim7", "--form", "consent_form",
                       "--experimenter", "AB")
    assert person.returncode == 2 and "reserved for simulated participants" in person.stderr
    from crs_study.consent.gate import needs_consent

    for device, simulated in (("sim://", False), ("serial:///dev/ttyUSB0", True)):
        with pytest.raises(ConsentError, match="simulated labels are for simulated "
                                               "responders on sim:// only"):
            needs_consent("sim7", device, simulated)
    assert needs_consent("p7", "sim://", True)  # a person's label: gated on sim:// too
    assert crs_study(*run_args(protocol, dataset, "sim7")).returncode == 0


# -- 4. copies outside the dataset -------------------------------------------------------------

def test_withdrawal_reaches_analysis_outputs_written_elsewhere(tmp_path):
    # the GLMM is not read: the plan's random intercept per participant is enough
    protocol, dataset, out = quick_analysis_protocol(tmp_path, repetitions=2), tmp_path / "ds", \
        tmp_path / "elsewhere" / "results"
    done = crs_study("dry-run", protocol, "--participants", 3, "--out", dataset,
                     "--responder", "random")
    assert done.returncode == 0, done.stderr
    analysed = crs_study("analyze", dataset, "--out", out, "--include-simulated")
    assert analysed.returncode == 0, analysed.stderr
    assert "sim02" in (out / "results.json").read_text()
    mine = out.parent / "notes.txt"  # the user's own file beside it stays
    mine.write_text("mine")
    listed = crs_study("consent", "withdraw", "--participant", "sim02", "--dataset", dataset,
                       "--dry-run")
    assert f"remove {out / 'results.json'}" in listed.stdout and (out / "results.json").exists()
    withdrawn = crs_study("consent", "withdraw", "--participant", "sim02", "--dataset", dataset)
    assert withdrawn.returncode == 0, withdrawn.stderr
    assert not (out / "results.json").exists() and not (out / "report.md").exists()
    assert "re-run crs-study analyze" in withdrawn.stdout
    assert mine.read_text() == "mine"
    assert "sim02" not in (dataset / ".crs-study-outputs.jsonl").read_text()


# -- 5. resume refuses a damaged session --------------------------------------------------------

def _damage(paths: SessionPaths, how: str) -> None:
    lines = paths.tsv.read_text().splitlines(keepends=True)
    if how == "tsv removed":
        paths.tsv.unlink()
    elif how == "tsv emptied":
        paths.tsv.write_text("")
    elif how == "cut in header":
        paths.tsv.write_text(lines[0][:20])
    elif how == "last row removed":
        paths.tsv.write_text("".join(lines[:-1]))
    elif how == "sidecar removed":
        paths.sidecar.unlink()
    elif how == "frame log removed":
        paths.frame_log.unlink()


@pytest.mark.parametrize("how, says", [
    ("tsv removed", "missing, but the sidecar"),
    ("tsv emptied", "holds empty, but the sidecar"),
    ("cut in header", "cut inside its header"),
    ("last row removed", "3 whole row"),
    ("sidecar removed", "sidecar .* is missing"),
    ("frame log removed", "frame log|missing, but the trial file"),
])
def test_resume_refuses_a_damaged_session_in_one_line(tmp_path, how, says):
    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "sim01", tmp_path / "ds", "sim://", 1, "random", "virtual")
    paused = run_session(spec, responder=PauseAt(plan_seed("tiny", "1.0.0", "sim01", 1), 4))
    assert (paused.status, paused.trials_completed) == ("interrupted", 4)
    paths = SessionPaths(spec.dataset, "sim01", 1)
    _damage(paths, how)
    before = tree(spec.dataset)
    with pytest.raises(DatasetError, match=says) as refused:
        run_session(spec)
    assert "\n" not in str(refused.value) and "backup" in str(refused.value)
    assert tree(spec.dataset) == before  # nothing changed


# -- 6. counterbalancing after a withdrawal ------------------------------------------------------

def test_the_next_participant_after_a_withdrawal_takes_a_new_counterbalance(tmp_path):
    protocol, dataset = tiny_protocol(tmp_path), tmp_path / "ds"
    for label in ("sim1", "sim2", "sim3"):
        run_session(SessionSpec(protocol, label, dataset, "sim://", 1, "random", "virtual"))
    from crs_study.consent import withdraw

    withdraw("sim2", [dataset])
    run_session(SessionSpec(protocol, "sim4", dataset, "sim://", 1, "random", "virtual"))
    assert Dataset(dataset).participants() == {"sim1": 0, "sim3": 2, "sim4": 3}


# -- 9. a board that stops reading ----------------------------------------------------------------

def test_a_board_that_stops_reading_stops_the_session(tmp_path):
    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "sim01", tmp_path / "ds", "sim://?hang_at=B@4", 1, "random",
                       "virtual")
    with pytest.raises(DeviceError, match=r"device fault at trial \d/8: .*B did not answer "
                                          "GET_BATTERY_VOLTAGE"):
        run_session(spec)
    meta = json.loads(SessionPaths(spec.dataset, "sim01", 1).sidecar.read_text())
    assert meta["Status"] == "interrupted" and "did not answer" in meta["Faults"][0]["message"]
    assert meta["Interruptions"][0]["Cause"] == "device-fault"
    faulted = meta["Faults"][0]["trial"]
    assert meta["TrialsCompleted"] == faulted  # the trial the board may have missed is not kept
    resumed = run_session(replace_url(spec, "sim://"))
    assert resumed.status == "complete"
    rows = resumed.tsv.read_text().splitlines()
    header = rows[0].split("\t")
    row = dict(zip(header, rows[faulted + 1].split("\t"), strict=True))
    assert (row["device_fault"], row["rerun"]) == ("1", "1")


def replace_url(spec: SessionSpec, url: str) -> SessionSpec:
    from dataclasses import replace

    return replace(spec, device_url=url)


# -- 10. dry-run workers die with their parent ------------------------------------------------

def _children(pid: int) -> set[int]:
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.add(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_sigkill_of_a_dry_run_ends_its_workers_and_its_pipeline(tmp_path):
    protocol = tiny_protocol(tmp_path, repetitions=6, iti=2.0)
    dataset = tmp_path / "ds"
    script = (f"{sys.executable} -m crs_study dry-run {protocol} --participants 6 --jobs 2 "
              f"--out {dataset} --responder random 2>&1 | tee {tmp_path / 'log'}")
    shell = subprocess.Popen(["bash", "-c", script], stdout=subprocess.DEVNULL,
                             start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        parent, workers = None, set()
        while time.monotonic() < deadline and len(workers) < 2:
            time.sleep(0.1)
            parent = next((p for p in _children(shell.pid)
                           if b"crs_study" in Path(f"/proc/{p}/cmdline").read_bytes()), None)
            workers = {w for w in _children(parent) if b"spawn" in
                       Path(f"/proc/{w}/cmdline").read_bytes()} if parent else set()
        assert parent and len(workers) >= 2, (parent, workers)
        os.kill(parent, signal.SIGKILL)
        shell.wait(timeout=15)  # tee sees the end of its input: the pipeline ends
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(map(_alive, workers)):
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)]
    finally:
        with_suppressed = [shell.pid, *workers] if "workers" in dir() else [shell.pid]
        for pid in with_suppressed:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        shell.wait()
    # the killed sessions resume: the same command finishes the dry-run
    again = crs_study("dry-run", protocol, "--participants", 6, "--jobs", 2, "--out", dataset,
                      "--responder", "random", timeout=300)
    assert again.returncode == 0, again.stderr


# -- 11. options ----------------------------------------------------------------------------

@pytest.mark.parametrize("args, says", [
    (["run", "pilot", "--participant", "sim01", "--device", "sim://", "--responder", "random",
      "--out", ""], "--out: expected a folder, got ''"),
    (["dry-run", "pilot", "--participants", "2", "--out", ""], "--out: expected a folder"),
    (["dry-run", "pilot", "--participants", "2147483648", "--out", "ds"],
     "--participants must be a whole number from 1 to 10000, got 2147483648"),
    (["dry-run", "pilot", "--participants", "0", "--out", "ds"], "from 1 to 10000, got 0"),
    (["analyze", "ds", "--out", ""], "--out: expected a folder"),
])
def test_absurd_options_are_one_line_errors_before_any_work(tmp_path, args, says):
    done = crs_study(*args, cwd=tmp_path, timeout=60)
    assert done.returncode == 2 and says in done.stderr and done.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []  # nothing written, not even in the current folder


# -- 12. the cause of every interruption, and reruns marked ------------------------------------

def test_each_interruption_says_why_and_reruns_are_marked(tmp_path):
    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "sim01", tmp_path / "ds", "sim://?disconnect_at=5", 1,
                       "random", "virtual")
    with pytest.raises(DeviceError):
        run_session(spec)
    spec = replace_url(spec, "sim://")
    run_session(spec, responder=PauseAt(plan_seed("tiny", "1.0.0", "sim01", 1), 5))
    done = run_session(spec)
    meta = json.loads(done.sidecar.read_text())
    faulted = meta["Faults"][0]["trial"]
    assert faulted < 5
    causes = [(i["Cause"], i["AtTrial"], i["TrialCut"]) for i in meta["Interruptions"]]
    assert causes == [("device-fault", faulted, True), ("signal", 5, True)]
    assert "port vanished" in meta["Interruptions"][0]["Detail"]
    rows = [line.split("\t") for line in done.tsv.read_text().splitlines()]
    column = rows[0].index("rerun")
    assert [int(r[0]) for r in rows[1:] if r[column] == "1"] == [faulted, 5]
    dictionary = json.loads((spec.dataset / "task-digitid_beh.json").read_text())
    assert "rerun" in dictionary and dictionary["rerun"]["Levels"]
