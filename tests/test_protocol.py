"""Protocol files: strict reading, line numbers, checks on the device (crs_study/protocol/)."""

from __future__ import annotations

import copy
import json
import re
import tomllib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.errors import ProtocolError
from crs_study.paths import shipped_file
from crs_study.protocol import OPTIONAL_KEYS, find_line, load_protocol

SHIPPED = shipped_file("protocols/digit_identification.toml")
PILOT = shipped_file("protocols/pilot.toml")


def shipped_data() -> dict:
    return tomllib.loads(SHIPPED.read_text())


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _value(k)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        # raw non-ASCII (json's \uXXXX surrogate pairs are no TOML escape); DEL escaped
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def dump_toml(data: dict) -> str:
    """A small TOML writer for the protocol's shape (tables of scalars, arrays, sub-tables)."""
    lines = [f"{_key(k)} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict)]

    def table(name: str, body: dict) -> None:
        lines.append(f"[{name}]")
        lines.extend(f"{_key(k)} = {_value(v)}" for k, v in body.items()
                     if not isinstance(v, dict))
        for k, v in body.items():
            if isinstance(v, dict):
                table(f"{name}.{_key(k)}", v)

    for k, v in data.items():
        if isinstance(v, dict):
            table(_key(k), v)
    return "\n".join(lines) + "\n"


def write(tmp_path, data: dict, name: str = "protocol.toml"):
    path = tmp_path / name
    path.write_text(dump_toml(data))
    return path


def edited(**changes) -> dict:
    """The shipped protocol with ``table__key=value`` changes (value ... deletes the key)."""
    data = copy.deepcopy(shipped_data())
    for dotted, value in changes.items():
        table, key = dotted.split("__")
        if value is ...:
            del data[table][key]
        else:
            data[table][key] = value
    return data


def test_shipped_protocols_load_with_the_contract_fields():
    for path in (SHIPPED, PILOT):
        p = load_protocol(path)
        assert p.text == path.read_text()
        import hashlib

        assert p.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
        assert p.conditions == ("pixel-only", "crs")
        assert p.frame_rate_hz == 15.0
        assert p.time_limit_s == 10.0
        assert p.feedback_practice and not p.feedback_test
        assert p.consent_form == "consent/consent_form.md" and p.consent_form_version == "1.0"
        assert p.layout().name == "crs2d"
        assert p.device == "crs2d" and p.analysis_plan.endswith(".toml")
        assert len(p.checks) >= 8


def test_shipped_protocol_matches_the_paper():
    p = load_protocol(SHIPPED)
    s = p.stimulus
    # Wang, Meng & Chen 2025: digits 0.81 x 0.49 pitch, 90 mm bump (Eq. 7), pixel-only vs CRS.
    assert (s.symbol_height_pitch, s.symbol_width_pitch, s.bump_diameter_mm) == (0.81, 0.49, 90)
    assert s.symbols == tuple(range(10))
    assert p.design.ordering == "blocked" and p.design.counterbalancing != "none"
    assert p.design.practice_trials > 0 and p.design.break_every > 0


def test_key_for_and_symbol_for_key():
    p = load_protocol(PILOT)
    assert p.key_for(7) == "7" and p.symbol_for_key("7") == 7 and p.symbol_for_key("x") is None
    assert p.prompt("crs").startswith("CRS block")


@pytest.mark.parametrize("changes, match", [
    pytest.param({"design__repetitions": 0}, r"design.repetitions: expected a whole number >= 1"
                 r", got 0", id="range"),
    pytest.param({"design__repetitions": 2.5}, r"design.repetitions: expected a whole number, "
                 r"got 2.5", id="type-float"),
    pytest.param({"stimulus__bump_height_mm": "5"}, r"stimulus.bump_height_mm: expected a "
                 r"number, got '5'", id="type-string"),
    pytest.param({"stimulus__placement": "corner"}, r"stimulus.placement: expected one of "
                 r"\['centre', 'offset'\], got 'corner'", id="choice"),
    pytest.param({"stimulus__digits": [1, 1, 2]}, r"stimulus.digits: a digit appears twice",
                 id="duplicate-digit"),
    pytest.param({"stimulus__digits": [1, 12]}, r"stimulus.digits\[1\]: expected a digit 0 to "
                 r"9, got 12", id="digit-range"),
    pytest.param({"stimulus__digits": [3]}, r"at least 2 digits", id="one-digit"),
    pytest.param({"responses__keys": ["a", "b"]}, r"responses.keys: expected 10 keys",
                 id="key-count"),
    pytest.param({"responses__keys": ["0"] * 10}, r"responses.keys: a key appears twice",
                 id="key-duplicate"),
    pytest.param({"responses__keys": ["00"] + [str(i) for i in range(1, 10)]},
                 r"responses.keys\[0\]: expected a single printable character", id="key-long"),
    pytest.param({"conditions__names": ["pixel-only", "optimised"]},
                 r"conditions.names\[1\]: expected a registered condition.*'optimised'",
                 id="condition"),
    pytest.param({"design__counterbalancing": "abba", "design__repetitions": 1},
                 r"design.counterbalancing: \"abba\" splits", id="abba-reps"),
    pytest.param({"design__ordering": "interleaved"}, r"design.counterbalancing: interleaved",
                 id="interleaved-counterbalanced"),
    pytest.param({"design__ordering": "interleaved", "design__counterbalancing": "none"},
                 r"conditions.prompts: an interleaved design changes condition from trial to "
                 r"trial", id="interleaved-with-prompts"),
    pytest.param({"responses__keys": ["q"] + [str(i) for i in range(1, 10)]},
                 r"responses.keys: 'q' pauses the session at the keypad", id="pause-key"),
    pytest.param({"stimulus__placement": "offset"}, r"stimulus.offset_mm: missing",
                 id="offset-missing"),
    pytest.param({"stimulus__offset_mm": [1.0, 2.0]}, r"stimulus.offset_mm: only used with "
                 r"placement = \"offset\"", id="offset-unused"),
    pytest.param({"study__id": "my study"}, r"study.id: expected letters", id="id"),
    pytest.param({"study__version": ""}, r"study.version: expected a non-empty", id="version"),
    pytest.param({"study__device": "crs9d"}, r"study.device: expected a built-in device",
                 id="device"),
    pytest.param({"study__colour": "red"}, r"study: unknown key 'colour' \(valid keys: ",
                 id="unknown"),
    pytest.param({"design__repetitions": ...}, r"design: missing required key 'repetitions'",
                 id="missing"),
    pytest.param({"responses__feedback": True}, r"responses.feedback: expected a string, got "
                 r"True", id="bool"),
    pytest.param({"design__inter_trial_interval_s": float("nan")},
                 r"inter_trial_interval_s: expected a finite number, got nan", id="nan"),
])
def test_malformed_values_are_one_line_errors_naming_file_line_key(tmp_path, changes, match):
    path = write(tmp_path, edited(**changes))
    with pytest.raises(ProtocolError, match=match) as info:
        load_protocol(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}:")
    assert re.match(rf"{re.escape(str(path))}:\d+: ", message), message


def test_line_number_points_at_the_key(tmp_path):
    text = SHIPPED.read_text().replace("repetitions = 5", "repetitions = -5")
    path = tmp_path / "p.toml"
    path.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.startswith("repetitions"))
    with pytest.raises(ProtocolError, match=rf"p.toml:{line}: design.repetitions: .* got -5"):
        load_protocol(path)


