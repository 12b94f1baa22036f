"""The session runner on a fake device: trial flow, durability, resume, faults, pauses."""

from __future__ import annotations

import csv
import hashlib
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from _session_helpers import FakeDevice, assert_same_but_reruns, tiny_protocol

import crs_study.session.runner as runner_module
from crs_study.dataset import read_frame_log
from crs_study.errors import ConsentError, CrsStudyError, DeviceError, SessionError
from crs_study.protocol import load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.session.dry_runs import dry_run, simulated_labels
from crs_study.session.responders.base import PauseInPlace, Responder, Response
from crs_study.session.responders.random import RandomResponder
from crs_study.session.runner import run_session, seed_check
from crs_study.session.spec import SessionSpec
from crs_study.session.trials import ceil_ms


@pytest.fixture
def devices(monkeypatch):
    """Every device the runner opens is a FakeDevice; options set per test."""
    made: list[FakeDevice] = []
    options: dict = {}

    def fake_open(url, layout, clock=None, **kw):
        device = FakeDevice(layout, clock, **options)
        made.append(device)
        return device

    monkeypatch.setattr(runner_module, "open_device", fake_open)  # the runner's name for it
    made_options = options
    return made, made_options


def read_rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


class Recorder(RandomResponder):
    """A random responder that remembers prompts and can pause at a chosen trial."""

    def __init__(self, seed, pause_at=None):
        super().__init__(seed)
        self.prompts, self.records, self.pause_at = [], [], pause_at

    def prompt(self, text, clock, rest_s=None):
        self.prompts.append(text)

    def respond(self, trial, stimulus, clock, time_limit_s):
        if trial.index == self.pause_at:
            raise KeyboardInterrupt
        self.records.append(stimulus)
        return super().respond(trial, stimulus, clock, time_limit_s)


def plan_seed_of(participant="sim01", session=1):
    from crs_study.protocol.plan import plan_seed

    return plan_seed("tiny", "1.0.0", participant, session)


def spec_for(tmp_path, protocol, name="ds", **kw):
    base = dict(protocol=protocol, participant="sim01", dataset=tmp_path / name,
                device_url="sim://", responder="random", clock="virtual")
    base.update(kw)
    return SessionSpec(**base)


def test_a_session_runs_and_is_stored(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    responder = Recorder(seed=5)
    notes = []
    result = run_session(spec_for(tmp_path, protocol), responder=responder,
                         progress=notes.append)
    assert result.status == "complete" and result.trials_completed == 8 == result.trials_run
    rows = read_rows(result.tsv)
    assert [int(r["trial_index"]) for r in rows] == list(range(8))
    assert notes[-1].endswith("trial 8/8")
    meta = json.loads(result.sidecar.read_text())
    assert meta["Status"] == "complete" and meta["TrialsCompleted"] == 8
    assert meta["TrialsSha256"] == hashlib.sha256(result.tsv.read_bytes()).hexdigest()
    assert meta["Protocol"] == protocol.read_text()
    assert meta["ProtocolSha256"] == hashlib.sha256(protocol.read_bytes()).hexdigest()
    assert "[geometry]" in meta["DeviceFile"] and meta["ConsentFormVersion"] == "1.0"
    assert len(responder.prompts) == 2  # one per condition block
    device = devices[0][0]
    frames = read_frame_log(result.tsv.parents[3] / "sourcedata/sub-sim01/ses-1"
                            / "sub-sim01_ses-1_task-digitid_frames.tsv.gz")
    for row, record in zip(rows, responder.records, strict=True):
        n = int(row["frames"])
        duration = float(row["stimulus_duration"])
        assert math.isclose(duration, n / 15.0, abs_tol=1e-6)
        assert record.setpoints.shape == (n, 37) and "true digit" not in repr(record)
        assert math.isclose(float(row["response_time_from_offset"]),
                            float(row["response_time"]) - duration, abs_tol=2e-6)
        assert row["correct"] == str(int(row["response"] == row["digit"]))
        assert float(row["trial_end"]) * 1000 == pytest.approx(
            round(float(row["trial_end"]) * 1000), abs=1e-6)
        log = [r for r in frames if r["trial"] == row["trial_index"]]
        assert [r["kind"] for r in log] == ["stimulus"] * n + ["neutral"]
        due = np.array([float(r["due"]) for r in log[:n]])
        assert np.allclose(np.diff(due), 1 / 15, atol=2e-6)  # the steady frame rate
    onsets = [float(r["onset"]) for r in rows]
    ends = [float(r["trial_end"]) for r in rows]
    assert all(e <= o for e, o in zip(ends[:-1], onsets[1:], strict=True))  # one after another
    assert device.closed and np.all(device.current == 0)  # left neutral


class _StartRecorder(RandomResponder):
    """A random responder noting when each trial starts (just before its first frame)."""

    def __init__(self, seed, events):
        super().__init__(seed)
        self.events = events

    def begin_trial(self, trial, now, clock):
        self.events.append(("start", trial.index))
        super().begin_trial(trial, now, clock)


def _record_tsv_fsyncs(monkeypatch, tsv, events):
    """Wrap os.fsync: each fsync of the session's _beh.tsv is noted with the number of rows
    the file holds at that moment (the rows written, and now made durable)."""
    import os

    real_fsync = os.fsync

    def fsync(fd):
        if tsv.exists() and os.path.samestat(os.fstat(fd), os.stat(tsv)):
            events.append(("fsync", tsv.read_bytes().count(b"\n") - 1))  # minus the header
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)


