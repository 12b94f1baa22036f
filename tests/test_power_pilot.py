"""Mode 1: the effect from a pilot dataset, fitted as ``analyze`` fits it, then extended."""

from __future__ import annotations

import numpy as np
import pytest
from _power_helpers import pilot_model_matching_analyze

from crs_study.analysis.synthetic import SyntheticSpec, write_dataset
from crs_study.power_analysis import PowerError, design_from_protocol, model_from_pilot, power


@pytest.fixture(scope="module")
def pilot(tmp_path_factory):
    spec = SyntheticSpec(n_participants=8, repetitions=3, participant_sd=0.5, digit_sd=0.4,
                         accuracy={"pixel-only": 0.5, "crs": 0.65}, seed=31)
    return write_dataset(tmp_path_factory.mktemp("pilot") / "pilot", spec)


def test_the_pilots_model_is_analyzes_fit(pilot):
    """The fixed effects and SDs that generate the studies are those of analyze's primary
    GLMM on the pilot (same sessions, exclusions, plan)."""
    model, variances = pilot_model_matching_analyze("digit_identification", pilot)
    assert model.participant_sd == pytest.approx(np.sqrt(variances["participant_id"]))
    assert model.digit_sd == pytest.approx(np.sqrt(variances["digit"]))
    assert model.source == "pilot" and model.details["n_participants"] == 8


def test_the_effect_scale_shrinks_the_condition_effect_and_the_power(pilot):
    kwargs = dict(pilot=pilot, participants="4:8:4", studies=150, jobs=1, seed=3)
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