def test_unknown_key_line_points_at_the_stray_key(tmp_path):
    text = SHIPPED.read_text().replace("[design]\n", "[design]\nrepetiton = 3\n")
    path = tmp_path / "p.toml"
    path.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.startswith("repetiton"))
    with pytest.raises(ProtocolError, match=rf":{line}: design: unknown key 'repetiton'"):
        load_protocol(path)


def test_find_line():
    text = "a = 1\n[t]\nx = 2\n[t.sub]\n\"y-z\" = 3\n[u]\ninline = {k = 1}\n"
    assert find_line(text, "a") == 1
    assert find_line(text, "t") == 2
    assert find_line(text, "t.x") == 3
    assert find_line(text, "t.sub.y-z") == 5
    assert find_line(text, "t.missing") == 2
    assert find_line(text, "u.inline.k") == 7
    assert find_line(text, "t.x[3]") == 3
    assert find_line(text, "nowhere") is None


def test_find_line_points_at_array_elements_and_skips_values_spanning_lines():
    text = ('[d.3]\n'
            '# a comment = 1\n'
            'strokes = [\n'                       # 3
            '  [[0, 0], [0.5, "a"]],  # x, [y]\n'  # 4: strokes[0]
            '  [ # comment ]\n'                   # 5: strokes[1]
            '    [0, 1],\n'
            '    [1, 1],\n'                       # 7: strokes[1][1]
            '  ],\n'
            ']\n'
            'v.w = [1,\n'                         # 10: a dotted key
            '  2, "x,]", 3]\n'                    # 11
            's = """\n'
            '[fake]\n'                            # inside a string: not a table
            'q = 1\n'
            '"""\n'
            'after = 2  # end\n')                # 16
    assert find_line(text, "d.3.strokes[0]") == 4
    assert find_line(text, "d.3.strokes[0][1]") == 4
    assert find_line(text, "d.3.strokes[1]") == 5
    assert find_line(text, "d.3.strokes[1][1]") == 7
    assert find_line(text, "d.3.strokes[2]") == 3  # no such element: the key's line
    assert find_line(text, "d.3.v.w") == 10
    assert find_line(text, "d.3.v.w[3]") == 11
    assert find_line(text, "d.3.after") == 16
    assert find_line(text, "fake.q") is None
    assert find_line(text, "d") == 1  # a table made by its first sub-table


