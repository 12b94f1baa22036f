"""PowerResult: the table, the answer with its Monte Carlo range, the one line, JSON, chart."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from crs_study.power_analysis import PowerDesign, model_from_parameters
from crs_study.power_analysis.result import PowerResult
from crs_study.power_analysis.study import FISHER, LR, SEPARATED, WALD, recorded_parameters

DESIGN = PowerDesign(("pixel-only", "crs"), "pixel-only", tuple(range(10)), (None,), 5)
MODEL = model_from_parameters(DESIGN, {"pixel-only": 0.5, "crs": 0.6}, participant_sd=0.4)


def _result(powers, studies=1000, sizes=None, kinds=None) -> PowerResult:
    """A result whose point i has round(powers[i] * studies) significant studies."""
    sizes = sizes or tuple(4 * (i + 1) for i in range(len(powers)))
    P = len(powers)
    p = np.full((P, studies, 1), 0.5)
    for i, power in enumerate(powers):
        p[i, :round(power * studies), 0] = 0.001
    kind = np.full((P, studies, 1), LR, dtype=np.int8) if kinds is None else kinds
    raw = {"p_value": p, "kind": kind, "log_odds": np.where(p < 0.05, 0.4, 0.1),
           "theta": np.zeros((P, studies, len(recorded_parameters(DESIGN)))),
           "converged": np.ones((P, studies), bool),
           "boundary": np.zeros((P, studies), bool), "reduced": np.zeros((P, studies), bool),
           "reference": np.zeros((P, studies), bool),
           "loglike": np.zeros((P, studies)), "loglike_reduced": np.zeros((P, studies, 1))}
    return PowerResult(DESIGN, MODEL, tuple((n, 5) for n in sizes), raw, seed=1, target=0.8)


def test_each_point_has_its_clopper_pearson_interval():
    table = _result([0.3, 0.55, 0.79, 0.9]).to_frame()
    assert table["significant"].tolist() == [300, 550, 790, 900]
    for _, row in table.iterrows():
        ci = stats.binomtest(row["significant"], 1000).proportion_ci(method="exact")
        assert (row["ci_low"], row["ci_high"]) == pytest.approx((ci.low, ci.high))


def test_the_answer_and_its_monte_carlo_range():
    """The first N at the target; the range from the first N whose interval reaches it to
    the first N whose whole interval is above it."""
    result = _result([0.3, 0.79, 0.81, 0.84, 0.95])      # 0.79: interval reaches 0.8
    answer = result.answers()[0]
    assert (answer.n, answer.low, answer.high) == (12, 8, 16)
    assert result.headline() == ("80 % power at N = 12 (Monte Carlo 95 %: 8-16); 1000 "
                                 "studies per point; 0 fits failed")


@pytest.mark.parametrize("powers, expected", [
    pytest.param([0.95, 0.99], "80 % power at N = 4 (Monte Carlo 95 %: 4 or fewer); ",
                 id="at-the-first-point"),
    pytest.param([0.5, 0.81], "80 % power at N = 8 (Monte Carlo 95 %: 8 to beyond 8); ",
                 id="interval-beyond-the-curve"),
    pytest.param([0.2, 0.6], "80 % power not reached by N = 8 (there 60.0 %, Monte Carlo "
                             "95 %: 56.9-63.1 %); ", id="not-reached"),
])
def test_the_headline_in_every_case(powers, expected):
    assert _result(powers).headline().startswith(expected)


def test_failed_and_separated_fits_are_counted_never_folded_away():
    kinds = np.full((2, 100, 1), LR, dtype=np.int8)
    kinds[0, :2, 0] = FISHER
    kinds[0, 2, 0] = WALD
    kinds[1, :4, 0] = SEPARATED
    result = _result([0.5, 0.9], studies=100, kinds=kinds)
    table = result.to_frame()
    assert table["full_failed"].tolist() == [2, 0] and table["reduced_failed"].tolist() == [1, 0]
    assert table["separated"].tolist() == [0, 4] and table["failed"].tolist() == [3, 0]
    assert result.headline().endswith("100 studies per point; 3 fits failed, 4 separated "
                                      "(tested at the supremum, counted)")


def test_json_is_strict_and_complete():
    result = _result([0.3, 0.9])
    data = json.loads(result.to_json())
    assert data["headline"] == result.headline()
    assert [p["power"] for p in data["points"]] == [0.3, 0.9]
    assert data["design"]["conditions"] == ["pixel-only", "crs"]
    assert data["model"]["accuracy"]["crs"] == pytest.approx(0.6)
    assert data["answers"][0]["n"] == 8 and data["studies_per_point"] == 1000


def test_the_chart_is_a_pure_function_of_the_result(tmp_path):
    result = _result([0.3, 0.7, 0.9])
    ax = result.plot()
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["crs vs pixel-only", "target 80 %"]
    assert ax.get_xlabel() == "participants (N)" and ax.get_ylabel() == "power (p < 0.05)"
    json_path, png_path = result.save(tmp_path / "out")
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads(json_path.read_text())["headline"] == result.headline()