def test_each_row_is_fsynced_before_the_next_trial_starts(tmp_path, devices, monkeypatch):
    """Each completed trial is appended to _beh.tsv and made durable (written,
    then fsynced) before the next trial starts. The order of fsyncs of the TSV and trial
    starts is recorded; before trial k starts, the TSV was fsynced holding its k rows."""
    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    events: list[tuple[str, int]] = []
    tsv = spec.dataset / "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.tsv"
    _record_tsv_fsyncs(monkeypatch, tsv, events)
    result = run_session(spec, responder=_StartRecorder(5, events))
    assert result.status == "complete" and result.trials_completed == 8
    starts = [i for i, (kind, _) in enumerate(events) if kind == "start"]
    assert [events[i][1] for i in starts] == list(range(8))
    for k, at in enumerate(starts):
        synced = [n for kind, n in events[:at] if kind == "fsync"]
        assert synced and synced[-1] == k, (k, events[:at])  # rows 0..k-1 durable, no more
    assert events[-1] == ("fsync", 8)  # and the last row before the session ends


def test_the_durability_order_test_sees_a_missing_fsync(tmp_path, devices, monkeypatch):
    """The check above fails when rows are not fsynced per trial: a dry-run's store
    (durable=False) syncs only when the session stops."""
    spec = spec_for(tmp_path, tiny_protocol(tmp_path), durable=False)
    events: list[tuple[str, int]] = []
    tsv = spec.dataset / "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.tsv"
    _record_tsv_fsyncs(monkeypatch, tsv, events)
    run_session(spec, responder=_StartRecorder(5, events))
    synced = [n for kind, n in events if kind == "fsync"]
    assert synced[-1] == 8 and not any(0 < n < 8 for n in synced)


def test_a_complete_session_is_never_rewritten(tmp_path, devices):
    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    first = run_session(spec)
    before = {p: p.read_bytes() for p in spec.dataset.rglob("*") if p.is_file()}
    again = run_session(spec)
    assert again.status == "already-complete" and "--session N" in again.message
    after = {p: p.read_bytes() for p in spec.dataset.rglob("*") if p.is_file()}
    assert after == before
    second = run_session(spec_for(tmp_path, spec.protocol, session=2))
    assert second.status == "complete" and second.tsv != first.tsv