def test_syntax_error_and_missing_file(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text("[study\nid = 1\n")
    with pytest.raises(ProtocolError, match=r"p.toml:1: not valid TOML: .*line 1, column 7"):
        load_protocol(path)
    with pytest.raises(ProtocolError, match=r"no such protocol file"):
        load_protocol(tmp_path / "absent.toml")
    with pytest.raises(ProtocolError, match=r"expected a protocol file, got a directory"):
        load_protocol(tmp_path)
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ProtocolError, match=r"cannot read"):
        load_protocol(tmp_path / "bin.toml")


def test_optional_keys_take_their_documented_defaults(tmp_path):
    data = edited(stimulus__stroke_pause_s=..., stimulus__start_hold_s=...,
                  stimulus__end_hold_s=..., design__practice_in=...,
                  design__break_duration_s=..., responses__time_limit_s=...,
                  responses__expected_response_s=..., study__title=...)
    del data["conditions"]["prompts"]
    p = load_protocol(write(tmp_path, data))
    assert p.stimulus.stroke_pause_s == OPTIONAL_KEYS["stimulus.stroke_pause_s"]
    assert p.stimulus.start_hold_s == OPTIONAL_KEYS["stimulus.start_hold_s"]
    assert p.design.practice_in == OPTIONAL_KEYS["design.practice_in"]
    assert p.time_limit_s is None
    assert p.prompt("crs") is None and p.title == ""


# --- checks against the device -------------------------------------------------------------

