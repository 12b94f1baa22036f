"""Replay: a session's tracks rebuilt from recorded responses reach the same state and
fingerprint; the sidecar carries the fingerprint as a typed, optional key."""

from __future__ import annotations

import json
from datetime import UTC, datetime

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.adaptive import (
    AdaptiveRun,
    AdaptiveSpec,
    QuestPlusSpec,
    RecordedTrial,
    StaircaseSpec,
)
from crs_study.dataset.session_metadata import SIDECAR_KEYS, SessionMetadata
from crs_study.errors import DatasetError, SessionError

STAIR = AdaptiveSpec("digit_height_pitch", "staircase", 30, 0.25, 1.5, "log", 12,
                     width_to_height=0.6,
                     staircase=StaircaseSpec("1-up-2-down", 1.5, (2, 1), 6, 4))
QUEST = AdaptiveSpec("digit_height_pitch", "quest-plus", 6, 0.25, 1.5, "log", 6,
                     target_rate=0.5, width_to_height=0.6,
                     quest_plus=QuestPlusSpec(8, (2.0, 6.0), (0.0, 0.05)))


def live(spec, outcomes):
    """A run played live: each block's levels as chosen, then its responses."""
    run, recorded = AdaptiveRun(spec, 10), []
    for block, correct in outcomes:
        if run.finished(block):
            continue
        level = run.next_level(block)
        run.update(block, correct)
        recorded.append(RecordedTrial(block, level, correct, f"row {len(recorded) + 1}"))
    return run, recorded


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1), st.one_of(st.booleans(), st.none())),
                max_size=70))
def test_replaying_the_record_reaches_the_same_state(outcomes):
    run, recorded = live(STAIR, outcomes)
    again = AdaptiveRun(STAIR, 10)
    again.replay(recorded)
    assert again.state() == run.state() and again.fingerprint() == run.fingerprint()


@settings(max_examples=5, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1), st.booleans()), min_size=1, max_size=12))
def test_quest_plus_replay_reaches_the_same_state(outcomes):
    run, recorded = live(QUEST, outcomes)
    again = AdaptiveRun(QUEST, 10)
    again.replay(recorded)
    assert again.fingerprint() == run.fingerprint()


def test_another_level_or_a_trial_after_the_end_is_refused():
    run, recorded = live(STAIR, [(0, True)] * 3)
    altered = [recorded[0], RecordedTrial(0, 0.25, True, "row 2")]
    with pytest.raises(SessionError, match=r"row 2: level 0.25 stored, but replaying"):
        AdaptiveRun(STAIR, 10).replay(altered)
    _, full = live(QUEST, [(0, True)] * 6)
    with pytest.raises(SessionError, match=r"row 7: a trial of block 0 after its quest-plus "
                                           r"finished \(6 trials\)"):
        AdaptiveRun(QUEST, 10).replay([*full, RecordedTrial(0, 1.5, True, "row 7")])


def test_the_fingerprint_depends_on_responses_and_settings():
    a, _ = live(STAIR, [(0, True), (0, False)])
    b, _ = live(STAIR, [(0, True), (0, True)])
    assert a.fingerprint() != b.fingerprint()
    c = AdaptiveRun(STAIR, 10)
    d = AdaptiveRun(AdaptiveSpec(**{**STAIR.__dict__, "trials": 31}), 10)
    assert c.fingerprint() != d.fingerprint()


@pytest.mark.parametrize("spec", [STAIR, QUEST], ids=["staircase", "quest-plus"])
def test_asking_a_track_for_its_level_changes_no_fingerprint(spec):
    """A resume asks the next trial's track whether it has finished (creating the track)
    before it writes the sidecar; a later resume checks the stored fingerprint at the same
    trial count without asking. The state is a function of the responses alone, so asking
    changes nothing (it did: two kills at the first trial of a block made the session
    unresumable, "the adaptive procedures' state after 1 trials differs")."""
    for before in ([], [(0, True)]):
        asked, _ = live(spec, before)
        untouched, _ = live(spec, before)
        asked.finished(0), asked.next_level(1), asked.finished(1)
        assert asked.state() == untouched.state()
        assert asked.fingerprint() == untouched.fingerprint()


def sidecar(adaptive_sha256=None) -> SessionMetadata:
    return SessionMetadata(
        task_name="digitid", task_description="d", instructions="i", protocol_text="p",
        protocol_sha256="a" * 64, protocol_path="p.toml", study_id="s", study_version="1",
        device_file_text="d", device_file_sha256="b" * 64, device_url="sim://",
        software_version="0", seed=1, counterbalance=0, plan_sha256="c" * 64,
        stimulus_sha256="d" * 64, participant="p01", session=1, consent_form_version="1",
        responder="observer", clock="virtual", frame_rate_hz=15.0,
        start_time=datetime(2026, 11, 24, tzinfo=UTC), end_time=None, status="running",
        trials_planned=4, trials_completed=2, trials_sha256="e" * 64,
        adaptive_state_sha256=adaptive_sha256)


def test_the_sidecar_key_is_typed_optional_and_round_trips():
    fixed = sidecar()
    assert list(json.loads(fixed.to_json())) == list(SIDECAR_KEYS)  # a fixed session's keys
    adaptive = sidecar("f" * 64)
    data = json.loads(adaptive.to_json())
    assert list(data)[list(data).index("TrialsSha256") + 1] == "AdaptiveStateSha256"
    assert SessionMetadata.from_json(adaptive.to_json()).to_json() == adaptive.to_json()
    data["AdaptiveStateSha256"] = "not a sha"
    with pytest.raises(DatasetError, match=r"x.json: AdaptiveStateSha256: expected a sha256"):
        SessionMetadata.from_json(json.dumps(data), "x.json")
