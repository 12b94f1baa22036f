"""The session sidecar as SessionMetadata: sidecars written by the previous code read and
round-trip byte for byte, strict reading names file and key, the runner writes through it.

The fixtures under tests/fixtures/sessions_4c71d44 were written by crs-study at commit 4c71d44
(the untyped dict writer), by tests/fixtures/sessions_4c71d44/make_fixture.py.
"""

from __future__ import annotations

import json
import string
from dataclasses import replace
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.dataset import schema
from crs_study.dataset.session_metadata import (
    FINGERPRINTS,
    SIDECAR_KEYS,
    Fault,
    Resume,
    SessionMetadata,
)
from crs_study.errors import DatasetError

FIXTURES = Path(__file__).parent / "fixtures" / "sessions_4c71d44"
#: Every sidecar of 4c71d44 in the fixtures (tests/fixtures/main_sessions: two more sessions,
#: made for the protocol split's resume test).
MAIN_SIDECARS = sorted(FIXTURES.glob("*/sub-*/ses-*/beh/sub-*_beh.json")) + sorted(
    (FIXTURES.parent / "main_sessions" / "dataset").glob("*/sub-*/ses-*/beh/sub-*_beh.json"))


def _sidecar(participant: str) -> Path:
    return FIXTURES / "dataset" / f"sub-{participant}" / "ses-1" / "beh" / \
        f"sub-{participant}_ses-1_task-digitid_beh.json"


def test_the_fixture_holds_every_kind_of_sidecar_the_previous_code_wrote():
    assert len(MAIN_SIDECARS) == 7
    kinds = {(m.status, m.clock, bool(m.resumes), bool(m.faults), m.stimulus_sha256 is None)
             for m in map(SessionMetadata.read, MAIN_SIDECARS)}
    assert ("interrupted", "virtual", True, True, False) in kinds   # fault, then a resume
    assert ("complete", "virtual", True, False, True) in kinds      # begun before the fingerprint
    assert ("complete", "real", False, False, False) in kinds


@pytest.mark.parametrize("path", MAIN_SIDECARS,
                         ids=lambda p: f"{p.parts[-6]}-{p.parts[-5]}-{p.parts[-4]}")
def test_sidecars_written_by_the_previous_code_round_trip_byte_for_byte(path):
    text = path.read_text(encoding="utf-8")
    metadata = SessionMetadata.from_json(text, path)
    assert metadata.to_json() == text
    assert list(json.loads(text)) == list(SIDECAR_KEYS)


def test_typed_fields_of_a_faulted_and_resumed_session():
    meta = SessionMetadata.read(_sidecar("p01"))
    assert (meta.participant, meta.session, meta.status) == ("p01", 1, "interrupted")
    assert (meta.trials_planned, meta.trials_completed) == (8, 4)
    assert isinstance(meta.seed, int) and isinstance(meta.frame_rate_hz, float)
    assert meta.start_time.tzinfo is not None and meta.end_time >= meta.start_time
    assert meta.simulated_device and meta.virtual_clock and not meta.is_complete
    (fault,) = meta.faults
    assert isinstance(fault, Fault) and fault.trial == 2 and "port vanished" in fault.message
    (resume,) = meta.resumes
    assert isinstance(resume, Resume)
    assert (resume.at_trial, resume.device_url, resume.software_version) == (2, "sim://",
                                                                             "0.1.0")
    assert set(meta.fingerprints()) == set(FINGERPRINTS)


def test_schema_lists_every_key_the_runner_writes():
    # schema.SESSION_KEYS listed 25 keys and lacked some the runner wrote; now it is the format's
    written = json.loads(_sidecar("p02").read_text())
    assert schema.SESSION_KEYS == tuple(written) == SIDECAR_KEYS
    assert len(SIDECAR_KEYS) == 30
    assert schema.SESSION_STATUSES == ("running", "interrupted", "complete")


def _bad(path: Path, edit) -> str:
    data = json.loads(path.read_text())
    edit(data)
    return json.dumps(data)


