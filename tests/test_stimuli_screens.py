"""The participant's screen texts: English defaults, translated in a set file's [set.screens]."""

from __future__ import annotations

import re
from dataclasses import asdict

import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study._toml import Section
from crs_study.errors import ProtocolError
from crs_study.paths import shipped_file
from crs_study.session.responders import make_responder
from crs_study.stimuli.screens import FIELDS, ScreenTexts
from crs_study.stimuli.symbol_set import load_set_file

LETTERS = shipped_file("letters.toml")


def _set_file(tmp_path, screens: str):
    text = LETTERS.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^(instructions = .*)$", lambda m: m.group(1) + "\n[set.screens]\n"
                  + screens, text, count=1)
    path = tmp_path / "set.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_the_shipped_set_file_documents_every_text_with_its_default():
    commented = dict(re.findall(r'(?m)^# (\w+) = "(.*)"$', LETTERS.read_text(encoding="utf-8")))
    assert {k: commented[k] for k in FIELDS} == asdict(ScreenTexts())


def test_a_translation_is_read_and_reaches_the_keypad(tmp_path):
    path = _set_file(tmp_path, 'answer = "JETZT ANTWORTEN"\ntime_left = "noch {seconds} s"\n')
    texts = load_set_file(path).screens
    assert texts.answer == "JETZT ANTWORTEN" and texts.time_left.format(seconds=3) == \
        "noch 3 s"
    assert texts.thank_you == ScreenTexts().thank_you  # the rest keep their defaults
    keypad = make_responder("keypad", seed=0, keys={"c": "C"}, texts=texts)
    assert keypad.texts is texts


@pytest.mark.parametrize("screens, message", [
    pytest.param('time_left = "noch {secs} s"\n',
                 r"set.screens.time_left: the field \{secs\} is not known here \(this text may "
                 r"use \{seconds\}\)", id="field"),
    pytest.param('paused = "PAUSE {seconds}"\n', r"\{seconds\} is not known here \(this text "
                 r"may use no field\)", id="no-field"),
    pytest.param('answr = "x"\n', r"unknown key 'answr'.*did you mean 'answer'", id="stray"),
    pytest.param("answer = 3\n", r"set.screens.answer: expected a string, got 3", id="type"),
    pytest.param('answer = "  "\n', r"expected a non-empty one-line string", id="blank"),
    pytest.param('answer = "{"\n', r"expected a text with \{field\} placeholders", id="brace"),
])
def test_a_bad_text_is_a_one_line_error_naming_the_key(tmp_path, screens, message):
    with pytest.raises(ProtocolError, match=message):
        load_set_file(_set_file(tmp_path, screens))


@given(st.text(st.characters(blacklist_categories=("Cc", "Cs"), blacklist_characters="{}"),
               min_size=1, max_size=60).filter(str.strip))
def test_any_one_line_text_without_fields_is_kept_as_written(text):
    section = Section({"correct": text}, "set.toml", "set.screens", ProtocolError,
                      keys=FIELDS)
    assert ScreenTexts.from_section(section).correct == text
