"""Injected faults fire once per session: the README's fault example, resumed once, runs to the
end; ``fault_period`` brings them back on every resumed run; ``--clock virtual`` is accepted
on virtual boards (``serial://lscsim://...``), which move no real servo."""

from __future__ import annotations

import json
import re

import pytest

from crs_study.cli import main
from crs_study.device import open_device
from crs_study.device.sim_options import SimOptions
from crs_study.errors import DeviceError
from crs_study.geometry.layout import load_layout
from crs_study.session.runner import simulated_url

README_FAULTS = "sim://?disconnect_at=3.5&garbage_rate=0.01&stall=A:3@2&brownout_at=5"


def sidecar(dataset, label="sim01"):
    path = dataset / f"sub-{label}/ses-1/beh/sub-{label}_ses-1_task-digitid_beh.json"
    return json.loads(path.read_text())


def test_the_readme_fault_example_runs_to_the_end_after_one_resume(tmp_path, capsys):
    readme = (__import__("pathlib").Path(__file__).parent.parent / "README.md").read_text()
    assert README_FAULTS in readme  # the example as the README prints it
    args = ["run", "pilot", "--participant", "sim01", "--device", README_FAULTS,
            "--out", str(tmp_path / "ds"), "--responder", "random"]
    assert main(args) == 2  # the disconnect, 3.5 s into the session
    err = capsys.readouterr().err
    # the disconnect, met by a send ("port vanished") or by the trial's heartbeat first
    assert re.search(r"device fault at trial \d+/26: .*(port vanished|did not answer)", err)
    assert "run the same command to resume" in err
    first = sidecar(tmp_path / "ds")
    assert first["Status"] == "interrupted" and len(first["Faults"]) == 1
    assert main(args) == 0  # the same command once more: to the end
    done = sidecar(tmp_path / "ds")
    assert done["Status"] == "complete" and len(done["Faults"]) == 1
    assert done["TrialsCompleted"] == done["TrialsPlanned"]


def test_a_fault_period_brings_the_faults_back_on_every_resumed_run(tmp_path, capsys):
    url = "sim://?disconnect_at=3.5&fault_period=2"
    args = ["run", "pilot", "--participant", "sim01", "--device", url,
            "--out", str(tmp_path / "ds"), "--responder", "random"]
    for faults in (1, 2, 3):
        assert main(args) == 2
        assert len(sidecar(tmp_path / "ds")["Faults"]) == faults
    capsys.readouterr()


def test_fault_times_on_a_resumed_opening():
    layout = load_layout("crs2d")
    once = SimOptions.parse("sim://?disconnect_at=3.5&brownout_at=5", layout, faults_met=1)
    assert once.fault_shift() is None
    first = SimOptions.parse("sim://?disconnect_at=3.5&brownout_at=5", layout)
    assert first.fault_shift() == 0.0
    again = SimOptions.parse("sim://?disconnect_at=3.5&brownout_at=5&fault_period=1", layout,
                             faults_met=2)
    assert again.fault_shift() == pytest.approx(1 - 3.5)  # the first 1 s after the open
    with open_device("sim://?disconnect_at=0.5", layout, faults_met=1) as device:
        device.clock.sleep(1.0)
        device.neutral()  # not injected again: no DeviceError
    with pytest.raises(DeviceError, match="fault_period"):
        SimOptions.parse("sim://?fault_period=0", layout)


def test_clock_virtual_is_accepted_on_virtual_boards(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CRS_STUDY_CONSENT_DIR", str(tmp_path / "consent"))
    assert simulated_url("serial://lscsim://A,lscsim://B")
    assert not simulated_url("serial:///dev/ttyUSB0,lscsim://B")
    assert main(["consent", "record", "--participant", "p01", "--form", "consent_form",
                 "--experimenter", "AB"]) == 0
    args = ["run", "pilot", "--participant", "p01", "--device",
            "serial://lscsim://A,lscsim://B", "--out", str(tmp_path / "ds"),
            "--responder", "random", "--clock", "virtual"]
    assert main(args) == 0
    assert sidecar(tmp_path / "ds", "p01")["Clock"] == "virtual"
    real = ["run", "pilot", "--participant", "p01", "--device", "serial:///dev/ttyUSB9",
            "--out", str(tmp_path / "ds2"), "--responder", "random", "--clock", "virtual"]
    assert main(real) == 2
    assert "moves real servos in real time" in capsys.readouterr().err