def test_pause_then_resume_equals_uninterrupted(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    whole = run_session(spec_for(tmp_path, protocol, "whole"))
    spec = spec_for(tmp_path, protocol, "parts")
    paused = run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=3))
    assert paused.status == "interrupted" and paused.trials_completed == 3
    assert json.loads(paused.sidecar.read_text())["Status"] == "interrupted"
    assert np.all(devices[0][-1].current == 0)  # the display was put to rest
    resumed = run_session(spec)
    assert resumed.status == "complete" and resumed.trials_run == 5
    # paused at trial 3's response: felt once already, so its rerun says rerun = 1
    assert_same_but_reruns(resumed.tsv, whole.tsv, cut={3})
    meta = json.loads(resumed.sidecar.read_text())
    assert len(meta["Resumes"]) == 1 and meta["Status"] == "complete"


def test_device_fault_interrupts_and_resumes(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    spec = spec_for(tmp_path, protocol)
    devices[1]["fail_at"] = 40  # during trial 2 or 3
    with pytest.raises(DeviceError, match=r"^device fault at trial \d/8: fake port vanished; "):
        run_session(spec)
    meta = json.loads(spec.dataset.joinpath(
        "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.json").read_text())
    assert meta["Status"] == "interrupted" and meta["Faults"][0]["message"] == \
        "fake port vanished"
    faulted = meta["Faults"][0]["trial"]
    assert meta["TrialsCompleted"] == faulted
    devices[1]["fail_at"] = None
    result = run_session(spec)
    rows = read_rows(result.tsv)
    assert len(rows) == 8
    assert [r["device_fault"] for r in rows] == ["1" if i == faulted else "0" for i in range(8)]


def test_device_missing_at_open_is_not_a_trial_fault(tmp_path, devices, monkeypatch):
    def refuse(self):
        raise DeviceError("no such port /dev/ttyUSB9")

    monkeypatch.setattr(FakeDevice, "open", refuse)
    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    with pytest.raises(DeviceError, match=r"^device fault before trial 1/8: no such port"):
        run_session(spec)
    meta = json.loads(spec.dataset.joinpath(
        "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.json").read_text())
    assert meta["Status"] == "interrupted" and meta["Faults"] == []


def test_resume_refuses_a_changed_protocol(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    spec = spec_for(tmp_path, protocol)
    run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=2))
    protocol.write_text(protocol.read_text().replace("inter_trial_interval_s = 0.5",
                                                     "inter_trial_interval_s = 0.6"))
    with pytest.raises(SessionError, match="cannot resume: the protocol file differs"):
        run_session(spec)
    with pytest.raises(SessionError, match="protocol file differs"):
        seed_check(spec)


def test_resume_refuses_software_that_draws_the_digits_differently(tmp_path, devices,
                                                                   monkeypatch):
    # The protocol file is unchanged, but the bump paths are not (as when an upgrade rescaled
    # the strokes mid-study): finishing the session would mix two stimuli in one session.
    import crs_study.session.resume as resume_module

    protocol = tiny_protocol(tmp_path)
    spec = spec_for(tmp_path, protocol)
    run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=2))
    sidecar = json.loads(spec.dataset.joinpath(
        "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.json").read_text())
    assert len(sidecar["StimulusSha256"]) == 64
    drawn = resume_module.make_stimulus

    def wider(protocol, layout, digit, level=None):
        original = drawn(protocol, layout, digit, level)
        return replace(original, centres_mm=original.centres_mm * [1.01, 1.0])

    monkeypatch.setattr(resume_module, "make_stimulus", wider)  # what the fingerprint draws
    with pytest.raises(SessionError, match=r"cannot resume: the stimulus \(the bump paths"):
        run_session(spec)


