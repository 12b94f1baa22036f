"""Stimulus levels ([levels]): parsing, device checks, plans, stimuli, dataset column, observer.

The shipped psychometric protocol (protocols/digit_size_psychometric.toml) and small level
protocols written here go through the same code as the fixed-stimulus protocols; a protocol
without [levels] is pinned unchanged by tests/test_plan.py.
"""

from __future__ import annotations

import copy
import csv
import json
import tomllib
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_protocol import dump_toml

from crs_study.dataset import column_dictionary, schema
from crs_study.errors import ProtocolError
from crs_study.paths import shipped_file
from crs_study.protocol import LEVEL_PARAMETERS, load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.stimuli.stimulus import make_stimulus

PSYCHOMETRIC = shipped_file("protocols/digit_size_psychometric.toml")
BASE = tomllib.loads(PSYCHOMETRIC.read_text())


def speed_protocol(values: list, **design) -> dict:
    """The psychometric protocol turned into a stroke-speed one (fixed 0.81 x 0.49 digits)."""
    data = copy.deepcopy(BASE)
    data["stimulus"].pop("stroke_speed_mm_s")
    data["stimulus"]["digit_height_pitch"] = 0.81
    data["stimulus"]["digit_width_pitch"] = 0.49
    data["levels"] = {"parameter": "stroke_speed_mm_s", "values": values}
    data["design"].update(design)
    return data


def write(tmp_path, data: dict, name: str = "levels.toml"):
    path = tmp_path / name
    path.write_text(dump_toml(data))
    return path


def load(tmp_path, data: dict, **kwargs):
    return load_protocol(write(tmp_path, data), **kwargs)


# --- parsing ----------------------------------------------------------------------------------

def test_shipped_psychometric_protocol_varies_digit_height():
    protocol = load_protocol(PSYCHOMETRIC)
    assert protocol.levels.parameter == "digit_height_pitch"
    assert protocol.levels.column == "digit_height" and protocol.levels.units == "pitch"
    assert protocol.level_values == (0.3, 0.5, 0.81, 1.2, 1.5)
    spec = protocol.stimulus_at(1.2)
    assert spec.symbol_height_pitch == 1.2
    assert spec.symbol_width_pitch == pytest.approx(1.2 * 0.605)
    assert spec.stroke_speed_mm_s == 20.0
    # every level is checked on the device: its own path-inside line
    assert sum("bump centre path inside" in c for c in protocol.checks) == 5


def test_protocol_without_levels_is_unchanged():
    protocol = load_protocol(shipped_file("protocols/digit_identification.toml"))
    assert protocol.levels is None and protocol.level_values == (None,)
    assert protocol.stimulus_at(None) is protocol.stimulus
    with pytest.raises(ProtocolError, match="varies no level, got level 0.5"):
        protocol.stimulus_at(0.5)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["levels"].update(parameter="bump_height_mm"),
     r"levels.parameter: expected one of \['digit_height_pitch', 'stroke_speed_mm_s'\], "
     r"got 'bump_height_mm'"),
    (lambda d: d["levels"].update(values=[]), r"levels.values: expected 2 to 20 levels"),
    (lambda d: d["levels"].update(values=[0.81]), r"levels.values: expected 2 to 20 levels"),
    (lambda d: d["levels"].update(values=0.81), r"levels.values: expected an array, got 0.81"),
    (lambda d: d["levels"].update(values=[0.5, "1"]),
     r"levels.values\[1\]: expected a number 0.01 to 20 \(digit_height_pitch\), got '1'"),
    (lambda d: d["levels"].update(values=[0.5, True]), r"levels.values\[1\]: .*got True"),
    (lambda d: d["levels"].update(values=[0.5, 0.0]), r"levels.values\[1\]: .*got 0.0"),
    (lambda d: d["levels"].update(values=[0.5, 0.8, 0.5]),
     r"levels.values: a level appears twice in \[0.5, 0.8, 0.5\]"),
    (lambda d: d["levels"].update(values=[1, 1.0]), r"a level appears twice"),
    (lambda d: d["levels"].pop("width_to_height"),
     r"levels: missing required key 'width_to_height'"),
    (lambda d: d["levels"].update(step=1), r"levels: unknown key 'step'"),
    (lambda d: d["stimulus"].update(digit_height_pitch=0.81),
     r"stimulus.digit_height_pitch: set by \[levels\] .*remove it from \[stimulus\], got 0.81"),
    (lambda d: d["stimulus"].update(digit_width_pitch=0.49),
     r"stimulus.digit_width_pitch: set by \[levels\]"),
    # 3.4 pitch is 102 mm: taller than the crs2d hexagon (104 mm corner to corner, less at
    # the width of the digit) -- the device check names the level
    (lambda d: d["levels"].update(values=[0.5, 3.4]),
     r"levels.values\[1\]: at digit_height_pitch = 3.4: stimulus.digit_height_pitch: "
     r"the bump centre leaves the pixel area"),
])
def test_bad_levels_are_one_line_errors(tmp_path, edit, message):
    data = copy.deepcopy(BASE)
    edit(data)
    with pytest.raises(ProtocolError, match=message) as info:
        load(tmp_path, data)
    text = str(info.value)
    assert "\n" not in text and text.startswith(str(tmp_path / "levels.toml") + ":")


