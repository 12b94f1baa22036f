"""The [adaptive] table of a protocol: loading, one-line errors at the key's line, validate's
summary, the plan, the writer's round trip and feasibility at every level."""

from __future__ import annotations

import dataclasses
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import crs_study
from crs_study.errors import ProtocolError
from crs_study.paths import shipped_file
from crs_study.protocol import load_protocol, protocol_to_toml
from crs_study.protocol.loader import protocol_from_text
from crs_study.protocol.plan import make_plan

SHIPPED = shipped_file("protocols/digit_size_adaptive.toml")
TEXT = SHIPPED.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def shipped():
    return load_protocol(SHIPPED)


def edited(tmp_path, old: str, new: str):
    assert old in TEXT, old
    path = tmp_path / "p.toml"
    path.write_text(TEXT.replace(old, new, 1), encoding="utf-8")
    return path


def test_the_shipped_adaptive_protocol(shipped):
    spec = shipped.adaptive
    assert spec.procedure == "quest-plus" and spec.trials == 40 and spec.rate == 0.5
    assert spec.grid()[0] == 0.25 and spec.grid()[-1] == 1.5 and len(spec.grid()) == 12
    # every level the procedure can show is a level of the protocol (checked on the device)
    assert shipped.levels.values == spec.shown_levels()
    assert any("digit_height_pitch = 1.5: bump centre path inside" in c for c in shipped.checks)
    assert shipped.stimulus_at(1.5).symbol_width_pitch == pytest.approx(1.5 * 0.605)


def test_the_plan_leaves_test_levels_to_the_procedure(shipped):
    plan = make_plan(shipped, "p01", 1, 0)
    test = [t for t in plan.trials if t.trial_type == "test"]
    assert len(test) == 80 and {t.level for t in test} == {None}
    assert {t.level for t in plan.trials if t.trial_type == "practice"} == {1.5}
    for condition in shipped.conditions:
        counts = [sum(t.symbol == d and t.condition == condition for t in test)
                  for d in shipped.symbols]
        assert sorted(counts) == [4] * 10  # 40 trials dealt evenly to the ten digits
    assert plan.block_conditions == ("pixel-only", "crs")


def test_validate_prints_the_procedure_and_its_range(shipped):
    summary = crs_study.validate(shipped)
    adaptive = summary.to_dict()["adaptive"] if hasattr(summary, "to_dict") else None
    assert adaptive is not None and adaptive["procedure"] == "quest-plus"
    assert (adaptive["min"], adaptive["max"], adaptive["scale"]) == (0.25, 1.5, "log")


