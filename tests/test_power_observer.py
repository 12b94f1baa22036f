"""Mode 2 (the simulated observer's predicted accuracies) and mode 3 (real dry-runs).

The prediction uses the observer's own decision rule (checked against
``PerceptualObserver.choice_probabilities``); mode 2's power is checked against mode 3's on
the same protocol at two points (``tests/fixtures/power/fidelity_full.csv``, 200 studies of
real dry-runs made by ``make_fidelity.py``, its plan's random part random intercepts on both
sides), within the Monte Carlo error of both.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _session_helpers import tiny_protocol
from scipy import stats

from crs_study.power_analysis import design_from_protocol, power
from crs_study.power_analysis.observer import (
    _choice_probability,
    model_from_observer,
    predict,
    shown_stimulus,
)
from crs_study.protocol import load_protocol
from crs_study.session.dry_runs import dry_run
from crs_study.session.responders.observer import PerceptualObserver

FIXTURES = Path(__file__).parent / "fixtures" / "power"
sys.path.insert(0, str(FIXTURES))
import make_fidelity  # noqa: E402  (the fixture's own generator, beside it)


def test_the_choice_rule_is_the_observers(layout2d):

    protocol = load_protocol("protocols/digit_identification.toml")
    observer = PerceptualObserver(layout2d, protocol, 3)
    record = shown_stimulus(protocol, layout2d, 4, "crs", None)
    choices = tuple(protocol.symbols)
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
    cov = first.participant_covariance()
    assert cov.shape == (2, 2) and cov[1, 1] > 0        # people differ in the CRS benefit
    alike = predict(path, draws=6, ability_sd=0.0, benefit_sd=0.0)
    assert alike.participant_sd() == 0.0 and not alike.participant_covariance().any()


@pytest.fixture(scope="module")
def pilot_protocol(tmp_path_factory):
    """The fixture's protocol: the pilot, its plan's random part random intercepts (what is
    compared is the observer's accuracies against real dry-runs, the same model fitted to
    both; the maximal model on two to four participants costs seconds a study)."""
    return make_fidelity.pilot_protocol(tmp_path_factory.mktemp("pilot"))


@pytest.fixture(scope="module")
def mode2(pilot_protocol):
    """Mode 2 at the fixture's points, two and a half times the fixture's studies (50 noise
    draws of the observer per stimulus, as the letter test). The fixture's 200 studies carry
    most of the Monte Carlo error of the difference: with 500 studies here its SE is 8 %
    above what 1000 would give, at about 60 % of the test's cost."""
    return power(pilot_protocol, participants=make_fidelity.PARTICIPANTS,
                 studies=500, seed=5, draws=50)


def test_mode_2_and_mode_3_agree_within_the_monte_carlo_error(mode2):
    """At N = 2 and 4 (pilot protocol) the power from the predicted accuracies (500
    studies) and from real dry-runs analysed as analyze does (200 studies) cannot be told
    apart: Fisher's exact test of the two counts p > 0.05, and mode 2's power inside mode
    3's Clopper-Pearson 95 % interval."""
    full = pd.read_csv(FIXTURES / "fidelity_full.csv")
    table = mode2.to_frame()
    for n in make_fidelity.PARTICIPANTS:
        rows = full.loc[full["n"] == n]
        k3, s3 = int((rows["p_value"] < 0.05).sum()), len(rows)
        assert s3 == make_fidelity.STUDIES
        row = table.loc[table["participants"] == n].iloc[0]
        k2, s2 = int(row["significant"]), int(row["studies"])
        assert 0.15 < k3 / s3 < 0.85                        # points that can tell
        assert stats.fisher_exact([[k2, s2 - k2], [k3, s3 - k3]]).pvalue > 0.05
        interval = stats.binomtest(k3, s3).proportion_ci(0.95, method="exact")
        assert interval.low <= k2 / s2 <= interval.high, (n, k2 / s2, k3 / s3)