@pytest.mark.parametrize("edit, message", [
    pytest.param(lambda d: d.update(Sttus="complete"),
                 r"unknown key Sttus \(did you mean 'Status'\?\); expected only TaskName, ",
                 id="unknown-key"),
    pytest.param(lambda d: d.pop("Seed"), r": missing key Seed$", id="missing-key"),
    pytest.param(lambda d: d.update(Seed="42"),
                 r": Seed: expected a whole number >= 0, got '42'$", id="seed-as-text"),
    pytest.param(lambda d: d.update(Seed=True),
                 r": Seed: expected a whole number >= 0, got True$", id="seed-as-boolean"),
    pytest.param(lambda d: d.update(Session=0), r": Session: expected a whole number >= 1",
                 id="session-0"),
    pytest.param(lambda d: d.update(Status="done"),
                 r": Status: expected one of \['running', 'interrupted', 'complete'\], "
                 r"got 'done'$", id="status"),
    pytest.param(lambda d: d.update(Clock="wall"), r": Clock: expected one of \['real', ",
                 id="clock"),
    pytest.param(lambda d: d.update(StartTime="2026-11-24 01:00"),
                 r": StartTime: expected an ISO 8601 time with a UTC offset", id="naive-time"),
    pytest.param(lambda d: d.update(ProtocolSha256="abc"),
                 r": ProtocolSha256: expected a sha256 \(64 lower-case hex digits\), got 'abc'",
                 id="sha"),
    pytest.param(lambda d: d.update(Protocol=None), r": Protocol: expected a string, got None",
                 id="protocol-null"),
    pytest.param(lambda d: d.update(FrameRateHz=0), r": FrameRateHz: expected a number > 0",
                 id="rate"),
    pytest.param(lambda d: d.update(Participant="sub-p01"),
                 r": Participant: expected a label of letters and digits, got 'sub-p01'",
                 id="label"),
    pytest.param(lambda d: d.update(Faults={}), r": Faults: expected a list, got \{\}",
                 id="faults-object"),
    pytest.param(lambda d: d["Faults"][0].update(trial=-1),
                 r": Faults\[0\]\.trial: expected a whole number >= 0, got -1$",
                 id="fault-trial"),
    pytest.param(lambda d: d["Faults"][0].pop("message"), r": missing key Faults\[0\]\.message$",
                 id="fault-missing"),
    pytest.param(lambda d: d["Resumes"][0].update(Tme="x"),
                 r": unknown key Resumes\[0\]\.Tme \(did you mean 'Time'\?\); expected only "
                 r"Time, AtTrial, DeviceURL, SoftwareVersion$", id="resume-unknown"),
    pytest.param(lambda d: d["Resumes"].append(3),
                 r": Resumes\[1\]: expected a JSON object, got 3$", id="resume-not-object"),
])
def test_a_bad_sidecar_is_one_line_naming_file_and_key(edit, message):
    path = _sidecar("p01")
    with pytest.raises(DatasetError, match=message) as caught:
        SessionMetadata.from_json(_bad(path, edit), path)
    text = str(caught.value)
    assert text.startswith(f"{path}: ") and "\n" not in text


@pytest.mark.parametrize("text, message", [
    ("{", r"not a readable session sidecar: Expecting property name"),
    ("[1, 2]", r"the sidecar: expected a JSON object, got \[1, 2\]"),
    ('"running"', r"the sidecar: expected a JSON object, got 'running'"),
])
def test_not_a_json_object_is_one_line(tmp_path, text, message):
    path = tmp_path / "sub-p01_ses-1_task-digitid_beh.json"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message):
        SessionMetadata.read(path)


def test_an_unreadable_sidecar_is_one_line(tmp_path):
    path = tmp_path / "s.json"
    path.write_bytes(b"\xff\xfe{")
    with pytest.raises(DatasetError, match=r"s\.json: not a readable session sidecar"):
        SessionMetadata.read(path)
    with pytest.raises(DatasetError, match=r"missing\.json: not a readable session sidecar"):
        SessionMetadata.read(tmp_path / "missing.json")


def test_a_sidecar_older_than_the_stimulus_fingerprint_reads_with_none():
    data = json.loads(_sidecar("p02").read_text())
    del data["StimulusSha256"]
    meta = SessionMetadata.from_dict(data, "old.json")
    assert meta.stimulus_sha256 is None
    assert json.loads(meta.to_json())["StimulusSha256"] is None