def _paused_before_the_stimulus_fingerprint(tmp_path):
    """A session paused at trial 3 whose sidecar lacks StimulusSha256 (older software's)."""
    protocol = tiny_protocol(tmp_path)
    spec = spec_for(tmp_path, protocol)
    run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=2))
    path = spec.dataset.joinpath("sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh.json")
    sidecar = json.loads(path.read_text())
    del sidecar["StimulusSha256"]
    path.write_text(json.dumps(sidecar))
    return spec, path


def test_a_session_begun_before_the_stimulus_fingerprint_resumes_without_one(tmp_path,
                                                                              devices):
    # Its first trials were drawn by older software: the sidecar must not vouch for them.
    spec, path = _paused_before_the_stimulus_fingerprint(tmp_path)
    run_session(spec)
    sidecar = json.loads(path.read_text())
    assert sidecar["Status"] == "complete" and sidecar["StimulusSha256"] is None


def test_a_second_resume_does_not_vouch_for_older_trials_either(tmp_path, devices):
    # Once resumed, such a sidecar holds "StimulusSha256": null; the next resume used to take
    # the key's presence for a fingerprint and record one for trials older software drew.
    spec, path = _paused_before_the_stimulus_fingerprint(tmp_path)
    run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=4))
    assert json.loads(path.read_text())["StimulusSha256"] is None
    assert run_session(spec).status == "complete"
    sidecar = json.loads(path.read_text())
    assert sidecar["StimulusSha256"] is None and len(sidecar["Resumes"]) == 2