def test_validate_command_text(capsys):
    from crs_study.cli import main

    assert main(["validate", str(SHIPPED)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"adaptive: quest-plus chooses digit_height_pitch in each block \(40 test "
                     r"trials\), 0.25 to 1.5 on a log scale \(12 levels", out)
    assert "QUEST+ (questplus): 25 thresholds" in out


@pytest.mark.parametrize(("old", "new", "message"), [
    ("max = 1.5", "max = 1.7", r":\d+: adaptive.max: at digit_height_pitch = 1.7: "),
    ("min = 0.25", "min = 0.0", r":\d+: adaptive.min: expected a number >= 0.01"),
    ("target_rate = 0.5", "target_rate = 0.1", r":\d+: adaptive.target_rate: the target rate "
     r"0.1 is at or below chance \(1 / 10 digits = 0.1\)"),
    ("target_rate = 0.5", "target_rate = 0.97", r":\d+: adaptive.target_rate: expected a rate "
     r"below 1 - the largest lapse rate"),
    ("levels = 12", "levels = 2", r":\d+: adaptive.levels: expected a whole number >= 3"),
    ("trials = 40", "trials = 0", r":\d+: adaptive.trials: expected a whole number >= 2"),
    ('scale = "log"', 'scale = "ln"', r":\d+: adaptive.scale: expected one of"),
    ("repetitions = 1 ", "repetitions = 2 ", r":\d+: design.repetitions: with \[adaptive\]"),
    ('procedure = "quest-plus"', 'procedure = "staircase"',
     r":\d+: adaptive.staircase: missing: procedure = \"staircase\" needs"),
    ("[adaptive.quest_plus]", "[adaptive.quest_plus]\nsteps = [1]",
     r":\d+: adaptive.quest_plus: unknown key 'steps'"),
    ("slopes = [1.0, 2.0, 4.0, 8.0]", "slopes = [0.0]",
     r":\d+: adaptive.quest_plus.slopes\[0\]: expected a number > 0"),
    ("width_to_height = 0.605", "width_to_height = 0.0",
     r":\d+: adaptive.width_to_height: expected a number >= 0.05"),
    ("\n[adaptive]\n", "\n[levels]\nparameter = \"digit_height_pitch\"\nvalues = [0.5, 1.0]\n"
     "width_to_height = 0.6\n\n[adaptive]\n", r"adaptive: a protocol either crosses"),
])
def test_bad_adaptive_settings_are_one_line_errors_at_their_line(tmp_path, old, new, message):
    path = edited(tmp_path, old, new)
    with pytest.raises(ProtocolError, match=message) as caught:
        load_protocol(path)
    text = str(caught.value)
    assert "\n" not in text and text.startswith(str(path))
    if caught.value.line is not None:
        key = caught.value.key_path.split(".")[-1].split("[")[0]
        line = path.read_text().splitlines()[caught.value.line - 1]
        assert key in line or line.startswith("[")


STAIRCASE = """
[adaptive.staircase]
rule = "{rule}"
start = {start}
steps = {steps}
stop_reversals = {stop}
estimate_reversals = {estimate}
"""


def staircase_text(rule="1-up-2-down", start=1.5, steps="[2, 1]", stop=0, estimate=6,
                   target=None) -> str:
    text = TEXT.replace('procedure = "quest-plus"', 'procedure = "staircase"')
    text = re.sub(r"\[adaptive.quest_plus\]\n(.*\n){3}", STAIRCASE.format(
        rule=rule, start=start, steps=steps, stop=stop, estimate=estimate).lstrip(), text)
    target_line = "" if target is None else f"target_rate = {target}"
    return re.sub(r"(?m)^target_rate = .*$", target_line, text)


def test_a_staircase_protocol_loads_and_names_its_bad_step(tmp_path):
    protocol = protocol_from_text(staircase_text(), tmp_path / "s.toml")
    assert protocol.adaptive.staircase.steps == (2, 1) and protocol.adaptive.rate == 0.5 ** 0.5
    with pytest.raises(ProtocolError, match=r"s.toml:\d+: adaptive.staircase.steps\[0\]: a "
                                            r"step of 12 levels cannot move"):
        protocol_from_text(staircase_text(steps="[12]"), tmp_path / "s.toml")
    with pytest.raises(ProtocolError, match=r"adaptive.staircase.start: expected a level of "
                                            r"the grid .*nearest \[0.92017, 1.082952\]"):
        protocol_from_text(staircase_text(start=1.0), tmp_path / "s.toml")
    with pytest.raises(ProtocolError, match=r"adaptive.target_rate: weighted steps: the "
                                            r"easier step is"):
        protocol_from_text(staircase_text(rule="weighted", target=0.7), tmp_path / "s.toml")


def test_a_protocol_changed_in_python_is_written_and_read_back(shipped):
    spec = dataclasses.replace(shipped.adaptive, trials=30, levels=8)
    changed = dataclasses.replace(shipped, adaptive=spec)
    assert changed.levels.values == spec.shown_levels()  # derived again
    settled = load_protocol(changed)
    assert settled.adaptive == spec and "[adaptive.quest_plus]" in settled.text
    assert "adaptive.trials, adaptive.levels" in protocol_to_toml(changed)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(
    st.sampled_from(["trials", "min", "max", "levels", "target_rate", "scale", "procedure",
                     "practice_level"]),
    st.one_of(st.integers(-5, 60), st.floats(-1, 3, allow_nan=False), st.text("abl-gn", max_size=3),
              st.booleans()), max_size=3))
def test_any_adaptive_values_load_or_fail_in_one_line(tmp_path_factory, values):
    text = TEXT
    for key, value in values.items():
        rendered = f'"{value}"' if isinstance(value, str) else \
            str(value).lower() if isinstance(value, bool) else repr(value)
        text = re.sub(rf"(?m)^{key} = [^#\n]*", f"{key} = {rendered}", text)
    text = text.replace("# practice_level", "practice_level") if "practice_level" in values \
        else text
    try:
        protocol_from_text(text, tmp_path_factory.mktemp("h") / "p.toml", check_device=False)
    except ProtocolError as error:
        assert "\n" not in str(error) and error.key_path is not None


def test_an_adaptive_speed_range_warns_at_its_bound(tmp_path):
    """Odd values of an adaptive level name the bound they concern, not [levels]."""
    text = TEXT.replace('parameter = "digit_height_pitch"    # column digit_height (pitches) '
                        'in the dataset\nwidth_to_height = 0.605             # the shipped '
                        "digits' shape, 0.49 / 0.81\n", 'parameter = "stroke_speed_mm_s"\n')
    text = text.replace("min = 0.25", "min = 20.0").replace("max = 1.5", "max = 120.0")
    text = text.replace("stroke_speed_mm_s = 20.0\n", "digit_height_pitch = 0.81\n"
                        "digit_width_pitch = 0.49\n")
    path = tmp_path / "speed.toml"
    path.write_text(text)
    protocol = load_protocol(path)
    assert protocol.adaptive.grid()[0] == 120.0
    fast = [w for w in protocol.warnings if "is fast" in w]
    assert fast and all(": adaptive.max: at stroke_speed_mm_s = " in w for w in fast)