def test_errors_carry_the_line_of_the_key(tmp_path):
    data = copy.deepcopy(BASE)
    data["levels"]["values"] = [0.5, 3.4]
    path = write(tmp_path, data)
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                if t.startswith("values ="))
    with pytest.raises(ProtocolError, match=rf"levels.toml:{line}: levels.values\[1\]"):
        load_protocol(path)


def test_speed_levels(tmp_path):
    protocol = load(tmp_path, speed_protocol([10, 20, 40]))
    assert protocol.levels.column == "stroke_speed" and protocol.levels.units == "mm/s"
    assert protocol.stimulus_at(40.0).stroke_speed_mm_s == 40.0
    with pytest.raises(ProtocolError, match=r"levels.width_to_height: only used with "
                       r"parameter = \"digit_height_pitch\""):
        data = speed_protocol([10, 20])
        data["levels"]["width_to_height"] = 0.6
        load(tmp_path, data)
    with pytest.raises(ProtocolError, match=r"stimulus.stroke_speed_mm_s: set by \[levels\]"):
        data = speed_protocol([10, 20])
        data["stimulus"]["stroke_speed_mm_s"] = 20.0
        load(tmp_path, data)
    with pytest.raises(ProtocolError, match=r"levels.values\[0\]: expected a number 1 to "
                       r"1000 \(stroke_speed_mm_s\), got 0.5"):
        load(tmp_path, speed_protocol([0.5, 20]))


