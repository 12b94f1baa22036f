"""A session whose stored frames this software would render otherwise is not resumed.

The feed cap now leaves room for the boards' whole-us pulses and dead-band
(crs_study.rendering.feed_cap), so a CRS frame's setpoints differ from those of the software
before it (a dry-run of the default protocol: 3350 of 6853 frame-log rows), while the
fingerprints (protocol, plan, device file, bump paths) are the same. Resuming a session begun
before the change would mix two renderings in one session: the runner compares the stored
frames of the trials so far with what it renders for them and refuses in one line.
"""

from __future__ import annotations

import pytest
from _session_helpers import PauseAt, record_consent, tiny_protocol

from crs_study.dataset import read_frame_log
from crs_study.errors import SessionError
from crs_study.geometry.layout import load_layout
from crs_study.protocol import load_protocol
from crs_study.protocol.plan import make_plan, plan_seed
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.render import Renderer
from crs_study.session import trials
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec

#: The trial the first run is paused at: trials 0..3 stored, CRS ones among them.
PAUSE_AT = 4


def older_renderer(layout, condition, wire=None):
    """The renderer as it was before the wire's room: the cap at the longest shape alone."""
    return Renderer(layout, condition, wire=None)


@pytest.fixture
def paused_by_older_software(tmp_path, monkeypatch):
    """A tiny session paused at trial 4 by software that rendered with the older cap."""
    record_consent("p01")  # a person's label passes the consent gate on sim:// too
    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "p01", tmp_path / "dataset", "sim://", 1, "random", "virtual",
                       counterbalance=1)
    with monkeypatch.context() as patch:
        patch.setattr(trials, "Renderer", older_renderer)
        patch.setattr(trials, "_trial_frames", {})
        paused = run_session(spec, responder=PauseAt(plan_seed("tiny", "1.0.0", "p01", 1),
                                                     PAUSE_AT))
    assert (paused.status, paused.trials_completed) == ("interrupted", PAUSE_AT)
    monkeypatch.setattr(trials, "_trial_frames", {})  # this software's frames from here on
    return spec


def test_a_session_rendered_otherwise_is_refused_in_one_line(paused_by_older_software):
    spec = paused_by_older_software
    with pytest.raises(SessionError, match=r"frames\.tsv\.gz: cannot resume: trial \d+ \(crs, "
                                           r"\d\) was shown with other setpoints than "
                                           r"this software renders") as caught:
        run_session(spec)
    assert "\n" not in str(caught.value)
    # nothing was written by the refused run: the session is still the paused one
    sidecar = spec.dataset / "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.json"
    assert '"Status": "interrupted"' in sidecar.read_text(encoding="utf-8")


def test_the_same_software_resumes_its_own_session(tmp_path, monkeypatch):
    monkeypatch.setattr(trials, "_trial_frames", {})
    record_consent("p01")
    spec = SessionSpec(tiny_protocol(tmp_path), "p01", tmp_path / "dataset", "sim://", 1,
                       "random", "virtual", counterbalance=1)
    paused = run_session(spec, responder=PauseAt(plan_seed("tiny", "1.0.0", "p01", 1),
                                                 PAUSE_AT))
    assert paused.trials_completed == PAUSE_AT
    finished = run_session(spec)
    assert (finished.status, finished.trials_completed) == ("complete", 8)


def _stimulus_frames(log) -> dict[str, list[str]]:
    """The stimulus frames of a frame log per trial, as setpoint text (the resume check's)."""
    stored: dict[str, list[str]] = {}
    for line in read_frame_log(log):
        if line["kind"] == "stimulus":
            values = [v for k, v in line.items() if k.startswith("a") and k[1:].isdigit()]
            stored.setdefault(line["trial"], []).append("\t".join(values))
    return stored


#: A dead-band wider than the default: the feed cap's room and rest floor change with it
#: (0.34 mm on the default protocol's CRS digits at 30 us against 1 us).
WIDE_DEADBAND_US = 30


