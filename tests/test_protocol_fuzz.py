"""Fuzzing: 500 malformed protocols, each refused with one line and no traceback.

Each example mutates the shipped protocol in a way that must make it invalid: delete a
required key or table, add an unknown key, give a key a value of the wrong type or out of
its range, or break the TOML syntax. Every example goes through the loader; one in ten also
goes through the command line (``crs_study.cli.main(["validate", path])``), which must exit 2
with exactly one line on stderr and no traceback.

Each message must also say where the fault is (:func:`where_expected`): the deleted key with
its table, the unknown key with its table and its line, the mutated key's full path and line
(for a value that breaks a device limit set by two keys, such as the bump's curvature, the
mutated key among those named), or the line of a syntax error.
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
import re
import tomllib

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_protocol import SHIPPED, dump_toml

from crs_study.cli import main
from crs_study.errors import ProtocolError
from crs_study.protocol import OPTIONAL_KEYS, load_protocol

BASE = tomllib.loads(SHIPPED.read_text())
BASE_TEXT = SHIPPED.read_text()
LEAVES = [(table, key) for table, body in BASE.items() for key, value in body.items()
          if not isinstance(value, dict)]
REQUIRED = [(t, k) for t, k in LEAVES if f"{t}.{k}" not in OPTIONAL_KEYS]

#: Values out of range (or otherwise refused) per key; each must fail on its own.
OUT_OF_RANGE = {
    ("study", "id"): ["", "has space", "-dash-first"],
    ("study", "version"): ["", "  "],
    ("study", "device"): ["crs3d", "missing.toml"],
    ("study", "consent_form"): ["consent/absent.md"],
    ("study", "consent_form_version"): ["9.9", ""],
    ("study", "analysis_plan"): [""],
    ("stimulus", "digits"): [[], [1], [0, 10], [-1, 2], [3, 3], [1.5, 2]],
    ("stimulus", "digit_height_pitch"): [0, -0.5, 25.0, 4.0],
    ("stimulus", "digit_width_pitch"): [0, -1, 21.0, 4.0],
    ("stimulus", "bump_diameter_mm"): [0, -90.0, 5000.0, 20.0],
    ("stimulus", "bump_height_mm"): [0, -5.0, 9.5, 150.0],
    ("stimulus", "stroke_speed_mm_s"): [0, 0.5, -20.0, 5000.0],
    ("stimulus", "placement"): ["middle", "CENTRE", ""],
    ("stimulus", "frame_rate_hz"): [0, -15.0, 16.0, 2000.0, math.inf, math.nan],
    ("stimulus", "stroke_pause_s"): [-0.1, 11.0],
    ("stimulus", "start_hold_s"): [-1.0, 60.0],
    ("stimulus", "end_hold_s"): [-1.0, 60.0],
    ("conditions", "names"): [[], ["pixel-only", "pixel-only"], ["holographic"]],
    ("design", "repetitions"): [0, -3, 1001],
    ("design", "ordering"): ["random", "mixed"],
    ("design", "counterbalancing"): ["ab", "latin-square", "none "],
    ("design", "max_same_digit_run"): [0, -1],
    ("design", "practice_trials"): [-1, 5000],
    ("design", "practice_in"): ["first", "never"],
    ("design", "break_every"): [-1],
    ("design", "break_duration_s"): [-5.0, 7200.0],
    ("design", "inter_trial_interval_s"): [-1.0, 61.0],
    ("responses", "keys"): [[], ["0"] * 10, ["ab"] + list("123456789"), [" "] + list("123456789")],
    ("responses", "time_limit_s"): [0, -1.0, 4000.0],
    ("responses", "feedback"): ["sometimes", "yes"],
    ("responses", "expected_response_s"): [-1.0, 4000.0],
}
# Every key with a range has an entry (a title may be any string).
assert set(OUT_OF_RANGE) == set(LEAVES) - {("study", "title")}

SYNTAX_BREAKERS = ["[", "key = ", "= 3", "x = [1,", 'y = "unterminated', "[study]",
                   "digits = 1", "a.b = 1\na = 2", "z = 1 2", "[[design]]", "\x00", "w = 0x"]


def wrong_type_values(value):
    """Values of another type than ``value`` that the key never accepts."""
    if isinstance(value, bool):
        return ["true", 1, [True]]
    if isinstance(value, int):
        return ["5", 2.5, True, [value], {"v": value}]
    if isinstance(value, float):
        return ["5.0", True, [value], {"v": value}]
    if isinstance(value, str):
        return [1, 2.5, False, [value], {"v": value}]
    if isinstance(value, list):
        return ["0,1,2", 3, True, {"v": 1}]
    raise TypeError(value)


@st.composite
def malformed(draw):
    """(kind, protocol text, what the message must name: see :func:`where_expected`)."""
    kind = draw(st.sampled_from(["delete", "delete-table", "unknown", "wrong-type",
                                 "out-of-range", "syntax"]))
    data = copy.deepcopy(BASE)
    if kind == "delete":
        table, key = draw(st.sampled_from(REQUIRED))
        del data[table][key]
        fault = (table, key)
    elif kind == "delete-table":
        table = draw(st.sampled_from(sorted(t for t in BASE if t != "conditions")))
        del data[table]
        fault = (None, table)
    elif kind == "unknown":
        name = draw(st.from_regex(r"[a-z][a-z0-9_]{0,12}", fullmatch=True))
        where = draw(st.sampled_from([None, *BASE]))
        target = data if where is None else data[where]
        if name in target:
            name += "_x"
        # text without lone surrogates, which no TOML file can hold (that would be a syntax
        # error, not the stray key this example is about)
        value = st.text(st.characters(exclude_categories=("Cs",)), max_size=5)
        target[name] = draw(st.one_of(st.integers(), value, st.booleans()))
        fault = (where, name)
    elif kind == "wrong-type":
        table, key = draw(st.sampled_from(LEAVES))
        data[table][key] = draw(st.sampled_from(wrong_type_values(BASE[table][key])))
        fault = (table, key)
    elif kind == "out-of-range":
        table, key = draw(st.sampled_from(sorted(OUT_OF_RANGE)))
        data[table][key] = draw(st.sampled_from(OUT_OF_RANGE[table, key]))
        fault = (table, key)
    if kind == "syntax":
        lines = BASE_TEXT.splitlines()
        at = draw(st.integers(0, len(lines)))
        lines.insert(at, draw(st.sampled_from(SYNTAX_BREAKERS)))
        return kind, "\n".join(lines) + "\n", (None, at + 1)
    return kind, dump_toml(data), fault


def where_expected(kind: str, fault: tuple, path, text: str, message: str) -> None:
    """Assert that ``message`` says where the fault of a malformed example is."""
    source = re.escape(str(path))
    table, key = fault
    if kind == "syntax":
        # tomllib reports the line where parsing failed: the inserted line or one after it
        # (an unclosed array or string swallows the lines that follow it). A breaker that
        # happens to be valid TOML (``digits = 1`` in another table) is a stray key, named
        # at its line.
        match = re.match(rf"^{source}:(\d+): ", message)
        assert match and int(match.group(1)) >= key, message
        return
    if kind == "delete-table":
        assert re.match(rf"^{source}: missing required key '{key}'$", message), message
        return
    line = r":\d+" if kind != "delete" else r"(:\d+)?"
    located = re.match(rf"^{source}{line}: ", message)
    assert located, message
    if kind == "delete":
        assert f"{table}: missing required key '{key}'" in message, message
        return
    if kind == "unknown":
        prefix = f"{table}: " if table else ""
        assert f": {prefix}unknown key '{key}'" in message, message
    else:  # wrong-type, out-of-range: the key path, first or among the keys named
        assert f"{table}.{key}" in message, message
    number = int(re.match(rf"^{source}:(\d+): ", message).group(1))
    named = text.splitlines()[number - 1]
    # the line is the mutated key's own, or (a fault involving several keys) a key it names
    keys = set(re.findall(r"^\s*([A-Za-z0-9_\-]+)\s*=", named))  # key = value
    keys |= set(re.findall(r"^\[[\w.\-]*?([\w\-]+)\]$", named))  # [table.key] (a dict value)
    assert keys & {key} or keys & set(re.findall(r"[a-z]+\.([A-Za-z0-9_\-]+)", message)), \
        (message, named)


def test_500_malformed_protocols_are_refused_in_one_line(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    seen: list[str] = []

    @settings(max_examples=500, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
    @given(malformed())
    def refuse(example):
        kind, text, fault = example
        path = folder / f"p{len(seen)}.toml"
        path.write_text(text)
        seen.append(kind)
        try:
            load_protocol(path)
        except ProtocolError as exc:
            message = str(exc)
            assert "\n" not in message and message.startswith(str(path)), message
            where_expected(kind, fault, path, text, message)
        else:
            raise AssertionError(f"{kind}: accepted a malformed protocol:\n{text}")
        if len(seen) % 10 == 0:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                status = main(["validate", str(path)])
            lines = err.getvalue().splitlines()
            assert status == 2 and len(lines) == 1, err.getvalue()
            assert "Traceback" not in err.getvalue()
            assert lines[0].startswith("crs-study validate: error: ")

    refuse()
    assert len(seen) >= 500
    assert set(seen) == {"delete", "delete-table", "unknown", "wrong-type", "out-of-range",
                         "syntax"}