@pytest.mark.parametrize("changes, match", [
    pytest.param({"stimulus__bump_height_mm": 9.5}, r"stimulus.bump_height_mm: expected at "
                 r"most the pixel travel 9 mm, got 9.5", id="travel"),
    pytest.param({"stimulus__frame_rate_hz": 20.0}, r"stimulus.frame_rate_hz: expected at most "
                 r"15.00 frames/s .*66.7 ms.* got 20.0", id="wire"),
    pytest.param({"stimulus__frame_rate_hz": 5e-324}, r"stimulus.frame_rate_hz: expected a "
                 r"number >= 1(\.0)?, got 5e-324", id="rate-denormal"),
    pytest.param({"stimulus__stroke_speed_mm_s": 1.0, "stimulus__digit_height_pitch": 12.0},
                 r"stimulus.stroke_speed_mm_s: digit 0 would take \d+ s to draw; expected at "
                 r"most 120 s", id="too-slow"),
    pytest.param({"stimulus__digit_height_pitch": 4.5}, r"stimulus.digit_height_pitch: the "
                 r"bump centre leaves the pixel area.*got 4.5 \(the digits' height alone",
                 id="outside"),
    # the key at fault is named, not the other size key (the width was blamed on the height)
    pytest.param({"stimulus__digit_width_pitch": 4.0}, r"stimulus.digit_width_pitch: the "
                 r"bump centre leaves the pixel area.*got 4.0 \(the digits' width alone",
                 id="outside-width"),
    pytest.param({"stimulus__digit_width_pitch": 2.3, "stimulus__digit_height_pitch": 2.6},
                 r"stimulus.digit_height_pitch: the bump centre leaves .* a corner leaves it: "
                 r"height and width 2.3 together", id="outside-corner"),
    pytest.param({"stimulus__placement": "offset", "stimulus__offset_mm": [50.0, 0.0]},
                 r"stimulus.offset_mm: the bump centre leaves the pixel area.*got \[50.0, 0.0\] "
                 r"\(the digits fit at the display centre\)", id="offset"),
    pytest.param({"stimulus__placement": "offset", "stimulus__offset_mm": [1.0, 0.0],
                  "stimulus__digit_width_pitch": 4.0},
                 r"stimulus.digit_width_pitch: the bump centre leaves", id="offset-but-width"),
    # z_f and l set the curvature together: both named, each with the bound it must meet
    # (l^2 kappa_y / (2 pi^2) = 400 * 0.0667 / 19.74 = 1.35 mm; sqrt(2 pi^2 5 / 0.0667) =
    # 38.5 mm)
    pytest.param({"stimulus__bump_diameter_mm": 20.0}, r"stimulus.bump_height_mm: the bump's "
                 r"curvature 0.2467/mm .*stimulus.bump_diameter_mm = 20.0\) exceeds the beam's "
                 r"yield curvature 0.0667/mm; expected bump_height_mm <= 1.35 at this diameter or "
                 r"bump_diameter_mm >= 38.\d at this height", id="yield"),
    pytest.param({"study__consent_form_version": "2.0"}, r"study.consent_form_version: expected "
                 r"the form's version '1.0'.* got '2.0'", id="consent-version"),
    pytest.param({"study__consent_form": "consent/none.md"}, r"study.consent_form: .*no such",
                 id="consent-missing"),
])
def test_device_checks(tmp_path, changes, match):
    path = write(tmp_path, edited(**changes))
    with pytest.raises(ProtocolError, match=match) as info:
        load_protocol(path)
    assert "\n" not in str(info.value)
    assert re.match(rf"{re.escape(str(path))}:\d+: ", str(info.value))


def test_curvature_check_is_the_paper_formula():
    # 2 pi^2 z_f / l^2 at z_f = 5, l = 20 (targets.Bump.curvature_max), against
    # 2 sigma_y / (E t) = 2 * 965 / (193e3 * 0.15) = 0.0667 /mm.
    assert 2 * 3.141592653589793**2 * 5 / 20**2 == pytest.approx(0.2467, abs=1e-4)


def _device_variant(tmp_path, **replacements) -> str:
    from crs_study.geometry.layout import device_file_path

    text = device_file_path("crs2d").read_text()
    for old, new in replacements.items():
        assert old in text
        text = text.replace(old, new)
    (tmp_path / "device.toml").write_text(text)
    return "device.toml"


def test_collapsing_device_is_refused_for_crs(tmp_path):
    # beta = 10 kPa: Delta = 3.87 / 10 < 1 (Eq. 4).
    device = _device_variant(tmp_path, **{"foundation_stiffness_kpa = 1.0":
                                          "foundation_stiffness_kpa = 10.0"})
    with pytest.raises(ProtocolError, match=r"conditions.names: the beams collapse .*Delta = "
                       r"0.39 < 1"):
        load_protocol(write(tmp_path, edited(study__device=device)))
    # Pixel-only alone does not use the beams.
    p = load_protocol(write(tmp_path, edited(study__device=device,
                                             conditions__names=["pixel-only"],
                                             conditions__prompts={}), "pixel.toml"))
    assert p.conditions == ("pixel-only",)


def test_boundary_feed_beyond_travel_is_refused(tmp_path):
    device = _device_variant(tmp_path, **{"boundary_travel_mm = 9.0":
                                          "boundary_travel_mm = 0.1"})
    with pytest.raises(ProtocolError, match=r"stimulus.bump_height_mm: digit \d cannot be "
                       r"shown: crs: setpoint out of range: beam \d+ (start|end)"):
        load_protocol(write(tmp_path, edited(study__device=device)))


def test_a_line_device_is_refused(tmp_path):
    with pytest.raises(ProtocolError, match=r"study.device: digits need a 2D display, got "
                       r"'crs1d'"):
        load_protocol(write(tmp_path, edited(study__device="crs1d")))