def test_construction_checks_every_field():
    meta = SessionMetadata.read(_sidecar("p02"))
    with pytest.raises(DatasetError, match=r"SessionMetadata.status \(Status\): expected one of"):
        replace(meta, status="done")
    with pytest.raises(DatasetError,
                       match=r"start_time \(StartTime\): expected a datetime, got '2026"):
        replace(meta, start_time="2026-11-24T00:00:00+00:00")  # a string, not a datetime
    with pytest.raises(DatasetError, match=r"resumes \(Resumes\): expected a tuple, got \[\]"):
        replace(meta, resumes=[])  # a list, not a tuple: the dataclass is frozen all through
    with pytest.raises(DatasetError, match=r"Resume.time \(Time\): expected an ISO 8601 time"):
        Resume(datetime(2026, 1, 1), 0, "sim://", "0.1.0")  # naive: no UTC offset
    with pytest.raises(DatasetError, match=r"frame_rate_hz \(FrameRateHz\): expected a float, "
                                           r"got 15$"):
        replace(meta, frame_rate_hz=15)
    with pytest.raises(DatasetError, match="9 trials completed of 8 planned"):
        replace(meta, trials_completed=9)


# --- property: any valid metadata survives to_json / from_json ---------------------------------

_label = st.text(string.ascii_letters + string.digits, min_size=1, max_size=8)
_sha = st.text("0123456789abcdef", min_size=64, max_size=64)
_text = st.text(max_size=40)
_count = st.integers(0, 10**6)
_time = st.datetimes(min_value=datetime(2000, 1, 1), max_value=datetime(2100, 1, 1),
                     timezones=st.sampled_from([UTC, timezone(timedelta(hours=2))]))


@st.composite
def metadata(draw) -> SessionMetadata:
    planned = draw(_count)
    return SessionMetadata(
        task_name=draw(_label), task_description=draw(_text), instructions=draw(_text),
        protocol_text=draw(_text), protocol_sha256=draw(_sha), protocol_path=draw(_text),
        study_id=draw(_text), study_version=draw(_text), device_file_text=draw(_text),
        device_file_sha256=draw(_sha), device_url=draw(_text), software_version=draw(_text),
        seed=draw(st.integers(0, 2**64 - 1)), counterbalance=draw(_count),
        plan_sha256=draw(_sha), stimulus_sha256=draw(st.none() | _sha),
        participant=draw(_label), session=draw(st.integers(1, 99)),
        consent_form_version=draw(_text), responder=draw(_text),
        clock=draw(st.sampled_from(["real", "virtual"])),
        frame_rate_hz=draw(st.floats(1e-3, 1e3, allow_nan=False)),
        start_time=draw(_time), end_time=draw(st.none() | _time),
        status=draw(st.sampled_from(["running", "interrupted", "complete"])),
        trials_planned=planned, trials_completed=draw(st.integers(0, planned)),
        trials_sha256=draw(st.none() | _sha),
        resumes=tuple(draw(st.lists(st.builds(Resume, _time, _count, _text, _text),
                                    max_size=3))),
        faults=tuple(draw(st.lists(st.builds(Fault, _count, _time, _text), max_size=3))),
    )


@settings(max_examples=150)
@given(metadata())
def test_to_json_then_from_json_is_the_identity(meta):
    text = meta.to_json()
    again = SessionMetadata.from_json(text, "x.json")
    assert again == meta and again.to_json() == text


@settings(max_examples=300)
@given(key=st.sampled_from(SIDECAR_KEYS),
       value=st.recursive(st.none() | st.booleans() | st.integers() | st.floats()
                          | st.text(max_size=5),
                          lambda inner: st.lists(inner, max_size=2)
                          | st.dictionaries(st.text(max_size=3), inner, max_size=2),
                          max_leaves=4))
def test_any_value_under_any_key_reads_or_is_one_dataset_error(key, value):
    data = json.loads(_sidecar("p01").read_text())
    data[key] = value
    try:
        meta = SessionMetadata.from_dict(data, "fuzz.json")
    except DatasetError as error:
        assert str(error).startswith("fuzz.json: ") and "\n" not in str(error)
    else:
        assert json.loads(meta.to_json())[key] == json.loads(json.dumps(value))


# --- the runner writes through it -----------------------------------------------------------

def test_a_dry_run_sidecar_is_session_metadata(tmp_path):
    from _session_helpers import tiny_protocol

    from crs_study.session.dry_runs import dry_run

    (result,) = dry_run(tiny_protocol(tmp_path), 1, tmp_path / "ds", responder="random")
    meta = SessionMetadata.read(result.sidecar)
    assert meta.to_json() == result.sidecar.read_text()
    assert (meta.status, meta.trials_completed, meta.participant) == ("complete", 8, "sim01")
    assert meta.end_time is not None and meta.end_time.tzinfo is not None
    assert meta.end_time.microsecond == 0 and meta.resumes == () and meta.faults == ()
