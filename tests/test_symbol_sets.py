"""Stimulus sets: the digit set (the default) and the shipped capital letters, end to end.

Sources for the numbers checked here: the chance rate 1/n and the stimulus information
log2(n) bits of n equiprobable symbols (Shannon 1948; Miller 1956, "information transmitted"
of an absolute-identification task); everything else is this framework's own contract
(crs_study/data/letters.toml, crs_study/stimuli/symbol_set.py).
"""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
from _power_helpers import chi2_plan
from _session_helpers import tiny_letter_protocol, tiny_protocol
from hypothesis import given, settings
from hypothesis import strategies as st

import crs_study
from crs_study.analysis.load import load_datasets
from crs_study.dataset.schema import DEFAULT_TASK
from crs_study.errors import DatasetError, ProtocolError
from crs_study.paths import data_dir, shipped_file
from crs_study.protocol.loader import load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.session.responders import make_responder
from crs_study.session.responders.scripted import parse_script
from crs_study.session.runner import dataset_task
from crs_study.stimuli.digits import digit_set
from crs_study.stimuli.sets import load_stimulus_set
from crs_study.stimuli.symbol_set import load_set_file

LETTERS = ("C", "J", "L", "M", "N", "S", "U", "V", "W", "Z")


# --- the sets ------------------------------------------------------------------------------

def test_the_shipped_letter_set():
    letters = load_stimulus_set("letters")
    assert letters.symbols == LETTERS
    assert letters.keys == {s: s.lower() for s in LETTERS}
    assert (letters.task, letters.column, letters.noun) == ("letterid", "symbol", "letter")
    assert letters.chance_rate == pytest.approx(0.1)
    assert all(len(letters.glyph(s).strokes) == 1 for s in LETTERS)  # unistroke, no pen lift
    width, height = letters.glyph("C").mean_extent
    assert width == pytest.approx(0.9743, abs=1e-4) and height == pytest.approx(0.9986, abs=1e-4)


def test_the_digit_set_is_the_default_and_the_datasets_default_task():
    digits = load_stimulus_set()
    assert digits.symbols == tuple(range(10)) and digits.column == "digit"
    assert digits.keys == {d: str(d) for d in range(10)}
    # dataset.schema writes the digit task out (the analysis may not import the stimuli)
    assert dataset_task(digit_set()) == DEFAULT_TASK


def test_a_protocol_without_a_set_shows_digits_with_unchanged_plans():
    protocol = load_protocol("pilot")
    assert protocol.symbol_set.name == "digits" and protocol.symbols == tuple(range(10))
    assert not re.search(r"(?m)^set\s*=", protocol.text)


def _set_file(tmp_path, edit=lambda text: text) -> Path:
    path = tmp_path / "mine.toml"
    path.write_text(edit((data_dir() / "letters.toml").read_text(encoding="utf-8")),
                    encoding="utf-8")
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('key = "m"', 'key = "q"'),
     r"mine\.toml:\d+: symbols\.M\.key: 'q' pauses the session"),
    (lambda t: t.replace('key = "m"', 'key = "c"'),
     r"symbols\.M\.key: the key 'c' already answers 'C'; expected one key per symbol"),
    (lambda t: t.replace('task = "letterid"', 'task = "letter-id"'),
     r"set\.task: expected a BIDS task label"),
    (lambda t: t.replace("format = 2", "format = 1"), r"format: expected 2"),
    (lambda t: t.replace('noun = "letter"', 'noun = "letter"\nnouns = "x"'),
     r"unknown key 'nouns'.*did you mean 'noun'"),
    (lambda t: t.replace("[symbols.Z]", '[symbols."n/a"]'), r"expected a symbol name"),
    (lambda t: t.split("[symbols.J]")[0], r"symbols: expected at least 2 symbols"),
    (lambda t: t.replace("[[0, 1], [0, 0], [1, 0]]", "[[0, 1], [0, 0], [1.5, 0]]"),
     r"symbols\.L\.strokes\[0\]\[2\]: expected x and y in the unit box"),
])
def test_a_bad_set_file_is_one_line_naming_the_key(tmp_path, edit, message):
    with pytest.raises(ProtocolError, match=message) as caught:
        load_set_file(_set_file(tmp_path, edit))
    assert "\n" not in str(caught.value)