def test_own_strokes_file_relative_to_the_protocol(tmp_path):
    (tmp_path / "mine.toml").write_text(
        "format = 1\n[digits.1]\nstrokes = [[[0.5, 1], [0.5, 0]]]\n"
        "[digits.7]\nstrokes = [[[0, 1], [1, 1], [0.3, 0]]]\n")
    data = edited(stimulus__strokes_file="mine.toml", stimulus__digits=[1, 7],
                  responses__keys=["1", "7"])
    p = load_protocol(write(tmp_path, data))
    assert p.stimulus.strokes_file == str(tmp_path / "mine.toml")
    with pytest.raises(ProtocolError, match=r":\d+: stimulus.strokes_file: .*mine.toml defines no "
                       r"strokes for digits 0, 2, 3, 4, 5, 6, 8, 9 of stimulus.digits"):
        load_protocol(write(tmp_path, edited(stimulus__strokes_file="mine.toml"), "b.toml"))
    with pytest.raises(ProtocolError, match=r"stimulus.strokes_file: expected a strokes file"):
        load_protocol(write(tmp_path, edited(stimulus__strokes_file="none.toml"), "c.toml"))


@settings(max_examples=25, deadline=None)
@given(repetitions=st.integers(-3, 40), speed=st.floats(-5, 2000, allow_nan=False),
       height=st.floats(-1, 12), rate=st.floats(0, 30), digit_height=st.floats(0, 6))
def test_numeric_values_either_load_or_fail_in_one_line(tmp_path_factory, repetitions, speed,
                                                        height, rate, digit_height):
    data = edited(design__repetitions=repetitions, stimulus__stroke_speed_mm_s=speed,
                  stimulus__bump_height_mm=height, stimulus__frame_rate_hz=rate,
                  stimulus__digit_height_pitch=digit_height)
    path = write(tmp_path_factory.mktemp("num"), data)
    try:
        p = load_protocol(path)
    except ProtocolError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(path))
    else:
        assert p.design.repetitions == repetitions and 0 < height <= 9 and 1 <= rate <= 15


# --- odd but legal values warn (STYLE rule 5) ------------------------------------------------

@pytest.mark.parametrize("changes, key, match", [
    # 10 digits x 2 conditions x 40 + 20 practice = 820 trials of about 7.2 s and 32 breaks
    # of 30 s: 1.8 h
    pytest.param({"design__repetitions": 40}, "repetitions",
                 r"design.repetitions: the session is expected to take 1.8 h \(820 trials at "
                 r"repetitions = 40; .*\), over 1.5 h", id="long-session"),
    # 210 trials a block with no break: 24 min (the session, 47 min, is not too long)
    pytest.param({"design__repetitions": 20, "design__break_every": 0}, "break_every",
                 r"design.break_every: block \d runs 2\d min without a break \(break_every = 0: "
                 r"no breaks\), over 20 min", id="no-breaks"),
    pytest.param({"responses__time_limit_s": 120.0}, "time_limit_s",
                 r"responses.time_limit_s: 120.0 s is a long time limit \(over 60 s\)",
                 id="time-limit"),
    pytest.param({"design__inter_trial_interval_s": 0.0}, "inter_trial_interval_s",
                 r"design.inter_trial_interval_s: 0.0 s: the next digit starts less than 0.1 s",
                 id="iti-zero"),
    pytest.param({"stimulus__stroke_speed_mm_s": 3.0}, "stroke_speed_mm_s",
                 r"stimulus.stroke_speed_mm_s: 3.0 mm/s is slow: the longest digit takes \d\d s "
                 r"to draw, holds included \(over 15 s", id="slow"),
    # lag 120 mm/s x 75 ms = 9.0 mm > 24.3 mm / 4 (0.81 pitch of 30 mm)
    pytest.param({"stimulus__stroke_speed_mm_s": 120.0}, "stroke_speed_mm_s",
                 r"stimulus.stroke_speed_mm_s: 120.0 mm/s is fast: the device's 75 ms latency "
                 r"\(the paper's\) lags the bump by 9.0 mm, over a quarter of the digit's "
                 r"24.3 mm height", id="fast"),
])
def test_odd_values_warn_naming_file_line_key(tmp_path, changes, key, match):
    path = write(tmp_path, edited(**changes))
    protocol = load_protocol(path)  # legal: loaded, not refused
    assert len(protocol.warnings) == 1, protocol.warnings
    warning = protocol.warnings[0]
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                if t.startswith(f"{key} ="))
    assert warning.startswith(f"{path}:{line}: "), warning
    assert re.search(match, warning), warning
    assert "\n" not in warning


