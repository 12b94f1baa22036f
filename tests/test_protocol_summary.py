"""The typed summary of a protocol and its plan (what ``validate`` prints)."""

from __future__ import annotations

import pytest

from crs_study.api import validate
from crs_study.protocol.summary import ConditionTrials, FrameRange


@pytest.mark.parametrize("name", ["pilot", "digit_size_psychometric", "digit_size_adaptive"])
def test_the_typed_counts_add_up_and_are_what_the_json_says(name):
    summary = validate(name, participant="p07", counterbalance=1)
    plan, protocol = summary.plan, summary.protocol
    assert [t.condition for t in summary.trials] == list(protocol.conditions)
    assert sum(t.practice + t.test for t in summary.trials) == len(plan)
    assert summary.trials[0] == ConditionTrials(
        protocol.conditions[0], plan.count("practice", protocol.conditions[0]),
        plan.count("test", protocol.conditions[0]))
    frames = [s.n_frames for s in summary.stimuli.values()]
    assert summary.frames_per_trial == FrameRange(min(frames), max(frames),
                                                  sum(frames) / len(frames))
    assert summary.breaks == sum(t.break_before for t in plan.trials)
    for level in summary.levels:  # fixed levels: every trial of a condition is at one level
        if level.trials is not None:
            assert all(t.practice + t.test == plan.count(None, t.condition, level.value)
                       for t in level.trials)
    assert (protocol.adaptive is not None) == any(lv.trials is None for lv in summary.levels)
    content = summary.to_dict()
    assert content["trials"]["per_condition"] == {
        t.condition: {"practice": t.practice, "test": t.test} for t in summary.trials}
    assert content["block_orders"]["cycle"] == len(summary.block_orders)
    assert content["frames_per_trial"]["max"] == summary.frames_per_trial.max
    assert content["example_plan"]["counterbalance"] == 1
