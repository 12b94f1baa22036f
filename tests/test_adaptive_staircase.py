"""The staircase against PsychoPy's StairHandler, and its own rules.

Outside reference: tests/fixtures/adaptive/psychopy_staircases.json, made by
tests/fixtures/adaptive/make_psychopy_staircases.py with PsychoPy 2026.2.5's
``psychopy.data.StairHandler`` on scripted responses (run in a throwaway environment; the
suite does not need PsychoPy). Weighted steps: Kaernbach 1991 (converges to the target).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.adaptive import AdaptiveSpec, Staircase, StaircaseSpec
from crs_study.errors import ProtocolError

FIXTURE = Path(__file__).parent / "fixtures" / "adaptive" / "psychopy_staircases.json"
CASES = json.loads(FIXTURE.read_text(encoding="utf-8"))["cases"]


def staircase_spec(start=1.0, steps=(2, 1), rule="1-up-2-down", scale="log", low=0.1,
                   high=1.0, levels=21, trials=60, target=None, parameter="digit_height_pitch",
                   stop_reversals=0, estimate_reversals=6) -> AdaptiveSpec:
    """A log grid 0.05 log units apart from 0.1 to 1.0 pitch by default."""
    return AdaptiveSpec(parameter, "staircase", trials, low, high, scale, levels,
                        target_rate=target,
                        width_to_height=0.605 if parameter == "digit_height_pitch" else None,
                        staircase=StaircaseSpec(rule, start, tuple(steps), stop_reversals,
                                                estimate_reversals))


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_same_levels_as_psychopy_stairhandler(case):
    rule = {2: "1-up-2-down", 3: "1-up-3-down"}[case["n_down"]]
    spec = staircase_spec(round(case["start"], 6), case["steps"], rule,
                          "log" if case["step_type"] == "log" else "linear",
                          round(case["min"], 6), round(case["max"], 6), case["levels_in_grid"],
                          trials=len(case["responses"]))
    stair = Staircase(spec)
    shown = []
    for response in case["responses"]:
        shown.append(stair.next_level)
        stair.update(bool(response))
    # the file keeps 6 decimals; the grid's ends are given to 6 decimals
    np.testing.assert_allclose(shown, case["levels"], rtol=0, atol=2e-6)
    reversal_levels = [spec.from_axis(u) for u in stair.reversal_axis]
    np.testing.assert_allclose(reversal_levels, case["reversal_levels"], rtol=0, atol=2e-6)
    # every level shown is one validate checked on the device
    assert set(shown) <= set(spec.shown_levels())


def test_estimate_is_the_mean_of_the_last_reversals_with_t_interval():
    stair = Staircase(staircase_spec(estimate_reversals=4, steps=(2,)))
    for response in [1, 1, 0, 1, 1, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 1, 0, 1, 1] * 2:
        stair.update(bool(response))
    last = stair.reversal_axis[-4:]
    assert stair.reversals >= 4
    estimate, low, high = stair.estimate()
    assert estimate == pytest.approx(10 ** np.mean(last))
    # t(0.975, 3) (scipy.stats.t.ppf) over n/2 = 2 effective reversals
    half = 3.182446305284263 * np.std(last, ddof=1) / np.sqrt(2)
    assert (low, high) == pytest.approx((10 ** (np.mean(last) - half),
                                         10 ** (np.mean(last) + half)))


def test_stops_after_trials_or_reversals():
    stair = Staircase(staircase_spec(trials=30, stop_reversals=4, estimate_reversals=4))
    responses = iter([True, True, False] * 20)
    while not stair.finished:
        stair.update(next(responses))
    assert stair.reversals == 4 and stair.trials < 30
    stair = Staircase(staircase_spec(trials=12))
    for _ in range(12):
        stair.update(True)
    assert stair.finished and stair.next_level == 0.1  # stopped at min


def test_speed_gets_faster_when_correct():
    """A faster stroke is harder: correct answers raise the speed."""
    spec = staircase_spec(start=40.0, steps=(1,), low=10.0, high=160.0, levels=5,
                          parameter="stroke_speed_mm_s")
    assert spec.grid() == (160.0, 80.0, 40.0, 20.0, 10.0)  # hardest first
    stair = Staircase(spec)
    stair.update(True)
    assert stair.next_level == 80.0


@pytest.mark.parametrize("target", [0.5, 0.75, 0.8])
def test_weighted_steps_converge_to_the_target_rate(target):
    """Kaernbach 1991: easier step / harder step = p / (1 - p) tracks the level where the
    observer is right with probability p."""
    rng = np.random.default_rng(3)
    high = round(10 ** (-1 + 39 * 0.05), 6)  # 40 levels 0.05 log units apart from 0.1
    spec = staircase_spec(rule="weighted", target=target, steps=(1,), low=0.1, high=high,
                          levels=40, trials=600, start=1.0)
    errors = []
    for _ in range(20):
        stair = Staircase(spec)
        for _ in range(600):
            u = math.log10(stair.next_level)
            p = 0.1 + 0.9 / (1 + math.exp(-8 * u))  # threshold 1.0, guess 0.1
            stair.update(bool(rng.random() < p))
        p_at = [0.1 + 0.9 / (1 + math.exp(-8 * math.log10(v))) for v in stair.levels_shown[100:]]
        errors.append(np.mean(p_at) - target)
    assert abs(np.mean(errors)) < 0.02


def test_state_is_a_pure_function_of_the_responses():
    responses = [True, True, False, True, True, True, False, False, True] * 4
    a, b = Staircase(staircase_spec()), Staircase(staircase_spec())
    for r in responses:
        a.update(r)
        b.update(r)
    assert a.state() == b.state()


@pytest.mark.parametrize(("kwargs", "key", "message"), [
    (dict(steps=(21,)), "adaptive.staircase.steps[0]", "cannot move"),
    (dict(steps=(0.5,)), "adaptive.staircase.steps[0]", "expected a whole number"),
    (dict(steps=()), "adaptive.staircase.steps", "non-empty"),
    (dict(levels=41), "adaptive.levels", "expected a whole number <= 40"),
    (dict(start=2.0), "adaptive.staircase.start", "expected a number"),
    (dict(start=0.5), "adaptive.staircase.start", "expected a level of the grid"),
    (dict(rule="weighted", target=0.7), "adaptive.target_rate", "expected a whole number"),
    (dict(rule="weighted", target=1.0), "adaptive.target_rate", "below 1"),
    (dict(rule="weighted"), "adaptive.target_rate", "missing"),
    (dict(target=0.8), "adaptive.target_rate", "set by rule"),
    (dict(low=1.5, high=0.5), "adaptive.max", "expected a level above min"),
    (dict(low=0.0), "adaptive.min", "expected a number"),
    (dict(low=1.0, high=1.000001, levels=3), "adaptive.levels", "closer than the 6 decimals"),
    (dict(estimate_reversals=8, stop_reversals=4), "adaptive.staircase.estimate_reversals",
     "at most stop_reversals"),
])
def test_bad_settings_name_their_key(kwargs, key, message):
    with pytest.raises(ProtocolError, match=message) as caught:
        staircase_spec(**kwargs)
    assert caught.value.key_path == key


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=80),
       st.sampled_from(["1-up-2-down", "1-up-3-down"]), st.sampled_from(["log", "linear"]))
def test_levels_stay_within_bounds_and_the_checked_set(responses, rule, scale):
    spec = staircase_spec(rule=rule, scale=scale, steps=(4, 2, 1), trials=100)
    stair = Staircase(spec)
    allowed = set(spec.grid())
    for r in responses:
        assert stair.next_level in allowed
        update = stair.update(r)
        assert update.reversals == stair.reversals
    assert spec.minimum <= stair.next_level <= spec.maximum