_LABEL = st.text("ABCDEFGHIJKLMNOPRSTUVWXYZ0123456789", min_size=1, max_size=3)
_POINT = st.tuples(st.floats(0, 1), st.floats(0, 1))


@settings(max_examples=40, deadline=None)
@given(labels=st.lists(_LABEL, min_size=2, max_size=8, unique=True),
       strokes=st.lists(st.lists(_POINT, min_size=2, max_size=5), min_size=8, max_size=8))
def test_any_valid_set_file_reads_back_in_order(tmp_path_factory, labels, strokes):
    keys = "abcdefghijklmnoprstuvwxyz"
    body = ['format = 2', '[set]', 'name = "mine"', 'noun = "shape"', 'task = "shapeid"',
            'title = "shapes"', 'description = "d"', 'instructions = "i"']
    for i, label in enumerate(labels):
        points = [*strokes[i], (0.0, 0.0), (1.0, 1.0)]  # a length > 0, extents > 0
        body += [f'[symbols."{label}"]', f'key = "{keys[i]}"',
                 "strokes = [[" + ", ".join(f"[{x!r}, {y!r}]" for x, y in points) + "]]"]
    path = tmp_path_factory.mktemp("set") / "set.toml"
    path.write_text("\n".join(body) + "\n", encoding="utf-8")
    loaded = load_set_file(path)
    assert loaded.symbols == tuple(labels)
    assert loaded.keys == {label: keys[i] for i, label in enumerate(labels)}
    assert loaded.chance_rate == pytest.approx(1 / len(labels))


# --- protocols -----------------------------------------------------------------------------

def test_the_letter_protocol_spells_its_keys_by_the_set(tmp_path):
    protocol = load_protocol("letter_identification")
    assert protocol.symbols == LETTERS and protocol.symbol_set.task == "letterid"
    assert protocol.responses.keys == tuple(s.lower() for s in LETTERS)
    text = shipped_file("protocols/letter_identification.toml").read_text(encoding="utf-8")
    digit_keys = tmp_path / "digit_keys.toml"
    digit_keys.write_text(text.replace("symbols = [", "digits = ["), encoding="utf-8")
    with pytest.raises(ProtocolError,
                       match=r"stimulus: unknown key .digits. \(valid keys: .*symbols\)"):
        load_protocol(digit_keys, check_device=False)
    digit_shown = tmp_path / "digit_shown.toml"
    digit_shown.write_text(text.replace('symbols = ["C", "J"', 'symbols = [7, "J"'),
                           encoding="utf-8")
    with pytest.raises(ProtocolError, match=r"stimulus\.symbols\[0\]: expected a letter "
                       r"C, J, L to N, S, U to W, Z, got 7"):
        load_protocol(digit_shown, check_device=False)
    no_keys = tmp_path / "no_keys.toml"
    no_keys.write_text(re.sub(r"(?m)^keys = .*\n", "", text), encoding="utf-8")
    assert load_protocol(no_keys, check_device=False).responses.keys == \
        protocol.responses.keys  # the set's own keys


def test_a_set_file_named_by_a_protocol_is_read_relative_to_it(tmp_path):
    _set_file(tmp_path, lambda t: t.replace('name = "letters"', 'name = "mine"'))
    path = tiny_letter_protocol(tmp_path)
    path.write_text(path.read_text().replace('set = "letters"', 'set = "mine.toml"'))
    protocol = load_protocol(path)
    assert protocol.symbol_set.name == "mine" and protocol.symbols == ("C", "L", "S")
    broken = tmp_path / "broken.toml"
    broken.write_text(path.read_text().replace('set = "mine.toml"', 'set = "nothere.toml"'))
    with pytest.raises(ProtocolError, match=r"stimulus\.set: expected a shipped stimulus set "
                       r"or a set file, got 'nothere.toml'"):
        load_protocol(broken)


def test_letter_plans_keep_the_run_constraint():
    protocol = load_protocol("letter_identification")
    plan = make_plan(protocol, "p1", 1, 0)
    for block in range(len(plan.block_conditions)):
        shown = [t.symbol for t in plan.trials if t.block == block]
        runs = [len(list(g)) for _, g in itertools.groupby(shown)]
        assert max(runs) <= protocol.design.max_same_symbol_run
    tests = [t for t in plan.trials if t.trial_type == "test"]
    assert sorted({t.symbol for t in tests}) == sorted(LETTERS)


