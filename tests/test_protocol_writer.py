"""A protocol changed in Python, written as TOML and read back (crs_study.protocol.writer) and
loaded through load_protocol as a file is: same fields, stable bytes, every check.

Before this, ``dry_run(replace(protocol, ...))`` raised ``TypeError: expected str, bytes or
os.PathLike object, not Protocol``, and a changed protocol kept the text
and sha256 of the file it was read from, which a session would have stored as what ran.
"""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import replace
from pathlib import Path

import pytest
from _session_helpers import tiny_protocol
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.errors import ProtocolError
from crs_study.geometry.layout import device_file_path
from crs_study.paths import shipped_protocols
from crs_study.protocol import load_protocol, protocol_from_text, protocol_to_toml
from crs_study.protocol.writer import changed_keys, toml_string

SHIPPED = sorted(shipped_protocols())


def _same_fields(a, b) -> bool:
    """Equal but for the text and its sha256 (and the device checks, never compared)."""
    return replace(a, text=b.text, sha256=b.sha256) == b


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_protocol_reads_back_as_itself(name):
    protocol = load_protocol(name)
    text = protocol_to_toml(protocol)
    again = protocol_from_text(text, protocol.path, check_device=False)
    assert _same_fields(protocol, again)
    assert again.sha256 == hashlib.sha256(text.encode()).hexdigest()
    assert "# changed in Python: no key." in text


def test_an_unchanged_protocol_object_is_returned_as_it_is():
    protocol = load_protocol("pilot")
    assert load_protocol(protocol) is protocol
    unchecked = load_protocol("pilot", check_device=False)
    assert unchecked.checks == ()
    checked = load_protocol(unchecked)          # the device checks run on the object
    assert checked.checks == protocol.checks and checked.sha256 == protocol.sha256


def test_a_changed_protocol_gets_the_text_that_runs():
    protocol = load_protocol("pilot")
    changed = replace(protocol, design=replace(protocol.design, repetitions=2),
                      stimulus=replace(protocol.stimulus, stroke_speed_mm_s=25.0))
    settled = load_protocol(changed)
    assert settled.design.repetitions == 2 and settled.stimulus.stroke_speed_mm_s == 25.0
    assert settled.path == protocol.path                  # the files it names are found there
    assert settled.sha256 != protocol.sha256
    assert settled.sha256 == hashlib.sha256(settled.text.encode()).hexdigest()
    assert settled.checks == protocol.checks              # every device check ran
    assert _same_fields(changed, settled)
    data = tomllib.loads(settled.text)
    assert data["design"]["repetitions"] == 2 and data["stimulus"]["stroke_speed_mm_s"] == 25.0
    assert settled.text.splitlines()[:3] == [
        "# Written by crs-study (crs_study.protocol.protocol_to_toml) from the protocol",
        f"# of sha256 {protocol.sha256};",
        "# changed in Python: stimulus.stroke_speed_mm_s, design.repetitions."]
    assert load_protocol(settled) is settled              # settled once, then kept


def test_the_written_bytes_are_pinned(tmp_path):
    """A session begun from a changed protocol stores this text and resumes only under its
    sha256: the writer's output must not drift (a change here refuses such resumes)."""
    protocol = load_protocol(tiny_protocol(tmp_path))
    built = replace(protocol, text="", sha256="", title="Tiny \"quoted\" \\ title",
                    design=replace(protocol.design, repetitions=3))
    text = protocol_to_toml(built)
    assert text == PINNED_TINY
    assert hashlib.sha256(text.encode()).hexdigest() == \
        load_protocol(built).sha256


PINNED_TINY = """\
# Written by crs-study from a protocol built in Python.

[study]
id = "tiny"
version = "1.0.0"
title = "Tiny \\"quoted\\" \\\\ title"
device = "crs2d"
consent_form = "consent/consent_form.md"
consent_form_version = "1.0"
analysis_plan = "analysis/pilot.toml"

[stimulus]
digits = [1, 4, 7]
digit_height_pitch = 0.81
digit_width_pitch = 0.49
bump_diameter_mm = 90.0
bump_height_mm = 5.0
stroke_speed_mm_s = 60.0
placement = "centre"
frame_rate_hz = 15.0
stroke_pause_s = 0.2
start_hold_s = 0.1
end_hold_s = 0.1

[conditions]
names = ["pixel-only", "crs"]

[conditions.prompts]
pixel-only = "Pixel-only block: remove the skeleton (beams off), then continue"
crs = "CRS block: mount the skeleton (beams on, boundary servos attached), then continue"

[design]
repetitions = 3
ordering = "blocked"
counterbalancing = "alternate"
max_same_digit_run = 2
practice_trials = 1
practice_in = "first-block"
break_every = 0
break_duration_s = 0.0
inter_trial_interval_s = 0.5

[responses]
keys = ["1", "4", "7"]
time_limit_s = 10.0
feedback = "practice"
expected_response_s = 2.0
"""


