"""Recovery: simulated observers with a known psychometric function (crs_study.adaptive.
recovery) tracked by each procedure over 200 simulated sessions (QUEST+: 100); the true
threshold lies in the procedure's 95 % interval in at least 90 % of them, and the estimates
are unbiased within a small fraction of the intervals' width."""

from __future__ import annotations

import pytest

from crs_study.adaptive import AdaptiveSpec, QuestPlusSpec, StaircaseSpec
from crs_study.adaptive.recovery import Observer, recovery

SESSIONS = 200
#: QUEST+'s sessions (its questplus steps cost about 15 ms each): at 100 an interval that
#: covers 95 % of the time falls below 90 % with probability 0.011, one that covers 80 %
#: reaches 90 % with probability 0.006 (binomial); the bias is judged against a fifth of
#: the intervals' width, whatever the number of sessions.
QUEST_SESSIONS = 100


@pytest.mark.parametrize("rule", ["1-up-2-down", "1-up-3-down"])
def test_staircase_recovers_the_threshold_at_its_rule_target(rule):
    spec = AdaptiveSpec("digit_height_pitch", "staircase", 60, 0.2, 1.6, "log", 19,
                        width_to_height=0.6,
                        staircase=StaircaseSpec(rule, 1.6, (4, 2, 1), 0, 6))
    result = recovery(spec, sessions=SESSIONS, observer=Observer(slope=4.0, lapse=0.02))
    assert result.missing == 0
    assert result.coverage >= 0.9, result.to_dict()
    assert abs(result.bias) < 0.1 * result.median_width, result.to_dict()


@pytest.mark.slow  # 100 QUEST+ sessions: half a minute (questplus's xarray steps)
def test_quest_plus_recovers_the_threshold_at_the_target_rate():
    spec = AdaptiveSpec("digit_height_pitch", "quest-plus", 20, 0.2, 1.6, "log", 12,
                        target_rate=0.5, width_to_height=0.6,
                        quest_plus=QuestPlusSpec(25, (1.0, 2.0, 4.0, 8.0), (0.0, 0.03, 0.06)))
    result = recovery(spec, sessions=QUEST_SESSIONS, observer=Observer(slope=4.0,
                                                                       lapse=0.02))
    assert result.coverage >= 0.9, result.to_dict()
    # 20 trials leave the slope uncertain: the posterior mean of the threshold at 50 % sits
    # slightly low (measured: -0.027 log10 units, 6 %), a tenth of the intervals' width
    assert abs(result.bias) < 0.2 * result.median_width, result.to_dict()