@pytest.mark.parametrize("changes", [
    pytest.param({}, id="shipped"),
    pytest.param({"design__repetitions": 25}, id="1.1-hours"),
    pytest.param({"design__break_every": 0}, id="7-minute-blocks-without-breaks"),
    pytest.param({"responses__time_limit_s": 60.0}, id="time-limit-60"),
    pytest.param({"design__inter_trial_interval_s": 0.1}, id="iti-0.1"),
    pytest.param({"stimulus__stroke_speed_mm_s": 80.0}, id="lag-6.0-mm"),
    pytest.param({"stimulus__stroke_speed_mm_s": 7.0}, id="slow-but-under-15-s"),
])
def test_ordinary_values_do_not_warn(tmp_path, changes):
    assert load_protocol(write(tmp_path, edited(**changes))).warnings == ()


def test_shipped_protocols_do_not_warn():
    for name in ("digit_identification", "pilot", "digit_size_psychometric"):
        assert load_protocol(shipped_file(f"protocols/{name}.toml")).warnings == ()


def test_a_varied_speed_warns_at_its_level(tmp_path):
    data = copy.deepcopy(shipped_data())
    del data["stimulus"]["stroke_speed_mm_s"]
    data["levels"] = {"parameter": "stroke_speed_mm_s", "values": [20.0, 160.0]}
    path = write(tmp_path, data)
    (warning,) = load_protocol(path).warnings
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                if t.startswith("values ="))
    assert warning.startswith(f"{path}:{line}: levels.values[1]: at stroke_speed_mm_s = 160: "
                              "160.0 mm/s is fast"), warning


def test_warnings_are_issued_as_crs_study_warnings(tmp_path):
    from crs_study.errors import CrsStudyWarning
    from crs_study.protocol import emit_warnings

    protocol = load_protocol(write(tmp_path, edited(design__inter_trial_interval_s=0.0)))
    with pytest.warns(CrsStudyWarning, match=r"design.inter_trial_interval_s: 0.0 s"):
        emit_warnings(protocol)


# --- where an error is: attributes, not text (nothing parses a message back) ----------------

def test_errors_carry_the_file_the_line_and_the_key_path(tmp_path):
    text = SHIPPED.read_text().replace("repetitions = 5", "repetitions = -5")
    path = tmp_path / "p.toml"
    path.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.startswith("repetitions"))
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    error = info.value
    assert (error.source, error.line, error.key_path) == (str(path), line, "design.repetitions")
    assert error.reason == "expected a whole number >= 1, got -5"
    # a device check names its key as well, and the line of the array element at fault
    data = copy.deepcopy(shipped_data())
    data["levels"] = {"parameter": "digit_height_pitch", "values": [0.5, 3.4],
                      "width_to_height": 0.605}
    for key in ("digit_height_pitch", "digit_width_pitch"):
        del data["stimulus"][key]
    path = write(tmp_path, data, "levels.toml")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    assert info.value.key_path == "levels.values[1]"
    assert info.value.line == next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                                   if t.startswith("values ="))


def test_a_misspelt_required_key_is_named_as_the_stray_key(tmp_path):
    text = SHIPPED.read_text().replace("repetitions = 5", "repetiton = 5")
    path = tmp_path / "p.toml"
    path.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.startswith("repetiton"))
    with pytest.raises(ProtocolError, match=rf"^{re.escape(str(path))}:{line}: design: unknown "
                       r"key 'repetiton' \(valid keys: break_duration_s, .*\); did you mean "
                       r"'repetitions'\?$") as info:
        load_protocol(path)
    assert info.value.key_path == "design.repetiton"


