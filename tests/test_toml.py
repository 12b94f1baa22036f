"""Strict TOML reading (crs_study/_toml.py, crs_study/_toml_lines.py) and the errors it raises.

A misspelt key is named as the stray key it is, with the valid keys and the closest one, in
every file kind read through ``_toml``: protocols, device files, strokes files and analysis
plans. The closest key is difflib's (Python's ``difflib.get_close_matches``, the outside
reference for "close"); the test below misspells real keys of the shipped files with one edit
(deletion, insertion, substitution or transposition of a character).
"""

from __future__ import annotations

import pickle
import re
import tomllib

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from crs_study._toml import Section, closest_key, misspelling_of, unknown_key_reason
from crs_study._toml_lines import find_line, locate, syntax_error, syntax_line
from crs_study.analysis.plan import load_plan
from crs_study.errors import (
    ConfigError,
    DeviceFileError,
    PlanError,
    ProtocolError,
)
from crs_study.geometry.layout import device_file_path, load_layout
from crs_study.paths import shipped_file
from crs_study.protocol import TABLE_KEYS, load_protocol
from crs_study.stimuli.digits import load_digits, shipped_strokes_path

# --- the errors carry where they are ---------------------------------------------------------


def test_config_error_message_is_built_from_its_attributes():
    error = ProtocolError("expected a number, got '5'", source="p.toml", line=7,
                          key_path="stimulus.bump_height_mm")
    assert str(error) == "p.toml:7: stimulus.bump_height_mm: expected a number, got '5'"
    assert (error.source, error.line, error.key_path) == ("p.toml", 7,
                                                           "stimulus.bump_height_mm")
    error.line = None  # a loader that knows no line
    assert str(error) == "p.toml: stimulus.bump_height_mm: expected a number, got '5'"
    stray = ConfigError("unknown key 'x'", source="d.toml", key_path="geometry.x",
                        shown_path="geometry")
    assert str(stray) == "d.toml: geometry: unknown key 'x'" and stray.key_path == "geometry.x"
    assert str(ConfigError("crs2d.toml: beams: a message made whole")) == \
        "crs2d.toml: beams: a message made whole"
    assert str(ConfigError("reason", key_path="k")) == "k: reason"


def test_config_errors_keep_their_attributes_through_pickling():
    # process pools and Dask send errors between processes
    error = PlanError("expected a number", source="p.toml", line=3, key_path="plan.alpha")
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is PlanError and str(copy) == str(error)
    assert (copy.source, copy.line, copy.key_path, copy.reason) == \
        ("p.toml", 3, "plan.alpha", "expected a number")


def test_locate_adds_the_file_and_the_line_of_the_key():
    text = "[design]\nrepetitions = 0\n"
    error = locate(ProtocolError("expected a whole number >= 1, got 0",
                                 key_path="design.repetitions"), "p.toml", text)
    assert str(error) == "p.toml:2: design.repetitions: expected a whole number >= 1, got 0"
    # an error of another file keeps its own place
    other = ProtocolError("bad", source="strokes.toml", line=9, key_path="digits.1.strokes")
    assert str(locate(other, "p.toml", text)) == "strokes.toml:9: digits.1.strokes: bad"


@pytest.mark.parametrize("text, line", [
    pytest.param("[study\nid = 1\n", 1, id="header"),
    pytest.param("a = 1\nb = [1,\n", 2, id="end-of-document"),
    pytest.param("a = 1\n\nb = = 2\n", 3, id="value"),
])
def test_syntax_errors_name_the_line_tomllib_gives(text, line):
    with pytest.raises(tomllib.TOMLDecodeError) as caught:
        tomllib.loads(text)
    assert syntax_line(caught.value, text) == line
    error = syntax_error(ProtocolError, "p.toml", caught.value, text)
    assert str(error).startswith(f"p.toml:{line}: not valid TOML: ") and error.line == line


# --- sections --------------------------------------------------------------------------------


def test_a_section_that_declares_its_keys_refuses_a_stray_one_first():
    text = "[design]\nrepetiton = 3\nordering = 5\n"
    with pytest.raises(ProtocolError) as caught:
        Section(tomllib.loads(text), "p.toml", error=ProtocolError, text=text).table(
            "design", keys=("repetitions", "ordering"))
    error = caught.value
    assert str(error) == ("p.toml:2: design: unknown key 'repetiton' (valid keys: ordering, "
                          "repetitions); did you mean 'repetitions'?")
    assert error.key_path == "design.repetiton" and error.line == 2


def test_a_section_that_learns_its_keys_names_the_stray_one_at_done():
    section = Section({"pich_mm": 30, "lattice": "hex"}, "d.toml", "geometry")
    section.string("lattice")
    section.number("pitch_mm", 30.0)
    with pytest.raises(ConfigError, match=r"^d.toml: geometry: unknown key 'pich_mm' \(valid "
                       r"keys: lattice, pitch_mm\); did you mean 'pitch_mm'\?$"):
        section.done()


def test_a_missing_required_key_names_the_close_stray_key():
    section = Section({"repetiton": 3}, "p.toml", "design")
    with pytest.raises(ConfigError, match=r"^p.toml: design: missing required key "
                       r"'repetitions'; is 'repetiton' a misspelling of it\?$") as caught:
        section.integer("repetitions")
    assert caught.value.key_path == "design.repetitions"