def test_a_changed_letter_protocol_is_written_and_read_back(tmp_path):
    protocol = load_protocol(tiny_letter_protocol(tmp_path))
    settled = load_protocol(replace(protocol, design=replace(protocol.design, repetitions=2)))
    assert 'set = "letters"' in settled.text and "max_same_symbol_run = 2" in settled.text
    assert settled.symbols == protocol.symbols and settled.design.repetitions == 2


# --- responders ----------------------------------------------------------------------------

def test_the_keypad_answers_with_the_sets_keys():
    protocol = load_protocol("letter_identification")
    keypad = make_responder("keypad", seed=0, protocol=protocol)
    assert keypad.keys == {s.lower(): s for s in LETTERS}


def test_a_script_of_letters(tmp_path):
    letters = load_stimulus_set("letters")
    assert parse_script("symbol\trt\nC\nn/a\nZ\t0.25\n", symbol_set=letters) == \
        [("C", 0.5), (None, 0.5), ("Z", 0.25)]
    with pytest.raises(Exception, match=r"<script>:1: .*got '7'"):
        parse_script("7\n", symbol_set=letters)


# --- end to end ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def letter_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("letters")
    protocol = tiny_letter_protocol(folder)
    result = crs_study.dry_run(protocol, participants=3, out=folder / "ds")
    return folder / "ds", result


def test_a_letter_dry_run_writes_a_letterid_dataset(letter_dataset):
    dataset, _ = letter_dataset
    files = sorted(p.name for p in dataset.glob("sub-*/ses-*/beh/*_beh.tsv"))
    assert files == [f"sub-sim0{i}_ses-1_task-letterid_beh.tsv" for i in (1, 2, 3)]
    header = (dataset / "sub-sim01/ses-1/beh" / files[0]).read_text().splitlines()[0]
    assert header.split("\t")[5] == "symbol"
    columns = json.loads((dataset / "task-letterid_beh.json").read_text())
    assert columns["TaskName"] == "letterid"
    assert columns["symbol"]["Levels"] == {s: f"the letter {s}" for s in LETTERS}
    assert not (dataset / "task-digitid_beh.json").exists()


def test_a_letter_dataset_is_analysed_with_the_sets_labels(letter_dataset):
    """The letter plan as shipped but for its p-value rule (chi2: this checks the labels; the
    parametric bootstrap of three participants' 18 trials, separated data, costs minutes and
    is tested on its own in test_analysis_bootstrap.py)."""
    dataset, _ = letter_dataset
    analysis = crs_study.analyze(dataset, chi2_plan("letter_identification"), write=False)
    accuracy = analysis.accuracy.to_frame()
    assert list(accuracy["condition"]) == ["pixel-only", "crs"]
    assert analysis.accuracy.chance == pytest.approx(1 / 3)   # three letters shown
    assert list(analysis.accuracy.by_symbol.columns[:2]) == ["symbol", "condition"]
    assert {name.split(":")[0] for name in analysis.primary.model["random_effects"]} == {
        "participant", "symbol"}
    for result in analysis.confusions.values():
        assert set(result.counts.index) <= {"C", "L", "S"}
        assert result.stimulus_bits == pytest.approx(math.log2(3))
    results = analysis.to_dict()
    assert "accuracy_by_symbol" in results and "per_symbol" in results
    assert "accuracy_by_digit" not in results
    assert "'symbol_height'" in analysis.psychometric.note and "digit_height" not in \
        analysis.psychometric.note  # the size column as letter datasets name it


def test_one_analysis_takes_one_task(letter_dataset, tmp_path):
    dataset = tmp_path / "both"
    shutil.copytree(letter_dataset[0], dataset)
    crs_study.dry_run(tiny_protocol(tmp_path), participants=1, out=dataset, responder="random",
                      prefix="simdig")
    with pytest.raises(DatasetError, match=r"several tasks: digitid .*letterid"):
        load_datasets(dataset)
    letters = load_datasets(dataset, task="letterid")
    assert set(letters.trials["participant"]) == {"sim01", "sim02", "sim03"}
    digits = load_datasets(dataset, task="digitid")
    assert "digit" in digits.trials.columns and digits.trials["digit"].dtype == "int64"