def test_a_misspelt_table_is_named_as_the_stray_table(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text(SHIPPED.read_text().replace("[design]", "[desing]"))
    with pytest.raises(ProtocolError, match=r"p.toml:\d+: unknown key 'desing' \(valid keys: "
                       r"adaptive, conditions, design, levels, responses, stimulus, study\); "
                       r"did you mean 'design'\?$"):
        load_protocol(path)


# --- the model checks its fields, from a file or from Python ---------------------------------

@pytest.mark.parametrize("table, changes, match", [
    pytest.param("design", {"repetitions": 0}, r"^design.repetitions: expected a whole number "
                 r">= 1, got 0$", id="repetitions"),
    pytest.param("design", {"ordering": "random"}, r"^design.ordering: expected one of "
                 r"\['blocked', 'interleaved'\], got 'random'$", id="ordering"),
    pytest.param("design", {"ordering": "interleaved"}, r"^design.counterbalancing: "
                 r"interleaved conditions have no block order", id="interleaved"),
    pytest.param("stimulus", {"frame_rate_hz": 0.5}, r"^stimulus.frame_rate_hz: expected a "
                 r"number >= 1, got 0.5$", id="frame-rate"),
    pytest.param("stimulus", {"symbols": (3,)}, r"^stimulus.digits: expected at least 2 digits",
                 id="one-digit"),
    pytest.param("stimulus", {"offset_mm": (5.0, 0.0)}, r"^stimulus.offset_mm: only used with "
                 r"placement = \"offset\"", id="offset-at-centre"),
    pytest.param("responses", {"keys": ("q",) + tuple("123456789")}, r"^responses.keys: 'q' "
                 r"pauses the session", id="pause-key"),
    pytest.param("responses", {"feedback": "always"}, r"^responses.feedback: expected one of",
                 id="feedback"),
    pytest.param("protocol", {"study_id": "my study"}, r"^study.id: expected letters",
                 id="study-id"),
    pytest.param("protocol", {"conditions": ("pixel-only", "crs", "crs")}, r"^conditions.names: "
                 r"a condition appears twice", id="conditions"),
])
def test_the_model_checks_fields_set_from_python(table, changes, match):
    from dataclasses import replace

    protocol = load_protocol(PILOT)
    target = protocol if table == "protocol" else getattr(protocol, table)
    with pytest.raises(ProtocolError, match=match) as info:
        replace(target, **changes)
    # no file: the message is the key path and the reason, as a file's would be after FILE:LINE
    assert info.value.source is None and info.value.line is None
    assert str(info.value) == f"{info.value.key_path}: {info.value.reason}"


#: keys whose every check is the model's: (table, key, dataclass field)
MODEL_KEYS = [("design", k, k) for k in ("repetitions", "ordering", "counterbalancing",
                                         "practice_trials", "practice_in",
                                         "break_every", "break_duration_s",
                                         "inter_trial_interval_s")] + \
    [("design", "max_same_digit_run", "max_same_symbol_run")] + \
    [("stimulus", k, k.replace("digit", "symbol")) for k in (
        "digit_height_pitch", "digit_width_pitch", "bump_diameter_mm", "bump_height_mm",
        "stroke_speed_mm_s", "frame_rate_hz", "stroke_pause_s", "start_hold_s",
        "end_hold_s")] + \
    [("responses", k, k) for k in ("time_limit_s", "feedback", "expected_response_s")] + \
    [("study", "id", "study_id"), ("study", "version", "version"), ("study", "title", "title")]

ANY_VALUE = st.one_of(st.integers(-5, 2000), st.floats(-10, 5000), st.booleans(),
                      st.sampled_from([float("nan"), float("inf"), "", " ", "x y", "none",
                                       "blocked", "abba", "latin", "every-block", "all", "1.0"]))


@settings(max_examples=120, deadline=None)
@given(where=st.sampled_from(MODEL_KEYS), value=ANY_VALUE)
def test_a_value_refused_in_a_file_and_from_python_reads_alike(tmp_path_factory, where, value):
    from dataclasses import replace

    table, key, name = where
    data = copy.deepcopy(shipped_data())
    data[table][key] = value
    path = write(tmp_path_factory.mktemp("alike"), data)
    base = load_protocol(PILOT, check_device=False)
    target = base if table == "study" else getattr(base, table)
    try:
        loaded = load_protocol(path, check_device=False)
    except ProtocolError as exc:
        with pytest.raises(ProtocolError) as info:
            replace(target, **{name: value})
        assert info.value.detail == exc.detail and exc.line is not None
    else:
        built = replace(target, **{name: value})
        stored = loaded if table == "study" else getattr(loaded, table)
        assert getattr(built, name) == getattr(stored, name)