def test_the_mode_3_fixture_is_what_the_code_makes_now(pilot_protocol):
    """Two studies of the fixture rerun (real sessions, analysed): the same chi2 p-values
    (the reported p of a study also depends on the null studies of its point; the chi2 p
    does not depend on the observer's prediction, so few draws)."""
    result = power(pilot_protocol, fidelity="full", participants=(2,), studies=2,
                   seed=make_fidelity.SEED, draws=4)
    stored = pd.read_csv(FIXTURES / "fidelity_full.csv")
    for study in range(2):
        row = stored.loc[(stored["n"] == 2) & (stored["study"] == study)].iloc[0]
        assert result.raw["p_value"][0, study, 0] == pytest.approx(row["p_chi2"], rel=1e-9)
    assert result.raw["reference"].all() and result.fidelity == "full"


def test_the_shown_stimulus_is_what_a_session_displays(tmp_path, monkeypatch):
    """The displayed setpoints of every test trial of a dry-run session equal the once-shown
    stimulus's within a servo step (the refresh phase of the wire)."""

    records = []
    respond = PerceptualObserver.respond

    def recording(self, trial, stimulus, clock, limit):
        if trial.trial_type == "test":
            records.append((trial.symbol, trial.condition, stimulus.setpoints))
        return respond(self, trial, stimulus, clock, limit)

    path = tiny_protocol(tmp_path, digits=(1, 4, 7), repetitions=2)
    monkeypatch.setattr(PerceptualObserver, "respond", recording)
    dry_run(path, 1, tmp_path / "data")
    protocol = load_protocol(path)
    assert len(records) == 12
    for digit, condition, displayed in records:
        shown = shown_stimulus(protocol, protocol.layout(), digit, condition, None)
        assert shown.setpoints.shape == displayed.shape
        assert np.abs(shown.setpoints - displayed).max() < 0.02


def test_mode_2_takes_a_given_participant_sd_and_the_designs_condition_order():

    design = design_from_protocol("digit_identification")
    model = model_from_observer(design, "digit_identification", participant_sd=0.2, draws=4)
    assert model.participant_sd == 0.2 and model.source == "observer"
    assert model.details["participant_sd_given"] is True
    assert model.details["participant_sd_from_calibration"] > 0
    assert design.conditions == ("pixel-only", "crs")
    accuracy = model.accuracy()
    assert accuracy[1] > accuracy[0]                 # CRS above pixel-only, as calibrated
    assert model.base.shape == (1, 10, 2) and np.isfinite(model.base).all()


def test_participants_differ_as_the_observers_do(tmp_path):
    """Without a given SD a participant of ability z and benefit draw w has the observer's
    accuracy at the temperature T exp(ability_sd z -+ benefit_sd w / 2) in each condition
    (the table interpolated in the log-temperature offset)."""
    from scipy.special import logit


    path = tiny_protocol(tmp_path, digits=(1, 4, 7))
    design = design_from_protocol(path)
    prediction = predict(path, draws=6)
    model = model_from_observer(design, path, prediction=prediction)
    sides = np.array([-1.0, 1.0])                  # pixel-only, crs (the design's order)
    for z, w in ((0.0, 0.0), (0.73, -1.2), (-1.9, 0.4)):
        offsets = prediction.ability_sd * z + 0.5 * prediction.benefit_sd * sides * w
        direct = np.stack([logit(prediction.p_correct(prediction.temperature_mm
                                                      * np.exp(o)))[..., c]
                           for c, o in enumerate(offsets)], axis=-1)
        np.testing.assert_allclose(model.participant_logits(z, [w]), direct, atol=2e-3)
    sharp, blunt = model.participant_logits(-2.0), model.participant_logits(2.0)
    assert (sharp.mean(axis=1) > blunt.mean(axis=1)).all()     # lower temperature: better
    helped, hindered = model.participant_logits(0.0, [-2.0]), model.participant_logits(0.0,
                                                                                     [2.0])
    gain = lambda x: x[..., 1].mean() - x[..., 0].mean()      # noqa: E731
    assert gain(helped) > gain(hindered)                       # the benefit varies
    given = model_from_observer(design, path, participant_sd=0.3, prediction=prediction)
    assert given.ability is None
    np.testing.assert_allclose(given.participant_logits(1.0), given.base + 0.3)
    sloped = model_from_observer(design, path, participant_sd=0.3, participant_slope_sd=0.5,
                                 prediction=prediction)
    np.testing.assert_allclose(sloped.participant_logits(1.0, [2.0]),
                               sloped.base + 0.3 + np.array([0.0, 1.0]))