def test_a_session_renders_for_its_devices_own_dead_band(tmp_path, monkeypatch):
    """The boards may hold a pulse up to the dead-band away from the one commanded, so the
    cap leaves room for the device's own dead-band (sim://?deadband_us=, a serial device's
    option), not the default's, and a resume on a device with another dead-band is refused
    (it would mix two renderings)."""
    monkeypatch.setattr(trials, "_trial_frames", {})
    record_consent("p01")
    url = f"sim://?deadband_us={WIDE_DEADBAND_US}"
    path = tiny_protocol(tmp_path)
    spec = SessionSpec(path, "p01", tmp_path / "dataset", url, 1, "random", "virtual",
                       counterbalance=1)
    paused = run_session(spec, responder=PauseAt(plan_seed("tiny", "1.0.0", "p01", 1),
                                                 PAUSE_AT))
    assert paused.trials_completed == PAUSE_AT
    protocol = load_protocol(path)
    layout = load_layout("crs2d")
    plan = make_plan(protocol, "p01", 1, 1)
    log = tmp_path / "dataset/sourcedata/sub-p01/ses-1/sub-p01_ses-1_task-digitid_frames.tsv.gz"
    stored = _stimulus_frames(log)
    wide = trials.TrialFrames(protocol, layout, WireSlack(WIDE_DEADBAND_US))
    default = trials.TrialFrames(protocol, layout)
    crs_differs = False
    for trial in plan.trials[:PAUSE_AT]:
        shown = stored[str(trial.index)]
        assert shown == wide.setpoint_text(trial.symbol, trial.condition)
        crs_differs |= shown != default.setpoint_text(trial.symbol, trial.condition)
    assert crs_differs  # the test can tell the two renderings apart
    with pytest.raises(SessionError, match="the device's dead-band"):
        run_session(SessionSpec(path, "p01", tmp_path / "dataset", "sim://", 1, "random",
                                "virtual", counterbalance=1))
    finished = run_session(spec)
    assert (finished.status, finished.trials_completed) == ("complete", 8)


def test_run_takes_the_device_options_from_the_command_line(tmp_path, monkeypatch, capsys):
    """``run --deadband-us`` reaches the device (and so the renderer), as ``device check``'s
    and ``live``'s do; a serial-only option on sim:// is refused before anything runs."""
    from crs_study.cli import main

    monkeypatch.setattr(trials, "_trial_frames", {})
    path = tiny_protocol(tmp_path)
    argv = ["run", str(path), "--participant", "sim01", "--device", "sim://", "--out",
            str(tmp_path / "ds"), "--responder", "random", "--clock", "virtual", "--json"]
    assert main([*argv, "--deadband-us", str(WIDE_DEADBAND_US)]) == 0
    log = tmp_path / "ds/sourcedata/sub-sim01/ses-1/sub-sim01_ses-1_task-digitid_frames.tsv.gz"
    protocol = load_protocol(path)
    wide = trials.TrialFrames(protocol, load_layout("crs2d"), WireSlack(WIDE_DEADBAND_US))
    default = trials.TrialFrames(protocol, load_layout("crs2d"))
    plan = make_plan(protocol, "sim01", 1, 0)
    stored = _stimulus_frames(log)
    assert len(stored) == len(plan.trials)
    differs = False
    for index, shown in stored.items():
        trial = plan.trials[int(index)]
        assert shown == wide.setpoint_text(trial.symbol, trial.condition)
        differs |= shown != default.setpoint_text(trial.symbol, trial.condition)
    assert differs
    capsys.readouterr()
    assert main([*argv, "--session", "2", "--no-battery-check"]) == 2
    err = capsys.readouterr().err
    assert "--no-battery-check: for serial:// devices only" in err and err.count("\n") == 1
    assert not (tmp_path / "ds/sub-sim01/ses-2").exists()
