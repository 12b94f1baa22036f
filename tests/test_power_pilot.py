"""Mode 1: the effect from a pilot dataset, fitted as ``analyze`` fits it, then extended."""

from __future__ import annotations

import numpy as np
import pytest
from _power_helpers import chi2_plan, pilot_model_matching_analyze

from crs_study.analysis.synthetic import SyntheticSpec, write_dataset
from crs_study.power_analysis import PowerError, design_from_protocol, model_from_pilot, power


@pytest.fixture(scope="module")
def pilot(tmp_path_factory):
    spec = SyntheticSpec(n_participants=8, repetitions=3, participant_sd=0.5, digit_sd=0.4,
                         accuracy={"pixel-only": 0.5, "crs": 0.65}, seed=31)
    return write_dataset(tmp_path_factory.mktemp("pilot") / "pilot", spec)


def test_the_pilots_model_is_analyzes_fit(pilot):
    """The fixed effects and the covariances of the random effects (intercepts and condition
    slopes, the plan's maximal model) that generate the studies are those of analyze's
    primary GLMM on the pilot (same sessions, exclusions, plan)."""
    model, variances = pilot_model_matching_analyze("digit_identification", pilot)
    participant = model.covariance("participant")
    assert model.participant_sd == pytest.approx(
        np.sqrt(variances["participant_id:Intercept"]))
    assert participant[1, 1] == pytest.approx(variances["participant_id:condition[crs]"])
    digit = model.covariance("symbol")
    assert model.digit_sd == pytest.approx(np.sqrt(variances["digit:Intercept"]))
    assert digit[1, 1] == pytest.approx(variances["digit:condition[crs]"])
    assert model.source == "pilot" and model.details["n_participants"] == 8
    assert model.details["random"] == \
        "(1 + condition | participant) + (1 + condition | digit)"


def test_a_null_pilot_whose_participants_differ_gives_that_slope_to_new_participants(tmp_path):
    """A pilot with no condition effect but participants differing in it: the model carries
    the pilot's slope, and studies drawn from it show the spread (and no effect)."""
    spec = SyntheticSpec(n_participants=30, repetitions=4, participant_sd=0.4, digit_sd=0.2,
                         participant_slope_sd=0.8, accuracy={"pixel-only": 0.6, "crs": 0.6},
                         seed=32)
    pilot = write_dataset(tmp_path / "null", spec)
    model = model_from_pilot(design_from_protocol("digit_identification"), pilot)
    slope = float(model.slope_sd("participant")[0])
    assert 0.4 < slope < 1.3                                   # the pilot's estimate of 0.8
    rng = np.random.default_rng(0)
    logits = np.array([model.participant_logits(z, [w])[0, 0]
                       for z, w in rng.standard_normal((4000, 2))])
    effects = logits[:, 1] - logits[:, 0]                     # each new participant's effect
    assert np.std(effects) == pytest.approx(slope, rel=0.05)
    assert abs(np.mean(effects) - (model.base[0, 0, 1] - model.base[0, 0, 0])) < 0.05


def test_the_effect_scale_shrinks_the_condition_effect_and_the_power(pilot):
    """The plan's chi2 p: what is tested is the effect and its power, and the bootstrap's
    null studies (below 20 participants) would double the cost. Both runs draw the same 20
    studies (one seed: common random numbers), so an effect scale that did not reach the
    simulated studies gives the same counts, not a lower power, however few the studies."""
    kwargs = dict(pilot=pilot, participants="4:8:4", studies=20, jobs=1, seed=3,
                  plan=chi2_plan("digit_identification"))
    full = power("digit_identification", **kwargs)
    half = power("digit_identification", effect_scale=0.5, **kwargs)
    effect = full.model.base[0, 0, 1] - full.model.base[0, 0, 0]
    assert half.model.base[0, 0, 1] - half.model.base[0, 0, 0] == pytest.approx(effect / 2)
    assert half.model.base[0, 0, 0] == full.model.base[0, 0, 0]
    assert (half.to_frame()["power"] < full.to_frame()["power"]).all()
    assert half.model.details["effect_scale"] == 0.5


def test_a_pilot_without_both_conditions_is_one_line_naming_the_option(tmp_path):
    one = write_dataset(tmp_path / "one", SyntheticSpec(n_participants=3, repetitions=1,
                                                        accuracy={"pixel-only": 0.5}))
    design = design_from_protocol("digit_identification")
    with pytest.raises(PowerError, match=r"^--pilot .*one: no analysed trial of condition\(s\) "
                                         r"\['crs'\]"):
        model_from_pilot(design, one)


def test_a_pilot_that_is_not_a_dataset_is_one_line_naming_the_option(tmp_path):
    design = design_from_protocol("digit_identification")
    with pytest.raises(PowerError, match=r"^--pilot .*nothing"):
        model_from_pilot(design, tmp_path / "nothing")
