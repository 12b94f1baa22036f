"""QUEST+ through crs_study's wrapper of the questplus package.

Outside reference: Watson (2017), QUEST+: a general multidimensional Bayesian adaptive
psychometric method, J Vis 17(3):10, Examples 1 ({1, 1, 2}: threshold) and 2 ({1, 3, 2}:
threshold, slope, lapse): the stimulus sequences for the published responses, as the
questplus package's own tests (questplus/tests/test_qp.py) list them from the paper's
Mathematica notebook. Recovery over 200 simulated sessions: tests/test_adaptive_recovery.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from crs_study.adaptive import AdaptiveSpec, QuestPlusDesign, QuestPlusEngine, QuestPlusSpec
from crs_study.adaptive.quest_plus import QuestPlusTrack, level_at_rate
from crs_study.errors import ProtocolError

C, I = True, False
# Watson 2017, Example 1: contrast threshold, slope 3.5, guess 0.5, lapse 0.02, dB.
EXAMPLE_1_RESPONSES = [C, C, C, C, I, I, C, C, C, C, C, C, C, C, I, C, C, I, C, C, I, C, C,
                       C, C, C, C, C, C, C, C, C]
EXAMPLE_1_CONTRASTS = [-18, -22, -25, -28, -30, -22, -13, -15, -16, -18, -19, -20, -21, -22,
                       -23, -19, -20, -20, -18, -18, -19, -17, -17, -18, -18, -18, -19, -19,
                       -19, -19, -19, -19]
# Watson 2017, Example 2: threshold, slope 2..5 and lapse 0..0.04 estimated.
EXAMPLE_2_CONTRASTS = [
    -18, -22, -25, -28, -30, -21, -12, -14, -15, -16, -18, -19, -20, -22, -23, -18, -19, -16,
    -17, -17, -18, -18, -18, -19, -19, -17, -17, -18, -18, -18, -18, -19, -19, -20, -18, -18,
    -18, -18, -18, -19, -19, -19, -19, -20, -18, -18, -18, -18, -18, -18, -18, -18, -18, -19,
    -19, -19, -20, -18, -18, -18, -18, -19, -19, -19, -18, -18, -18, -18, -19, -19, -19, -19,
    -19, -19, -19, -19, -20, -21, -19, -19, -19, -19, -19, -19, -19, -18, -19, -19, -16, -16,
    -16, -16, -16, -16, 0, 0, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19,
    -19, -21, -21, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19, -19,
    -19]
EXAMPLE_2_RESPONSES = [
    C, C, C, C, I, I, C, C, C, C, C, C, C, C, I, C, I, C, C, C, C, C, C, C, I, C, C, C, C, C,
    C, C, C, I, C, C, C, C, C, C, C, C, C, I, C, C, C, I, C, C, C, C, C, C, C, C, I, C, C, C,
    C, C, C, I, C, C, C, C, C, C, C, C, C, C, C, C, C, I, C, I, C, C, C, C, I, C, C, I, C, C,
    C, C, C, C, C, I, C, C, C, C, C, C, C, C, C, C, C, C, C, C, C, I, C, C, C, I, C, I, I, C,
    C, C, C, I, C, C, C, C]
CONTRASTS = tuple(float(c) for c in range(-40, 1))


def replay(design, responses):
    engine = QuestPlusEngine(design)
    shown = []
    for correct in responses:
        shown.append(engine.next_intensity)
        engine.update(engine.next_intensity, correct)
    return engine, shown


def test_watson_example_1_threshold():
    design = QuestPlusDesign(CONTRASTS, CONTRASTS, (3.5,), (0.02,), 0.5, "dB", "mode")
    engine, shown = replay(design, EXAMPLE_1_RESPONSES)
    assert shown == EXAMPLE_1_CONTRASTS
    assert engine.estimate["threshold"] == -20  # Watson 2017, Example 1


def test_watson_example_2_threshold_slope_lapse():
    design = QuestPlusDesign(CONTRASTS, CONTRASTS, (2.0, 3.0, 4.0, 5.0),
                             (0.0, 0.01, 0.02, 0.03, 0.04), 0.5, "dB", "mode")
    assert len(EXAMPLE_2_RESPONSES) == len(EXAMPLE_2_CONTRASTS) == 128
    engine, shown = replay(design, EXAMPLE_2_RESPONSES)
    assert shown == EXAMPLE_2_CONTRASTS
    estimate = engine.estimate
    assert (estimate["threshold"], estimate["slope"]) == (-20, 5)  # Watson 2017, Example 2
    assert estimate["lapse_rate"] == pytest.approx(0.04)


def quest_spec(trials=60, target=0.75, levels=16, lapses=(0.0, 0.02, 0.05),
               parameter="digit_height_pitch", low=0.2, high=1.5) -> AdaptiveSpec:
    return AdaptiveSpec(parameter, "quest-plus", trials, low, high, "log", levels,
                        target_rate=target,
                        width_to_height=0.605 if parameter == "digit_height_pitch" else None,
                        quest_plus=QuestPlusSpec(25, (1.5, 3.0, 6.0, 12.0), lapses))


def weibull_correct(level, threshold_u, slope, guess=0.1, lapse=0.02):
    """questplus's log10 Weibull on the difficulty axis u = log10(level)."""
    u = np.log10(level)
    return 1 - lapse - (1 - guess - lapse) * np.exp(-10 ** (slope * (u - threshold_u)))


