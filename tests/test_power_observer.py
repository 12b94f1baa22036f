"""Mode 2 (the simulated observer's predicted accuracies) and mode 3 (real dry-runs).

The prediction uses the observer's own decision rule (checked against
``PerceptualObserver.choice_probabilities``); mode 2's power is checked against mode 3's on
the same protocol at two points (``tests/fixtures/power/fidelity_full.csv``, 150 studies of
real dry-runs made by ``make_fidelity.py``), within the Monte Carlo error of both.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _session_helpers import tiny_protocol

from crs_study.power import design_from_protocol, power
from crs_study.power.observer import _choice_probability, predict, shown_stimulus
from crs_study.protocol import load_protocol

FIXTURES = Path(__file__).parent / "fixtures" / "power"
sys.path.insert(0, str(FIXTURES))
import make_fidelity  # noqa: E402  (the fixture's own generator, beside it)


def test_the_choice_rule_is_the_observers(layout2d):
    from crs_study.responders.observer import PerceptualObserver

    protocol = load_protocol("protocols/digit_identification.toml")
    observer = PerceptualObserver(layout2d, protocol, 3)
    record = shown_stimulus(protocol, layout2d, 4, "crs", None)
    choices = tuple(protocol.digits)
    for j in range(5):
        path = observer.peak_path(record, np.random.default_rng([1, j]))
        p, d = observer.choice_probabilities(path, choices)
        ours = _choice_probability(d[None, None, None, None, :], np.array([[[4]]]),
                                   observer.temperature_mm, observer.options.lapse)
        assert ours[0, 0, 0, 0] == pytest.approx(p[choices.index(4)], rel=1e-12)
    guess = _choice_probability(np.full((1, 1, 1, 1, 10), np.nan), np.array([[[0]]]), 1.0,
                                0.05)
    assert guess[0, 0, 0, 0] == pytest.approx(0.1)          # too short a path: a guess


def test_predictions_are_deterministic_and_shaped_by_the_protocol(tmp_path):
    path = tiny_protocol(tmp_path, digits=(1, 4, 7))
    first = predict(path, draws=6)
    again = predict(path, draws=6)
    assert first.accuracy.shape == (1, 3, 2) and first.distances.shape == (1, 3, 2, 6, 3)
    assert np.array_equal(first.accuracy, again.accuracy)
    assert ((first.accuracy > 0) & (first.accuracy < 1)).all()
    assert first.participant_sd() > 0
    assert predict(path, draws=6, ability_sd=0.0).participant_sd() == 0.0


@pytest.fixture(scope="module")
def mode2():
    """Mode 2 at the fixture's points, many studies (the observer's default prediction)."""
    return power("digit_identification", participants=make_fidelity.PARTICIPANTS,
                 studies=2000, seed=5)


def test_mode_2_and_mode_3_agree_within_the_monte_carlo_error(mode2):
    """At N = 2 and 3 the power from the predicted accuracies and from real dry-runs
    (analysed as analyze does) differ by less than 2.5 standard errors of the difference."""
    full = pd.read_csv(FIXTURES / "fidelity_full.csv")
    table = mode2.to_frame()
    for n in make_fidelity.PARTICIPANTS:
        rows = full.loc[full["n"] == n]
        k3, s3 = int((rows["p_value"] < 0.05).sum()), len(rows)
        row = table.loc[table["participants"] == n].iloc[0]
        p2, p3 = row["power"], k3 / s3
        se = np.sqrt(p2 * (1 - p2) / row["studies"] + p3 * (1 - p3) / s3)
        assert abs(p2 - p3) < 2.5 * se, (n, p2, p3, se)
        assert 0.3 < p3 < 0.995                               # points that can tell


def test_the_mode_3_fixture_is_what_the_code_makes_now():
    """Study 0 of the fixture rerun (two real sessions, analysed): the same p-values."""
    result = power("digit_identification", fidelity="full", participants=(2,), studies=2,
                   seed=make_fidelity.SEED)
    stored = pd.read_csv(FIXTURES / "fidelity_full.csv")
    for study in range(2):
        row = stored.loc[(stored["n"] == 2) & (stored["study"] == study)].iloc[0]
        assert result.raw["p_value"][0, study, 0] == pytest.approx(row["p_value"], rel=1e-9)
    assert result.raw["reference"].all() and result.fidelity == "full"


def test_mode_2_takes_a_given_participant_sd_and_the_designs_condition_order():
    from crs_study.power.observer import model_from_observer

    design = design_from_protocol("digit_identification")
    model = model_from_observer(design, "digit_identification", participant_sd=0.2, draws=4)
    assert model.participant_sd == 0.2 and model.source == "observer"
    assert model.details["participant_sd_given"] is True
    assert model.details["participant_sd_from_calibration"] > 0
    assert design.conditions == ("pixel-only", "crs")
    accuracy = model.accuracy()
    assert accuracy[1] > accuracy[0]                 # CRS above pixel-only, as calibrated
    assert model.base.shape == (1, 10, 2) and np.isfinite(model.base).all()