def test_resume_cuts_a_torn_row(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    whole = run_session(spec_for(tmp_path, protocol, "whole"))
    spec = spec_for(tmp_path, protocol, "parts")
    paused = run_session(spec, responder=Recorder(seed=plan_seed_of(), pause_at=4))
    with open(paused.tsv, "ab") as handle:
        handle.write(b"4\ttest\t1\tcrs\t0\t7\t3")  # killed in the middle of a write
    run_session(spec)
    assert_same_but_reruns(paused.tsv, whole.tsv, cut={4})
    torn = list((spec.dataset / "sourcedata/sub-sim01/ses-1").glob("*torn*.bin"))
    assert [t.read_bytes() for t in torn] == [b"4\ttest\t1\tcrs\t0\t7\t3"]


def test_timeouts_and_answers_during_the_stimulus(tmp_path, devices):
    protocol = tiny_protocol(tmp_path, time_limit=2.0)
    script = tmp_path / "answers.txt"
    script.write_text("digit\trt\nn/a\n4\t-0.2\n7\t5.0\n" + "1\n" * 5)
    result = run_session(spec_for(tmp_path, protocol, responder=f"scripted:{script}"))
    rows = read_rows(result.tsv)
    assert rows[0]["response"] == "n/a" and rows[0]["timed_out"] == "1"
    assert rows[0]["correct"] == "n/a"
    assert float(rows[0]["response_time_from_offset"]) == pytest.approx(2.0)
    assert float(rows[1]["response_time_from_offset"]) == pytest.approx(-0.2)
    assert rows[2]["timed_out"] == "1"  # 5 s after offset is beyond the 2 s limit
    assert rows[3]["response"] == "1" and rows[3]["responder"] == "scripted"


def test_late_frames_are_counted(tmp_path, devices, monkeypatch):
    def slow_send(self, setpoints_mm, move_ms=None):
        report = original(self, setpoints_mm)
        if len(self.sent) % 5 == 0:
            self.clock.advance(0.2)  # a hiccup of three frame periods
        return report

    original = FakeDevice.send
    monkeypatch.setattr(FakeDevice, "send", slow_send)
    result = run_session(spec_for(tmp_path, tiny_protocol(tmp_path)))
    rows = read_rows(result.tsv)
    assert sum(int(r["late_frames"]) for r in rows) == result.late_frames > 0


def test_keypad_needs_the_real_clock(tmp_path, devices):
    with pytest.raises(SessionError, match="keypad responder needs --clock real"):
        run_session(spec_for(tmp_path, tiny_protocol(tmp_path), responder="keypad"))


def test_real_devices_need_consent(tmp_path, devices):
    spec = spec_for(tmp_path, tiny_protocol(tmp_path), device_url="serial:///dev/null",
                    consent_register=tmp_path / "register", clock="real", participant="p01")
    with pytest.raises(ConsentError, match="no consent record for participant 'p01'"):
        run_session(spec)
    assert not (spec.dataset / "sub-p01/ses-1/beh").exists()


def test_a_virtual_clock_never_drives_a_real_device(tmp_path, devices):
    """Session time faster than the wall on real servos would store fictional data."""
    spec = spec_for(tmp_path, tiny_protocol(tmp_path), device_url="serial:///dev/null")
    with pytest.raises(SessionError, match="--clock virtual needs the simulated device"):
        run_session(spec)
    assert not spec.dataset.exists()


@pytest.mark.parametrize("responder, match", [
    pytest.param("keypad", "needs --clock real", id="keypad-on-virtual-clock"),
    pytest.param("scripted:no-such-file.txt", "no-such-file", id="missing-script"),
])
def test_a_run_refused_at_the_start_writes_nothing(tmp_path, devices, responder, match):
    """A typo must not take a counterbalance slot or leave an empty session behind."""
    protocol = tiny_protocol(tmp_path)
    run_session(spec_for(tmp_path, protocol, participant="sim1"))
    before = (tmp_path / "ds" / "participants.tsv").read_bytes()
    with pytest.raises(CrsStudyError, match=match):
        run_session(spec_for(tmp_path, protocol, participant="sim2", responder=responder))
    assert (tmp_path / "ds" / "participants.tsv").read_bytes() == before
    assert not (tmp_path / "ds" / "sub-sim2").exists()


def test_keypad_without_a_terminal_writes_nothing(tmp_path, devices, monkeypatch):
    import io

    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    spec = spec_for(tmp_path, tiny_protocol(tmp_path), responder="keypad", clock="real")
    with pytest.raises(SessionError, match="needs a terminal"):
        run_session(spec)
    assert not spec.dataset.exists()


@pytest.mark.parametrize("change, match", [
    pytest.param(dict(responder="observer"), "responder 'random', now 'observer'", id="responder"),
    pytest.param(dict(device_url="serial:///dev/null", clock="real", responder="random"),
                 "clock 'virtual', now 'real'", id="clock-and-device"),
])
def test_a_session_is_finished_as_it_began(tmp_path, devices, change, match):
    """Rows by a guessing simulation must not be followed by rows from another kind of
    responder, device or clock under the same session."""
    protocol = tiny_protocol(tmp_path)
    register = tmp_path / "register"  # a person's label: every run passes the consent gate
    from crs_study.consent import Register, read_form
    from crs_study.paths import shipped_file

    Register(register).record(read_form(shipped_file("consent/consent_form.md")), "AB", "p01")
    person = dict(participant="p01", consent_register=register)
    devices[1]["fail_at"] = 40  # during trial 2 or 3
    with pytest.raises(DeviceError):
        run_session(spec_for(tmp_path, protocol, **person))
    devices[1].pop("fail_at")
    with pytest.raises(SessionError, match=f"cannot resume.*{match}"):
        run_session(spec_for(tmp_path, protocol, **person, **change))
    assert run_session(spec_for(tmp_path, protocol, **person)).status == "complete"


def test_a_resumed_session_prompts_the_person_first(tmp_path, devices):
    """After a pause mid-block the experimenter sees where the session stands and the
    block's prompt again (the skeleton may have been taken off meanwhile)."""
    from crs_study.consent import Register, read_form
    from crs_study.paths import shipped_file

    protocol = tiny_protocol(tmp_path)
    register = tmp_path / "register"  # a person answers: the consent gate on sim:// too
    Register(register).record(read_form(shipped_file("consent/consent_form.md")), "AB", "p01")
    person_spec = dict(participant="p01", consent_register=register)
    devices[1]["fail_at"] = 40  # during trial 2 or 3
    with pytest.raises(DeviceError):
        run_session(spec_for(tmp_path, protocol, **person_spec))
    devices[1].pop("fail_at")

    class Person(Recorder):
        name = "random"  # the same kind as the session began with
        simulated = False

        def prompt(self, text, clock, rest_s=None):
            self.prompts.append(text)

    person = Person(seed=1)
    person.prompts = []
    run_session(spec_for(tmp_path, protocol, **person_spec), responder=person)
    assert person.prompts[0].startswith("Resuming at trial ")
    assert "skeleton" in person.prompts[0]  # the pilot's block prompts name the skeleton


def test_simulated_participants_rest_through_breaks(tmp_path, devices):
    """A dry-run's session time counts the protocol's breaks, as the plan's estimate does."""
    protocol = tiny_protocol(tmp_path, break_every=2)
    text = protocol.read_text().replace("break_duration_s = 0.0", "break_duration_s = 7.0")
    protocol.write_text(text)
    rows = read_rows(run_session(spec_for(tmp_path, protocol)).tsv)
    plan = [t for t in make_plan(load_protocol(protocol), "sim01", 1, 0).trials]
    for row, trial in zip(rows[1:], plan[1:], strict=True):
        if trial.break_before:
            previous = rows[int(row["trial_index"]) - 1]
            assert float(row["onset"]) - float(previous["trial_end"]) >= 7.0 - 1e-9


def test_a_dry_run_has_no_person_at_the_keypad(tmp_path):
    with pytest.raises(SessionError, match="no person at the keypad"):
        dry_run(tiny_protocol(tmp_path), 2, tmp_path / "ds", responder="keypad")
    assert not (tmp_path / "ds").exists()


def test_counterbalance_follows_arrival(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    first = run_session(spec_for(tmp_path, protocol, participant="sim1"))
    second = run_session(spec_for(tmp_path, protocol, participant="sim2"))
    order = [read_rows(r.tsv)[0]["condition"] for r in (first, second)]
    assert order == ["pixel-only", "crs"]  # "alternate": arrival 0 then 1
    report = seed_check(spec_for(tmp_path, protocol, participant="sim2"))
    assert report["counterbalance"] == 1 and report["stored"].startswith("complete")


def test_random_responder_is_resume_safe():
    class Trial:
        index = 3

    class Stim:
        symbol_choices = (1, 4, 7)
        duration_s, onset_time = 1.0, 0.0

    from crs_study.clock import VirtualClock

    answers = [RandomResponder(9).respond(Trial, Stim, VirtualClock(), None) for _ in range(2)]
    assert answers[0] == answers[1]


def test_ceil_ms_is_exact():
    assert ceil_ms(1.2341) == 1.235 and ceil_ms(2.0) == 2.0 and ceil_ms(0.0004) == 0.001


def test_simulated_labels():
    assert simulated_labels(3) == ["sim01", "sim02", "sim03"]
    assert simulated_labels(100)[0] == "sim001"
    with pytest.raises(SessionError, match="--participants must be"):
        simulated_labels(0)


def test_dry_run_counterbalances(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    notes = []
    results = dry_run(protocol, 3, tmp_path / "ds", responder="random", progress=notes.append)
    assert [r.participant for r in results] == ["sim01", "sim02", "sim03"]
    assert notes[-1].startswith("dry-run: 3/3 participants")
    lines = (tmp_path / "ds/participants.tsv").read_text().splitlines()
    assert lines[1:] == ["sub-sim01\t0", "sub-sim02\t1", "sub-sim03\t2"]
    with pytest.raises(SessionError, match="uses the simulated device"):
        dry_run(protocol, 1, tmp_path / "x", device_url="serial:///dev/ttyUSB0")


class _Fixed(Responder):
    name = "fixed"

    def respond(self, trial, stimulus, clock, time_limit_s):
        return Response(stimulus.symbol_choices[0], stimulus.duration_s + 0.1)


def test_feedback_only_on_practice(tmp_path, devices):
    calls = []

    class Feedback(_Fixed):
        def feedback(self, trial, response, correct):
            calls.append((trial.trial_type, correct))

    run_session(spec_for(tmp_path, tiny_protocol(tmp_path)), responder=Feedback())
    assert [c[0] for c in calls] == ["practice", "practice"]


# --- review: completed sessions, interrupts while storing, full disks ------------------------

@pytest.mark.parametrize("damage", ["rows removed", "torn tail added", "cell edited"])
def test_a_damaged_complete_session_is_refused_and_left_alone(tmp_path, devices, damage):
    """A rerun used to 'resume' a complete session whose rows were cut, appending new trials
    (with whatever responder the rerun named) to a finished session, and to cut a torn tail
    out of it. A completed session is now checked read-only and never rewritten."""
    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    result = run_session(spec)
    data = result.tsv.read_bytes()
    lines = data.splitlines(keepends=True)
    damaged = {"rows removed": b"".join(lines[:-2]),
               "torn tail added": data + b"8\ttest\t1",
               "cell edited": data.replace(b"\tcrs\t", b"\tCRS\t", 1)}[damage]
    result.tsv.write_bytes(damaged)
    before = {p: p.read_bytes() for p in spec.dataset.rglob("*") if p.is_file()}
    with pytest.raises(SessionError, match="marked complete.*never rewritten"):
        run_session(spec)
    after = {p: p.read_bytes() for p in spec.dataset.rglob("*") if p.is_file()}
    assert after == before


def test_ctrl_c_while_a_trial_is_stored_keeps_row_and_sidecar_together(tmp_path, devices,
                                                                         monkeypatch):
    """Ctrl-C between the row's append and the sidecar used to leave the sidecar's
    TrialsSha256/TrialsCompleted disagreeing with the TSV (a false tamper warning). The
    storing of a trial is now held whole and the pause comes after it."""
    import os
    import signal

    from crs_study.dataset import SessionStore

    real_append = SessionStore.append_row

    def append_then_interrupt(self, row):
        if row["trial_index"] == 3:
            os.kill(os.getpid(), signal.SIGINT)  # arrives between the row and the sidecar
        real_append(self, row)

    monkeypatch.setattr(SessionStore, "append_row", append_then_interrupt)
    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    paused = run_session(spec)
    assert paused.status == "interrupted" and paused.trials_completed == 4
    meta = json.loads(paused.sidecar.read_text())
    assert meta["TrialsCompleted"] == 4 == len(read_rows(paused.tsv))
    assert meta["TrialsSha256"] == hashlib.sha256(paused.tsv.read_bytes()).hexdigest()
    monkeypatch.setattr(SessionStore, "append_row", real_append)
    whole = run_session(spec_for(tmp_path, spec.protocol, "whole"))
    assert run_session(spec).status == "complete"
    assert paused.tsv.read_bytes() == whole.tsv.read_bytes()


def test_disk_full_mid_session_is_one_line_and_loses_nothing(tmp_path, devices, monkeypatch):
    """ENOSPC on a row's append: one-line DatasetError naming the file, the stored rows
    whole, the half-written row cut back, and the same command resumes exactly."""
    import errno

    import crs_study._files as files
    from crs_study.errors import DatasetError

    spec = spec_for(tmp_path, tiny_protocol(tmp_path))
    tsv_name = "sub-sim01_ses-1_task-digitid_beh.tsv"
    real_write = files.os.write
    calls = {"rows": 0}

    def full_disk(fd, data):
        if os_path_of(fd).endswith(tsv_name):
            calls["rows"] += 1
            if calls["rows"] == 6:  # header + 4 rows fit, the 5th is cut short
                real_write(fd, bytes(data)[:7])
                raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    def os_path_of(fd):
        import os
        return os.readlink(f"/proc/self/fd/{fd}")

    monkeypatch.setattr(files.os, "write", full_disk)
    with pytest.raises(DatasetError, match=rf"{tsv_name}: cannot append to: No space left"
                       ) as raised:
        run_session(spec)
    # ... and says the session is paused and how to go on
    assert "the session is paused at trial 5/" in str(raised.value)
    assert str(raised.value).endswith("run the same command to resume")
    monkeypatch.setattr(files.os, "write", real_write)
    tsv = spec.dataset / "sub-sim01/ses-1/beh" / tsv_name
    assert tsv.read_bytes().endswith(b"\n") and len(read_rows(tsv)) == 4
    whole = run_session(spec_for(tmp_path, spec.protocol, "whole"))
    assert run_session(spec).status == "complete"
    # trial 4 was shown and answered before its row met the full disk: rerun = 1
    assert_same_but_reruns(tsv, whole.tsv, cut={4})


def test_participants_arriving_together_get_their_own_counterbalance(tmp_path, devices,
                                                                     monkeypatch):
    """The order of arrival used to be read without the dataset lock and written back as
    given: a second runner registering in between left both participants on index 0."""
    import crs_study.session.runner as runner
    from crs_study.dataset import Dataset

    real_prepare = runner.prepare

    def prepare_then_another_arrives(spec):
        prepared = real_prepare(spec)
        Dataset(spec.dataset).register_participant("other")  # the other runner, in between
        return prepared

    monkeypatch.setattr(runner, "prepare", prepare_then_another_arrives)
    spec = spec_for(tmp_path, tiny_protocol(tmp_path), participant="sim02")
    result = run_session(spec)
    assert Dataset(spec.dataset).participants() == {"other": 0, "sim02": 1}
    assert json.loads(result.sidecar.read_text())["Counterbalance"] == 1


class PausesInPlace(Recorder):
    """Pauses in place (the keypad's p) once while trial 1 waits for its answer and once
    during trial 3's stimulus (at its third frame); counts the pauses."""

    def __init__(self, seed):
        super().__init__(seed)
        self.pauses, self.polls, self.asked = 0, 0, set()

    def begin_trial(self, trial, onset_time, clock):
        self.current, self.polls = trial.index, 0

    def poll(self):
        self.polls += 1
        if self.current == 3 and self.polls == 3 and 3 not in self.asked:
            self.asked.add(3)
            raise PauseInPlace("p")

    def pause(self, clock):
        self.pauses += 1

    def respond(self, trial, stimulus, clock, time_limit_s):
        if trial.index == 1 and 1 not in self.asked:
            self.asked.add(1)
            raise PauseInPlace("p")
        return super().respond(trial, stimulus, clock, time_limit_s)


def test_a_pause_in_place_plays_the_trial_again_and_goes_on(tmp_path, devices):
    protocol = tiny_protocol(tmp_path)
    responder = PausesInPlace(seed=5)
    result = run_session(spec_for(tmp_path, protocol), responder=responder)
    assert result.status == "complete" and responder.pauses == 2
    rows = read_rows(result.tsv)
    assert [int(r["trial_index"]) for r in rows] == list(range(8))  # nothing lost or doubled
    assert [r["rerun"] for r in rows] == ["0", "1", "0", "1", "0", "0", "0", "0"]
    # paused during a stimulus: the display went neutral before the pause, at once
    # (its first two frames, then neutral, then the same stimulus from its first frame)
    sent = devices[0][0].sent
    flat = [bool(np.array_equal(s, devices[0][0].layout.neutral_setpoints())) for s in sent]
    cut = [i for i in range(3, len(sent) - 1) if flat[i] and flat[i - 3]
           and not flat[i - 1] and not flat[i - 2]]
    assert len(cut) == 1 and np.array_equal(sent[cut[0] + 1], sent[cut[0] - 2])
    assert len(responder.prompts) == 2  # a trial played again repeats no block prompt