def test_level_at_rate_inverts_the_weibull():
    u = level_at_rate(np.array([-0.3]), np.array([4.0]), 0.1, np.array([0.02]), 0.75)
    assert weibull_correct(10 ** u.item(), -0.3, 4.0) == pytest.approx(0.75)


def test_a_60_trial_block_runs_on_the_levels_grid():
    """Every next level of a 60-trial block is one of the spec's levels, and the block ends
    after 60 responses (how fast each level comes is crs-study bench adaptive's figure)."""
    spec = quest_spec()
    track = QuestPlusTrack(spec, 10)
    grid = np.asarray(spec.grid())
    rng = np.random.default_rng(2)
    answered = 0
    while not track.finished:
        level = track.next_level
        assert np.min(np.abs(grid - level)) <= 1e-9 * level
        track.update(bool(rng.random() < weibull_correct(level, -0.2, 4.0)))
        answered += 1
    assert answered == 60


def test_state_is_a_pure_function_of_the_responses():
    responses = [True, False, True, True, True, False, True, True] * 3
    a, b = QuestPlusTrack(quest_spec(), 10), QuestPlusTrack(quest_spec(), 10)
    for r in responses:
        a.update(r)
        b.update(r)
    assert a.state() == b.state() and a.next_level == b.next_level


def test_levels_shown_are_the_grid():
    spec = quest_spec(levels=5, low=0.25, high=1.0)
    assert spec.grid() == (0.25, 0.353553, 0.5, 0.707107, 1.0)
    track = QuestPlusTrack(spec, 10)
    for r in [True] * 5 + [False] * 5:
        assert track.next_level in spec.grid()
        track.update(r)


@pytest.mark.parametrize(("kwargs", "key", "message"), [
    (dict(target=0.96), "adaptive.target_rate", "below 1 - the largest lapse rate"),
    (dict(target=None), "adaptive.target_rate", "missing"),
    (dict(levels=2), "adaptive.levels", ">= 3"),
    (dict(lapses=(0.0, 0.0)), "adaptive.quest_plus.lapse_rates", "appears twice"),
    (dict(lapses=(0.6,)), "adaptive.quest_plus.lapse_rates[0]", "<= 0.5"),
])
def test_bad_settings_name_their_key(kwargs, key, message):
    with pytest.raises(ProtocolError, match=message) as caught:
        quest_spec(**kwargs)
    assert caught.value.key_path == key