def test_valid_keys_alike_are_not_taken_for_misspellings():
    # a valid key read later is no misspelling of a missing one (MISSPELLING_CUTOFF)
    section = Section({"digit_width_pitch": 0.49}, "p.toml", "stimulus")
    with pytest.raises(ConfigError, match=r"missing required key 'digit_height_pitch'$"):
        section.number("digit_height_pitch")


def test_no_two_valid_keys_of_a_shipped_table_pass_for_misspellings_of_each_other():
    # so the hint of a missing key never points at a valid key (MISSPELLING_CUTOFF); the
    # protocol's tables are declared (TABLE_KEYS), the others read off the shipped files
    tables = {("protocol", t): set(keys) for t, keys in TABLE_KEYS.items()}
    for kind, (path, *_) in KINDS.items():
        for table, key in _keys(path.read_text(encoding="utf-8")):
            tables.setdefault((kind, table), set()).add(key)
    for path in (device_file_path("crs1d"), shipped_file("analysis/digit_size_psychometric.toml")):
        for table, key in _keys(path.read_text(encoding="utf-8")):
            tables.setdefault((path.name, table), set()).add(key)
    for (kind, table), keys in tables.items():
        for key in keys:
            assert misspelling_of(key, keys - {key}) is None, (kind, table, key)


def test_no_suggestion_when_nothing_is_close():
    assert closest_key("colour", ["id", "version", "device"]) is None
    assert unknown_key_reason("colour", ["id", "version"]) == \
        "unknown key 'colour' (valid keys: id, version)"


# --- one-edit misspellings of the shipped files' keys, in every file kind --------------------


#: Tables whose keys are names (channels, conditions), not a fixed set of keys.
NAMED = {"calibration", "conditions.prompts"}


def _keys(text: str) -> list[tuple[str, str]]:
    """(table, key) of each ``key = value`` line of a TOML text ("" for the top level); keys
    in arrays of tables ([[...]]), in inline tables and in tables of names are left out."""
    found, table = [], ""
    for line in text.splitlines():
        header = re.match(r"^\[(\[?)([^\]]+)\]", line)
        if header:
            table = None if header.group(1) or header.group(2) in NAMED else header.group(2)
            continue
        key = re.match(r"^([A-Za-z0-9_-]+)\s*=", line)
        if key and table is not None and not line.rstrip().endswith("= ["):
            found.append((table, key.group(1)))
    return found


def _rename(text: str, table: str, key: str, new: str) -> str:
    lines, current = text.splitlines(keepends=True), ""
    for i, line in enumerate(lines):
        header = re.match(r"^\[(\[?)([^\]]+)\]", line)
        if header:
            current = header.group(2)
        elif current == table and re.match(rf"^{re.escape(key)}\s*=", line):
            lines[i] = new + line[len(key):]
            return "".join(lines)
    raise AssertionError((table, key))


@st.composite
def one_edit(draw, key: str) -> str:
    """``key`` with one character deleted, inserted, replaced or swapped with the next."""
    alphabet = "abcdefghijklmnopqrstuvwxyz_"
    i = draw(st.integers(0, len(key) - 1))
    kind = draw(st.sampled_from(["delete", "insert", "replace", "swap"]))
    if kind == "delete":
        return key[:i] + key[i + 1:]
    if kind == "swap" and i < len(key) - 1:
        return key[:i] + key[i + 1] + key[i] + key[i + 2:]
    char = draw(st.sampled_from(alphabet))
    return key[:i] + char + key[i + (kind == "replace"):]


def _protocol(path):
    return load_protocol(path, check_device=False)


#: kind -> (shipped file, loader, error class, keys declared up front)
KINDS = {
    "protocol": (shipped_file("protocols/digit_identification.toml"), _protocol,
                 ProtocolError, True),
    "device file": (device_file_path("crs2d"), load_layout, DeviceFileError, False),
    "strokes file": (shipped_strokes_path(), load_digits, ProtocolError, True),
    "analysis plan": (shipped_file("analysis/digit_identification.toml"), load_plan,
                      PlanError, False),
}


@st.composite
def misspelt(draw):
    kind = draw(st.sampled_from(sorted(KINDS)))
    text = KINDS[kind][0].read_text(encoding="utf-8")
    table, key = draw(st.sampled_from([k for k in _keys(text) if len(k[1]) >= 5]))
    typo = draw(one_edit(key))
    present = {k for t, k in _keys(text) if t == table}
    assume(typo != key and typo not in present and re.fullmatch(r"[A-Za-z0-9_-]+", typo))
    if kind == "protocol":
        assume(typo not in TABLE_KEYS[table])
    return kind, _rename(text, table, key, typo), table, key, typo


@settings(max_examples=160, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(misspelt())
def test_a_misspelt_key_is_named_with_the_key_it_was_meant_to_be(tmp_path_factory, example):
    kind, text, table, key, typo = example
    _, load, error, declared = KINDS[kind]
    path = tmp_path_factory.mktemp("typo") / "file.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(error) as caught:
        load(path)
    message = str(caught.value)
    assert "\n" not in message and str(path) in message or path.name in message, message
    stray = f"unknown key '{typo}' (valid keys: "
    if declared:  # refused as the stray key, before anything is read
        assert stray in message and message.endswith(f"did you mean '{key}'?"), message
        assert caught.value.key_path == (f"{table}.{typo}" if table else typo)
        assert caught.value.line == find_line(text, caught.value.key_path)
    else:  # a required key is missed first, an optional one's stray key is found at the end
        assert (message.endswith(f"missing required key '{key}'; is '{typo}' a misspelling "
                                 "of it?")
                or (stray in message and message.endswith(f"did you mean '{key}'?"))), message
