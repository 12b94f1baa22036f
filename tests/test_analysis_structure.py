"""The primary model's random structure: the plan's keys, the maximal model, the reduction
rule for a singular fit, and lme4's notation (parser and labels).

Outside references: lme4's formula notation (Bates et al. 2015, J. Stat. Softw. 67(1),
Table 2: ``(1 + x | g)``, ``(x || g)``, ``(0 + x | g)``); the rule of Barr et al. (2013,
J. Mem. Lang. 68:255) and Bates et al. (2015, "Parsimonious mixed models") as the plan states
it; lme4's own reduction of the same datasets is in the slopes corpus
(tests/test_glmm_slopes_corpus.py).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis.glmm_simulate import simulate_cells, slope_covariance
from crs_study.analysis.glmm_terms import RandomTerm, parse_random, structure_label
from crs_study.analysis.plan import AnalysisPlan
from crs_study.analysis.primary import fit_primary, primary_test
from crs_study.analysis.structure import RandomSpec, planned_terms, written_terms
from crs_study.errors import AnalysisError, PlanError

CONDITIONS = ["pixel-only", "crs"]


def _cells(seed: int, participants: int = 12, slope_sd: float = 0.6, symbol_slope: float = 0.0,
           correlation: float = 0.0, effect: float = 0.6):
    return simulate_cells(np.random.default_rng(seed), participants, 10, 8, [0.0, effect],
                          slope_covariance(0.6, slope_sd, correlation),
                          slope_covariance(0.3, symbol_slope), conditions=CONDITIONS)


# ------------------------------------------------------------------------------- notation
@pytest.mark.parametrize(("text", "expected"), [
    ("(1 | participant)", [("1", "participant", True)]),
    ("(1 + condition | participant) + (1 | digit)",
     [("1 + condition", "participant", True), ("1", "digit", True)]),
    ("(condition || participant)", [("condition", "participant", False)]),
    ("  (0 + condition|symbol)  ", [("0 + condition", "symbol", True)]),
])
def test_lme4_terms_are_read(text, expected):
    assert parse_random(text) == expected


@pytest.mark.parametrize(("text", "match"), [
    ("", "expected lme4 terms"),
    ("1 | participant", "cannot read"),
    ("(1 | participant) (1 | digit)", "cannot read"),
    ("(1 | participant) + (1 | participant)", "appears twice"),
    ("( | participant)", "nothing before the bar"),
    ("(1 | participant) + x", r"cannot read '\+ x'"),
])
def test_unreadable_random_parts_are_one_line_errors(text, match):
    with pytest.raises(AnalysisError, match=match) as info:
        parse_random(text)
    assert "\n" not in str(info.value)


@settings(max_examples=200, deadline=None)
@given(st.text(alphabet="()|+ 01abcdgiknoprstu_", max_size=40))
def test_the_parser_never_fails_otherwise(text):
    try:
        terms = parse_random(text)
    except AnalysisError as exc:
        assert "\n" not in str(exc)
    else:
        assert terms and all(group for _, group, _ in terms)


def test_labels_are_lme4s():
    assert RandomTerm("participant_id", ("Intercept", "condition[crs]")).label() == \
        "(1 + condition | participant)"
    assert RandomTerm("digit", ("Intercept", "condition[crs]"), False).label() == \
        "(1 + condition || digit)"
    assert RandomTerm("digit", ("condition[crs]",)).label() == "(0 + condition | digit)"
    assert structure_label([]) == "none"


def test_written_structures_hold_the_intercept_and_condition_only():
    assert written_terms("(1 + condition | participant) + (1 | symbol)") == [
        ("participant", True, True, True), ("symbol", True, False, True)]
    assert written_terms("(0 + condition || digit)") == [("digit", False, True, False)]
    with pytest.raises(AnalysisError, match="'level' in the term of 'participant'"):
        written_terms("(1 + level | participant)")
    with pytest.raises(AnalysisError, match="grouping factor 'session'"):
        written_terms("(1 | session)")


# ------------------------------------------------------------------------------- the plan
def _plan(**primary):
    return AnalysisPlan.from_dict({"plan": {"name": "x"}, "primary": primary}, "p.toml")


def test_the_plans_default_is_the_maximal_model_with_its_singular_fits_kept():
    primary = _plan().primary
    assert (primary.structure, primary.singular_fit, primary.reduction) == (
        "maximal", "keep", ("correlations", "slopes"))
    written = _plan(structure="(1 + condition | participant) + (1 | digit)").primary
    assert written.random_effects == ("participant", "digit")


@pytest.mark.parametrize(("primary", "match"), [
    ({"structure": "(1 + level | participant)"}, r"primary\.structure: .*'level'"),
    ({"structure": "(1 | participant)", "random_effects": ["participant", "digit"]},
     r"primary\.structure: .*name the same factors"),
    ({"singular_fit": "ignore"}, r"primary\.singular_fit: expected one of"),
    ({"reduction": ["slopes", "everything"]}, r"primary\.reduction: expected values among"),
    ({"method": "agq", "structure": "maximal"}, "adaptive quadrature needs a single"),
])
def test_bad_structures_are_refused_naming_the_key(primary, match):
    with pytest.raises(PlanError, match=match) as info:
        _plan(**primary)
    assert "\n" not in str(info.value)


# ------------------------------------------------------------------------------- maximal
def test_the_maximal_model_has_a_slope_where_condition_varies_within():
    cells = _cells(1)
    columns = {"participant": "participant_id", "digit": "digit", "symbol": "digit"}
    spec = RandomSpec(("participant", "digit"))
    terms, notes = planned_terms(spec, cells, ["condition[crs]"], columns)
    assert structure_label(terms) == "(1 + condition | participant) + (1 + condition | digit)"
    assert not notes
    between = cells.loc[(cells["participant_id"] < "p06") == (cells["condition"] == "crs")]
    terms, notes = planned_terms(spec, between, ["condition[crs]"], columns)
    assert structure_label(terms) == "(1 | participant) + (1 + condition | digit)"
    assert "condition does not vary within participant" in notes[0]


def test_a_regular_maximal_fit_is_used_as_planned():
    fits = fit_primary(_cells(2, participants=20, symbol_slope=0.4), CONDITIONS, "pixel-only",
                       ("participant", "digit"))
    assert len(fits.steps) == 1 and not fits.steps[0].action
    assert fits.full.random_formula == \
        "(1 + condition | participant) + (1 + condition | digit)"
    assert fits.tests[0].reduced.random_formula == fits.full.random_formula   # slopes kept


def test_a_singular_fit_is_reduced_step_by_step_and_every_step_is_told():
    # no symbol slope in the truth: the symbols' term loses rank; the rule drops the
    # correlations, then the slope whose variance is smallest, until the fit is regular
    fits = fit_primary(_cells(4), CONDITIONS, "pixel-only", ("participant", "digit"),
                       singular_fit="reduce")
    steps = fits.steps
    assert steps[0].formula == "(1 + condition | participant) + (1 + condition | digit)"
    assert steps[0].singular and "dropped the correlations" in steps[0].action
    assert "dropped the random slope of 'condition[crs]' by digit" in "".join(
        s.action for s in steps)
    assert not steps[-1].action and not steps[-1].singular
    assert fits.full.random_formula == steps[-1].formula
    assert "(1 + condition || participant)" in fits.full.random_formula
    kept = fit_primary(_cells(4), CONDITIONS, "pixel-only", ("participant", "digit"))
    assert len(kept.steps) == 1 and kept.full.is_singular          # the default: keep


def test_the_report_says_which_model_was_fitted_and_why():
    result = primary_test(_cells(4), CONDITIONS, "pixel-only", ("participant", "digit"),
                          singular_fit="reduce")
    structure = result.model["structure"]
    assert structure["planned"] == "(1 + condition | participant) + (1 + condition | digit)"
    assert structure["reduced"] and structure["fitted"] != structure["planned"]
    assert [s["random"] for s in structure["steps"]][0] == structure["planned"]
    summary = result.summary()
    assert "Random effects:" in summary and "Fixed effects:" in summary
    assert "the plan asks for 'maximal'" in summary and "dropped the correlations" in summary
    assert repr(result).startswith("<PrimaryResult correct ~ condition + (1")


def test_intercepts_alone_are_fitted_when_planned_and_flagged():
    result = primary_test(_cells(4), CONDITIONS, "pixel-only", ("participant", "digit"),
                          structure="intercepts")
    assert result.model["random_formula"] == "(1 | participant) + (1 | digit)"
    assert any("anti-conservative" in w for w in result.warnings)


def test_a_written_structure_is_fitted_as_written():
    fits = fit_primary(_cells(5), CONDITIONS, "pixel-only", ("participant", "digit"),
                       structure="(1 + condition || participant) + (1 | digit)")
    assert fits.full.random_formula == "(1 + condition || participant) + (1 | digit)"


def test_a_model_that_cannot_be_fitted_is_reduced_like_a_singular_one(monkeypatch):
    from crs_study.analysis import glmm, primary

    calls = []
    real = glmm.fit_glmm

    def failing_with_slopes(*args, **kwargs):
        calls.append(structure_label(kwargs["random"]))
        if any(t.size > 1 for t in kwargs["random"]):
            raise glmm.GlmmFitError("numerical failure (a test)")
        return real(*args, **kwargs)

    monkeypatch.setattr(primary.glmm, "fit_glmm", failing_with_slopes)
    fits = fit_primary(_cells(6), CONDITIONS, "pixel-only", ("participant", "digit"))
    assert fits.full.random_formula == "(1 | participant) + (1 | digit)"
    assert fits.steps[0].error == "numerical failure (a test)"
    assert "the fit failed" in fits.steps[0].action


def test_the_structure_travels_into_results_json_keys():
    result = primary_test(_cells(7), CONDITIONS, "pixel-only", ("participant",))
    table = pd.DataFrame(result.model["random_effects_table"])
    assert set(table.columns) >= {"group", "effect", "variance", "sd", "corr"}
    assert result.model["structure"]["effects"] == ["participant"]
