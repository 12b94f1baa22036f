"""``crs-study validate`` lists every error of a protocol in one run, not one per run.

Each listed error must be the very error the file raises when it holds that mistake alone
(the same message, file, line and key), and nothing a repair caused may be listed.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from crs_study.api import validate
from crs_study.errors import ProtocolError, ProtocolProblems
from crs_study.protocol import load_protocol
from crs_study.protocol.problems import protocol_problems
from tests._session_helpers import tiny_protocol

#: Mistakes in distinct keys, each (text in the tiny protocol, its replacement): a misspelt
#: key, wrong types and ranges in four tables, a condition nobody registered, and two device
#: checks (the pixels' travel, the wire's frame rate) that reading alone cannot see.
MISTAKES = [
    pytest.param("repetitions = 1", "repetiton = 1", id="misspelt-key"),
    pytest.param("inter_trial_interval_s = 0.5", 'inter_trial_interval_s = "x"', id="type"),
    pytest.param("time_limit_s = 10.0", "time_limit_s = -3", id="range"),
    pytest.param('names = ["pixel-only", "crs"]', 'names = ["pixel-only", "crss"]',
                 id="condition"),
    pytest.param('ordering = "blocked"', 'ordering = "random"', id="choice"),
    pytest.param("bump_height_mm = 5.0", "bump_height_mm = 12.0", id="travel"),
    pytest.param("frame_rate_hz = 15.0", "frame_rate_hz = 150.0", id="wire"),
]


def _with(path: Path, name: str, changes) -> Path:
    text = path.read_text(encoding="utf-8")
    for old, new in changes:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    if any("crss" in new for _, new in changes):  # its prompt goes with the name
        text = text.replace('crs = "CRS block', 'crss = "CRS block')
    out = path.parent / name
    out.write_text(text, encoding="utf-8")
    return out


def _alone(path: Path, change) -> str:
    with pytest.raises(ProtocolError) as raised:
        load_protocol(_with(path, "alone.toml", [change]))
    return str(raised.value).replace("alone.toml", "all.toml")


def test_one_run_lists_every_error_each_as_the_file_with_it_alone_says(tmp_path):
    base = tiny_protocol(tmp_path)
    changes = [p.values for p in MISTAKES]
    expected = [_alone(base, change) for change in changes]
    everything = _with(base, "all.toml", changes)
    run = subprocess.run([sys.executable, "-m", "crs_study", "validate", str(everything)],
                         capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.splitlines()
    assert lines[-1] == f"crs-study validate: {len(MISTAKES)} errors in {everything}"
    listed = [line.removeprefix("crs-study validate: error: ") for line in lines[:-1]]
    assert sorted(listed) == sorted(expected)
    with pytest.raises(ProtocolError) as first:  # the first listed is the one loading raises
        load_protocol(everything)
    assert listed[0] == str(first.value)


@pytest.mark.parametrize("digits, key", [
    pytest.param("[1, 4, 77]", "stimulus.digits[2]", id="two-for-three-keys"),
    pytest.param('["a", 4]', "stimulus.digits[0]", id="one-left"),
])
def test_a_consequence_of_a_repair_is_not_listed(tmp_path, digits, key):
    """Dropping the bad digit leaves fewer digits than keys (or one digit alone): no second
    error."""
    path = _with(tiny_protocol(tmp_path), "digits.toml",
                 [("digits = [1, 4, 7]", f"digits = {digits}")])
    problems = protocol_problems(path)
    assert [p.key_path for p in problems] == [key]


def test_one_error_stays_a_plain_protocol_error_and_a_valid_file_has_none(tmp_path):
    base = tiny_protocol(tmp_path)
    assert protocol_problems(base) == ()
    with pytest.raises(ProtocolError) as raised:
        validate(_with(base, "one.toml", [MISTAKES[2].values]))
    assert type(raised.value) is ProtocolError
    assert "responses.time_limit_s: expected a number > 0, got -3" in str(raised.value)


def test_the_python_api_raises_every_problem_and_they_pickle(tmp_path):
    path = _with(tiny_protocol(tmp_path), "two.toml", [p.values for p in MISTAKES[1:3]])
    with pytest.raises(ProtocolProblems) as raised:
        validate(path)
    problems = raised.value.problems
    assert [p.key_path for p in problems] == ["design.inter_trial_interval_s",
                                              "responses.time_limit_s"]
    assert str(raised.value) == "\n".join(map(str, problems))
    assert raised.value.key_path == problems[0].key_path  # a ProtocolError like the first
    again = pickle.loads(pickle.dumps(raised.value))
    assert str(again) == str(raised.value) and again.line == problems[0].line