BAD_VALUE = st.one_of(
    st.booleans(), st.text(alphabet="abc 1.-", max_size=3), st.none().map(lambda _: {"a": 1}),
    st.floats(max_value=0.0099, allow_nan=False, allow_infinity=False),
    st.floats(min_value=1000.01, allow_nan=False, allow_infinity=False),
    st.lists(st.integers(), max_size=2),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(parameter=st.sampled_from(sorted(LEVEL_PARAMETERS)), good=st.lists(
    st.floats(min_value=1.0, max_value=1.6), min_size=1, max_size=4, unique=True),
    bad=BAD_VALUE, where=st.integers(0, 4))
def test_malformed_level_values_are_refused_in_one_line(tmp_path, parameter, good, bad, where):
    """Any value that is not a number in range makes the protocol a one-line error naming
    levels.values (never a traceback, never accepted)."""
    data = speed_protocol([]) if parameter == "stroke_speed_mm_s" else copy.deepcopy(BASE)
    values = [v * 10 if parameter == "stroke_speed_mm_s" else v for v in good]
    values.insert(min(where, len(values)), bad)
    data["levels"]["values"] = values
    with pytest.raises(ProtocolError, match=r"levels\.values") as info:
        load(tmp_path, data, check_device=False)
    assert "\n" not in str(info.value)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(values=st.lists(st.floats(min_value=0.2, max_value=1.2), min_size=2, max_size=5,
                       unique=True).filter(lambda v: len({float(x) for x in v}) == len(v)),
       ratio=st.floats(min_value=0.5, max_value=0.7))
def test_valid_height_levels_parse_and_fit_the_display(tmp_path, values, ratio):
    """Heights up to 1.2 pitch (36 mm) at width ratios 0.5-0.7 fit crs2d: accepted, each
    level's spec has the value and the width follows it. (Larger digits reach the CRS
    limits: at 1.75 pitch x 0.5 the beams would collapse on the digit 0, and the device
    check refuses it, as it must.)"""
    data = copy.deepcopy(BASE)
    data["levels"] = {"parameter": "digit_height_pitch", "values": values,
                      "width_to_height": ratio}
    protocol = load(tmp_path, data)
    assert protocol.level_values == tuple(float(v) for v in values)
    for v in values:
        spec = protocol.stimulus_at(v)
        assert spec.symbol_height_pitch == v
        assert spec.symbol_width_pitch == pytest.approx(v * ratio)


# --- plan -------------------------------------------------------------------------------------

def test_plan_crosses_levels_with_conditions_and_digits():
    protocol = load_protocol(PSYCHOMETRIC)
    plan = make_plan(protocol, "p1", 1, 0)
    test = [t for t in plan.trials if t.trial_type == "test"]
    cells = Counter((t.condition, t.symbol, t.level) for t in test)
    assert len(cells) == 2 * 10 * 5 and set(cells.values()) == {protocol.design.repetitions}
    practice = [t for t in plan.trials if t.trial_type == "practice"]
    for condition in protocol.conditions:  # 5 practice trials: each level once
        levels = sorted(t.level for t in practice if t.condition == condition)
        assert levels == sorted(protocol.level_values)
    for block in {t.block for t in plan.trials}:  # the run constraint, practice included
        digits = [t.symbol for t in plan.trials if t.block == block]
        runs = max(len(list(g)) for _, g in __import__("itertools").groupby(digits))
        assert runs <= protocol.design.max_same_symbol_run
    assert plan.count("test", "crs", 0.3) == 10


def test_plan_with_levels_is_deterministic_and_hashed(tmp_path):
    protocol = load_protocol(PSYCHOMETRIC)
    one, two = make_plan(protocol, "p1", 1, 1), make_plan(protocol, "p1", 1, 1)
    assert one == two and one.sha256() == two.sha256()
    assert make_plan(protocol, "p2", 1, 1).sha256() != one.sha256()
    # the same trials with other level values: a different fingerprint
    data = copy.deepcopy(BASE)
    data["levels"]["values"] = [0.3, 0.5, 0.81, 1.2, 1.4]
    other = make_plan(load(tmp_path, data), "p1", 1, 1)
    assert other.seed == one.seed
    assert [(t.condition, t.symbol) for t in other.trials] == \
        [(t.condition, t.symbol) for t in one.trials]
    assert other.sha256() != one.sha256()


# --- stimulus and observer --------------------------------------------------------------------

def test_stimulus_per_digit_and_level(layout2d):
    protocol = load_protocol(PSYCHOMETRIC)
    small, large = (make_stimulus(protocol, layout2d, 3, v) for v in (0.5, 1.5))
    assert small is make_stimulus(protocol, layout2d, 3, 0.5)  # cached
    extent = [np.ptp(s.centres_mm[s.drawn], axis=0) for s in (small, large)]
    # the digit keeps its shape: extents in proportion to the heights (1.5 / 0.5)
    # (within 2 %: the path is sampled at whole frames, so its end points move a little)
    assert extent[1] == pytest.approx(extent[0] * 1.5 / 0.5, rel=0.02)
    assert large.n_frames > small.n_frames  # same speed, longer path


def test_observer_templates_are_per_level(layout2d):
    from crs_study.session.responders.observer import PerceptualObserver

    protocol = load_protocol(PSYCHOMETRIC)
    observer = PerceptualObserver(layout2d, protocol, seed=1)
    # the templates of a digit at two heights differ in size by the height ratio
    size = [np.sqrt(np.mean(np.sum(observer.template(8, v) ** 2, axis=1))) for v in (0.5, 1.2)]
    assert size[1] / size[0] == pytest.approx(1.2 / 0.5, rel=0.02)  # whole-frame sampling
    # a bigger digit puts its templates further apart (in mm): the decision is easier
    spread = [np.mean([np.sqrt(np.mean(np.sum((observer.template(a, v)
                                               - observer.template(b, v)) ** 2, axis=1)))
                       for a in range(10) for b in range(a)]) for v in (0.5, 1.2)]
    assert spread[1] > 2 * spread[0]
    # the sensing window holds every drawn path: at 1.5 pitch the 7 spans 1.02 x 1.51 pitch
    # (its box, 0.605 x 1.5 / W by 1.5 / H with W = 0.8913, H = 0.9958;
    # crs_study/stimuli/digits.py),
    # a half-diagonal of 27 mm
    reach = max(np.hypot(*make_stimulus(protocol, layout2d, d, v).centres_mm.T).max()
                for d in protocol.symbols for v in protocol.level_values)
    assert observer._gx.max() - observer._gx.mean() >= reach


# --- dataset, end to end ----------------------------------------------------------------------

def test_level_columns_in_schema_and_dictionary():
    assert schema.trial_columns() == tuple(schema.TRIAL_COLUMNS)
    columns = schema.trial_columns("digit_height")
    assert columns[columns.index("digit") + 1] == "digit_height"
    with pytest.raises(ValueError, match="expected a level column"):
        schema.trial_columns("bump_size")
    from crs_study.analysis.plan import KNOWN_LEVEL_COLUMNS

    dictionary = column_dictionary()
    for parameter, (column, units, _, _) in LEVEL_PARAMETERS.items():
        assert column in KNOWN_LEVEL_COLUMNS and column in schema.LEVEL_COLUMNS
        assert dictionary[column]["Units"] == units, parameter


def test_dry_run_of_a_tiny_level_protocol(tmp_path):
    """Two digits, three speeds, one condition: the TSV has the stroke_speed column, each
    (digit, speed) cell once, and the analysis finds the level column; a rerun is a no-op."""
    from crs_study.analysis.psychometric import find_level_column
    from crs_study.session.dry_runs import dry_run

    data = speed_protocol([10, 20, 40], repetitions=1, practice_trials=0, break_every=0,
                          counterbalancing="none", inter_trial_interval_s=0.5)
    data["stimulus"]["digits"] = [1, 7]
    data["responses"]["keys"] = ["1", "7"]
    data["conditions"] = {"names": ["crs"]}
    path = write(tmp_path, data)
    results = dry_run(path, 1, tmp_path / "ds")
    assert [r.status for r in results] == ["complete"]
    with open(results[0].tsv, newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    assert list(rows[0])[list(rows[0]).index("digit") + 1] == "stroke_speed"
    assert Counter((r["digit"], float(r["stroke_speed"])) for r in rows) == \
        {(d, v): 1 for d in ("1", "7") for v in (10.0, 20.0, 40.0)}
    # frames per trial fall with the speed (the same path drawn faster)
    frames = {float(r["stroke_speed"]): int(r["frames"]) for r in rows if r["digit"] == "7"}
    assert frames[10.0] > frames[20.0] > frames[40.0]
    sidecar = json.loads(results[0].sidecar.read_text())
    assert "stroke_speed_mm_s" in sidecar["Protocol"]
    import pandas as pd

    assert find_level_column(pd.DataFrame({"stroke_speed": [float(r["stroke_speed"])
                                                            for r in rows]})) == "stroke_speed"
    again = dry_run(path, 1, tmp_path / "ds")
    assert [r.status for r in again] == ["already-complete"]


def test_validate_prints_levels_and_counts(capsys):
    from crs_study.cli import main

    assert main(["validate", str(PSYCHOMETRIC)]) == 0
    out = capsys.readouterr().out
    assert "levels: digit_height_pitch = 0.3, 0.5, 0.81, 1.2, 1.5 (pitch; dataset column " \
        "digit_height; width = 0.605 x height)" in out
    assert "  digit_height_pitch = 0.81: pixel-only 1 practice + 10 test, crs 1 practice + " \
        "10 test; frames per trial" in out
    assert main(["validate", str(PSYCHOMETRIC), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    per_level = summary["levels"]["per_level"]
    assert sum(v["per_condition"]["crs"]["test"] for v in per_level.values()) == \
        summary["trials"]["per_condition"]["crs"]["test"] == 50
