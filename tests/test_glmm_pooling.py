"""Pooling rows of a GLMM fit: ``row_codes`` against numpy's ``unique`` over rows.

Reference: ``numpy.unique(axis=0, return_inverse=True)`` (the distinct rows in
lexicographic order and each row's index among them), which ``row_codes`` must equal
whichever way it builds its keys (mixed radix of whole numbers, or column-wise codes).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis.glmm_data import row_codes


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 80), k=st.integers(1, 5), seed=st.integers(0, 2**20),
       high=st.integers(1, 40), kind=st.sampled_from(["whole", "half", "negative", "wide"]))
def test_row_codes_equal_numpys_unique_rows(n, k, seed, high, kind):
    rng = np.random.default_rng(seed)
    columns = rng.integers(0, high, (n, k)).astype(float)
    if kind == "half":
        columns[:, 0] += 0.5 * rng.integers(0, 2, n)
    elif kind == "negative":
        columns[:, -1] -= high // 2
    elif kind == "wide":
        columns[:, 0] *= 10_000
    inverse, distinct = row_codes(columns)
    expected, expected_inverse = np.unique(columns, axis=0, return_inverse=True)
    assert np.array_equal(distinct, expected)
    assert np.array_equal(inverse, expected_inverse.ravel())