def test_paths_are_written_relative_to_the_protocol_so_they_resolve_alike(tmp_path):
    folder = tmp_path / "study" / "protocols"
    folder.mkdir(parents=True)
    device = device_file_path("crs2d")
    (tmp_path / "study" / "my_device.toml").write_bytes(device.read_bytes())
    path = tiny_protocol(folder)
    text = path.read_text().replace('device = "crs2d"', 'device = "../my_device.toml"')
    path.write_text(text)
    protocol = load_protocol(path)
    changed = load_protocol(replace(protocol, design=replace(protocol.design, repetitions=2)))
    assert 'device = "../my_device.toml"' in changed.text
    assert Path(changed.device).resolve() == (tmp_path / "study" / "my_device.toml").resolve()


def test_a_changed_protocol_is_checked_as_a_file_is():
    """Checks that join two tables or need the device are the loader's: they run on the
    written text, and the error names the changed protocol, not a line of text the user
    never saw."""
    protocol = load_protocol("pilot")
    interleaved = replace(protocol, design=replace(protocol.design, ordering="interleaved",
                                                   counterbalancing="none"))
    with pytest.raises(ProtocolError, match=r"pilot\.toml \(changed in Python\): "
                       r"conditions\.prompts: an interleaved design") as caught:
        load_protocol(interleaved)
    assert caught.value.line is None and caught.value.key_path == "conditions.prompts"
    too_big = replace(protocol, stimulus=replace(protocol.stimulus, symbol_height_pitch=9.0,
                                                 symbol_width_pitch=9.0))
    with pytest.raises(ProtocolError, match=r"\(changed in Python\): stimulus\."):
        load_protocol(too_big)
    with pytest.raises(ProtocolError, match=r"design\.repetitions: expected"):
        replace(protocol.design, repetitions=0)      # the model's own check, on replace


def test_warnings_of_a_changed_protocol_name_it_without_a_line():
    protocol = load_protocol("pilot")
    long = load_protocol(replace(protocol, design=replace(protocol.design, repetitions=40)))
    assert long.warnings
    assert all(w.startswith(f"{protocol.path} (changed in Python): ") for w in long.warnings)


def test_changed_keys_compare_values_not_spelling():
    assert changed_keys({"a": {"x": 1, "y": [1, 2]}}, {"a": {"x": 1.0, "y": (1, 2)}}) == []
    assert changed_keys({"a": {"x": 1}, "b": {"z": 1}}, {"a": {"x": 2, "w": 0}}) == \
        ["a.x", "a.w", "b"]


@given(st.text(st.characters(blacklist_categories=("Cs",))))
def test_any_text_reads_back_from_a_toml_string(text):
    assert tomllib.loads(f"key = {toml_string(text)}")["key"] == text


def test_a_lone_surrogate_is_a_protocol_error():
    with pytest.raises(ProtocolError, match="a lone surrogate"):
        toml_string("x\ud800")


_ONE_LINE = st.text(st.characters(blacklist_categories=("Cs", "Cc")), min_size=1,
                    max_size=40).filter(lambda s: s.strip() and s.isprintable())


@st.composite
def _changed(draw, protocol):
    design = replace(
        protocol.design,
        repetitions=draw(st.integers(1, 3)), practice_trials=draw(st.integers(0, 4)),
        max_same_symbol_run=draw(st.integers(1, 5)), break_every=draw(st.integers(0, 50)),
        break_duration_s=draw(st.floats(0, 3600)),
        inter_trial_interval_s=draw(st.floats(0, 60)))
    stimulus = replace(protocol.stimulus, stroke_pause_s=draw(st.floats(0, 10)),
                       end_hold_s=draw(st.floats(0, 10)))
    responses = replace(protocol.responses,
                        time_limit_s=draw(st.none() | st.floats(0.01, 3600)),
                        expected_response_s=draw(st.floats(0, 3600)))
    prompts = tuple((c, draw(_ONE_LINE)) for c in protocol.conditions
                    if draw(st.booleans()))
    changed = replace(protocol, title=draw(st.text(st.characters(
        blacklist_categories=("Cs",)), max_size=30)), condition_prompts=prompts,
        design=design, stimulus=stimulus, responses=responses)
    if protocol.levels is not None:
        values = draw(st.lists(st.floats(0.5, 1.5), min_size=2, max_size=5, unique=True))
        levels = replace(protocol.levels, values=tuple(values))
        # the loader puts the first level into [stimulus] (Protocol.stimulus_at)
        changed = replace(changed, levels=levels,
                          stimulus=levels.spec_at(changed.stimulus, levels.values[0]))
    return changed


@pytest.mark.parametrize("name", ["pilot", "digit_size_psychometric", "letter_identification"])
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_any_changed_protocol_reads_back_with_the_same_fields(name, data):
    protocol = load_protocol(name, check_device=False)
    changed = data.draw(_changed(protocol))
    text = protocol_to_toml(changed)
    assert _same_fields(changed, protocol_from_text(text, protocol.path, check_device=False))


def test_the_settled_text_saved_beside_the_original_is_the_same_protocol(tmp_path):
    """So a session begun in Python resumes from the command line (README, "In Python")."""
    protocol = load_protocol(tiny_protocol(tmp_path))
    settled = load_protocol(replace(protocol, design=replace(protocol.design, repetitions=2)))
    saved = tmp_path / "twice.toml"
    saved.write_text(settled.text, encoding="utf-8")
    again = load_protocol(saved)
    assert again.sha256 == settled.sha256
    assert replace(again, path=settled.path) == settled
