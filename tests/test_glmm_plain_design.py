"""The design of a formula of plain numeric columns is built without patsy; it must be the
design patsy builds (the outside reference: patsy's ``dmatrix``), and every other formula
must go to patsy. The columns a fit pools are factorised by counting where they are small
whole numbers; the codes must be pandas'."""

import numpy as np
import pandas as pd
import patsy
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis.glmm_data import factorize, patsy_design, plain_design

DATA = pd.DataFrame({"c": [0.0, 1.0, 0.0, 1.0, 1.0], "x": [1, 2, 3, 4, 5],
                     "flag": [True, False, True, False, True],
                     "label": ["a", "b", "a", "b", "a"],
                     "gap": [0.5, np.nan, 1.0, 2.0, 3.0]},
                    index=[10, 11, 12, 13, 14])
TOKENS = ["c", "x", "flag", "label", "gap", "1", "0", "-1", "C(c)", "c:x", "np.log(x)",
          "Intercept", "missing"]


@settings(max_examples=120, deadline=None)
@given(st.lists(st.sampled_from(TOKENS), min_size=1, max_size=4),
       st.sampled_from([" + ", "+", "  +  "]))
def test_a_plain_design_is_patsys_and_anything_else_goes_to_patsy(tokens, joiner):
    formula = joiner.join(tokens)
    plain = plain_design(DATA, formula)
    try:
        reference = patsy.dmatrix(formula, DATA, NA_action="raise", return_type="dataframe")
    except Exception:       # patsy refuses it: it must not be read as plain
        assert plain is None
        return
    if plain is None:
        return
    assert list(plain.columns) == list(reference.columns)
    assert plain.index.equals(reference.index)
    np.testing.assert_array_equal(plain.to_numpy(), reference.to_numpy())


def test_the_plain_forms_are_taken_and_the_others_are_not():
    for formula in ["1 + c", "c", "0 + c", "1", "1 + c + x", " c + x "]:
        assert plain_design(DATA, formula) is not None, formula
    for formula in ["0", "flag", "label", "1 + gap", "c + c", "-1 + c", "C(c)", "c:x",
                    "1 + missing", "True"]:
        assert plain_design(DATA, formula) is None, formula


def test_a_bad_formula_still_gets_patsys_one_line_error():
    import pytest

    from crs_study.errors import AnalysisError
    with pytest.raises(AnalysisError, match="missing"):
        patsy_design(DATA, "1 + missing")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.integers(0, 30), st.integers(-5, 5),
                          st.floats(-1e3, 1e3, allow_nan=False), st.sampled_from([0.0, 1.0])),
                min_size=1, max_size=60),
       st.sampled_from(["float", "int"]))
def test_factorize_gives_pandas_sorted_codes(values, kind):
    """The counting path for small whole numbers and pandas' hashing for the rest give
    ``pandas.factorize(sort=True)``'s codes (the outside reference) and count."""
    if kind == "int":
        column = np.array([int(v) for v in values], dtype=np.int64)
    else:
        column = np.array(values, dtype=float)
    codes, distinct = factorize(column)
    expected, uniques = pd.factorize(column, sort=True)
    np.testing.assert_array_equal(codes, expected)
    assert distinct == len(uniques)
