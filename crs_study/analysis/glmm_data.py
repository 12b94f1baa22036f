"""The data of a GLMM fit, prepared: the design, the responses, the groups and the pooled rows.

What :func:`crs_study.analysis.glmm.fit_glmm` does before it maximises anything: the fixed
design from a patsy formula or a matrix (aliased columns and unused levels dropped, each
noted), the responses as successes out of trials, each random term's level codes and design
(a grouping factor with one level dropped), and rows sharing every one of these pooled into
one binomial row (the likelihood kernel is the same; 16,000 trials of a two-condition design
cost as much as 80 rows).
"""

from __future__ import annotations

import keyword
import re

import numpy as np
import pandas as pd
from scipy.special import gammaln

from crs_study.analysis.glmm_core import MAX_QUADRATURE, BinomialData
from crs_study.analysis.glmm_terms import RandomTerm, parse_random
from crs_study.errors import AnalysisError


def random_terms(data: pd.DataFrame, random, random_design) -> list[RandomTerm]:
    """The terms of ``random`` (lme4 text, or RandomTerm objects), their columns checked."""
    if isinstance(random, str):
        return [RandomTerm(group, tuple(patsy_columns(data, design)), correlated, design)
                for design, group, correlated in parse_random(random)]
    terms = list(random)
    for term in terms:
        if not isinstance(term, RandomTerm):
            raise AnalysisError(f"random= takes lme4 text or RandomTerm objects, got "
                                f"{type(term).__name__}")
        if term.design is None and not term.is_intercept:
            if random_design is None:
                raise AnalysisError(f"random term {term.label()} names design columns "
                                    f"{list(term.columns)!r}: give them as random_design=")
            missing = [c for c in term.columns if c not in random_design.columns]
            if missing:
                raise AnalysisError(f"random term {term.label()}: column(s) {missing!r} are "
                                    f"not in random_design {list(random_design.columns)!r}")
    return terms


def patsy_columns(data: pd.DataFrame, design: str) -> list[str]:
    return list(patsy_design(data, design).columns)


#: A formula of numeric columns alone, with or without the intercept: ``1 + c``, ``c``,
#: ``0 + c``, ``1``.
_PLAIN_FORMULA = re.compile(r"^\s*(?:(?P<intercept>[01])\s*(?:\+\s*|$))?"
                            r"(?P<columns>[A-Za-z_]\w*(?:\s*\+\s*[A-Za-z_]\w*)*)?\s*$")


def plain_columns(data: pd.DataFrame, formula: str) -> tuple[list[str], bool] | None:
    """``(columns, intercept)`` of a formula that is a sum of numeric columns without
    missing values (``intercept`` unless it starts with ``0``), or None for any other
    formula, which patsy reads."""
    match = _PLAIN_FORMULA.match(formula)
    if match is None or not formula.strip():
        return None
    names = re.split(r"\s*\+\s*", match["columns"].strip()) if match["columns"] else []
    if len(set(names)) != len(names):
        return None
    for name in names:
        if name not in data.columns or name == "Intercept" or keyword.iskeyword(name):
            return None
        column = data[name]
        dtype = column.dtype
        if isinstance(dtype, np.dtype):     # numeric but not bool, no NaN (pandas' checks)
            if dtype.kind not in "iufc" or (dtype.kind in "fc"
                                            and np.isnan(column.to_numpy()).any()):
                return None
        elif not (pd.api.types.is_numeric_dtype(column) and not pd.api.types.is_bool_dtype(
                column)) or column.isna().any():
            return None
    intercept = match["intercept"] != "0"
    return (names, intercept) if names or intercept else None


def plain_matrix(data: pd.DataFrame, formula: str) -> tuple[np.ndarray, list[str]] | None:
    """The design patsy builds for a sum of numeric columns (:func:`plain_columns`) as
    ``(matrix, column names)``, the intercept first, named ``Intercept``; None for any
    other formula."""
    plain = plain_columns(data, formula)
    if plain is None:
        return None
    names, intercept = plain
    X = np.empty((len(data), len(names) + intercept))
    if intercept:
        X[:, 0] = 1.0
    for j, name in enumerate(names):
        X[:, j + intercept] = data[name].to_numpy(dtype=float)
    return X, ["Intercept"] * intercept + names


def plain_design(data: pd.DataFrame, formula: str) -> pd.DataFrame | None:
    """:func:`plain_matrix` as patsy's data frame (the data's index), or None. A fit's
    several designs cost more through patsy than the fit."""
    plain = plain_matrix(data, formula)
    if plain is None:
        return None
    return pd.DataFrame(plain[0], columns=plain[1], index=data.index)


def patsy_design(data: pd.DataFrame, formula: str,
                  what: str = "random-effects formula") -> pd.DataFrame:
    plain = plain_design(data, formula)
    if plain is not None:
        return plain
    import patsy

    try:
        return patsy.dmatrix(formula, data, NA_action="raise", return_type="dataframe")
    except patsy.PatsyError as exc:
        message = str(exc).splitlines()[0]
        raise AnalysisError(f"{what} {formula!r}: {message}") from None


# ----------------------------------------------------------------------------- preparation
def check_arguments(data, response, trials, group_list, method, n_quadrature) -> None:
    if not isinstance(data, pd.DataFrame):
        raise AnalysisError(f"fit_glmm expects a pandas DataFrame, got {type(data).__name__}")
    for role, col in [("response", response), ("trials", trials)] + [
            ("group", g) for g in group_list]:
        if col is not None and col not in data.columns:
            raise AnalysisError(f"{role} column {col!r} is not in the data; columns: "
                                f"{list(data.columns)!r}")
    if method not in ("laplace", "agq"):
        raise AnalysisError(f"method must be 'laplace' or 'agq', got {method!r}")
    if (isinstance(n_quadrature, bool) or not isinstance(n_quadrature, int | np.integer)
            or not 1 <= n_quadrature <= MAX_QUADRATURE):
        raise AnalysisError(f"n_quadrature must be an integer in 1..{MAX_QUADRATURE}, "
                            f"got {n_quadrature!r}")
    if len(data) == 0:
        raise AnalysisError("no rows to fit: the data frame is empty")


def drop_unused_levels(data: pd.DataFrame, fixed, notes: list[str]) -> pd.DataFrame:
    """Remove categories without rows from categorical columns named in the formula."""
    if not isinstance(fixed, str):
        return data
    tokens = set(re.findall(r"[A-Za-z_][A-Za-z0-9_.]*", fixed))
    out = data
    for col in [c for c in data.columns if c in tokens]:     # a column read costs: named only
        if isinstance(data[col].dtype, pd.CategoricalDtype):
            present = set(data[col].dropna().unique())
            unused = [c for c in data[col].cat.categories if c not in present]
            if unused:
                out = out.copy() if out is data else out
                out[col] = out[col].cat.remove_unused_categories()
                notes.append(f"level(s) {unused!r} of {col!r} have no trials; dropped from the "
                             f"model")
    return out


def fixed_design(data: pd.DataFrame, fixed) -> tuple[np.ndarray, list[str]]:
    if isinstance(fixed, pd.DataFrame):
        if not fixed.index.equals(data.index):
            raise AnalysisError(f"the design matrix's rows must be the data's (same index): "
                                f"{len(fixed)} rows against {len(data)}, or another order")
        X = fixed.to_numpy(dtype=float)
        names = [str(c) for c in fixed.columns]
    elif isinstance(fixed, str):
        if "~" in fixed:
            raise AnalysisError(f"fixed is the right-hand side of a formula (e.g. 'condition'), "
                                f"got {fixed!r}; give the response as response=")
        plain = plain_matrix(data, fixed)
        if plain is None:
            design = patsy_design(data, fixed, "fixed-effects formula")
            X, names = design.to_numpy(dtype=float), list(design.columns)
        else:
            X, names = plain
    else:
        raise AnalysisError(f"fixed must be a formula string or a DataFrame, got "
                            f"{type(fixed).__name__}")
    if not np.all(np.isfinite(X)):
        raise AnalysisError("the fixed-effects design has missing or infinite values")
    return X, names


def drop_aliased(X: np.ndarray, names: list[str], notes: list[str]):
    """Drop design columns that are zero or linear combinations of others (lme4 does too)."""
    from scipy.linalg import qr

    if X.shape[1] == 0:
        raise AnalysisError("the fixed-effects design has no columns")
    # X is finite (fixed_design checked it): no second scan
    _, R, piv = qr(X, mode="economic", pivoting=True, check_finite=False)
    diag = np.abs(np.diag(R))
    rank = int(np.sum(diag > max(X.shape) * np.finfo(float).eps * diag[0])) if diag[0] else 0
    if rank == X.shape[1]:
        return X, names
    keep = np.sort(piv[:rank])
    dropped = [names[i] for i in sorted(piv[rank:])]
    notes.append(f"fixed-effect column(s) {dropped!r} are empty or aliased with others "
                 f"(a condition without trials?); dropped")
    return X[:, keep], [names[i] for i in keep]


def response_arrays(data: pd.DataFrame, response: str, trials: str | None):
    """Successes, trials and the binomial constant ``sum log C(trials, successes)``."""
    column = data[response]
    y = (column.to_numpy(dtype=float) if isinstance(column.dtype, np.dtype)
         and column.dtype.kind in "iuf"
         else pd.to_numeric(column, errors="coerce").to_numpy(dtype=float))
    bad = ~np.isfinite(y)
    if bad.any():
        first = data[response].to_numpy()[bad][0]
        raise AnalysisError(f"response {response!r} has {int(bad.sum())} missing or non-numeric "
                            f"value(s), e.g. {first!r}")
    if trials is None:
        if not np.all((y == 0) | (y == 1)):
            raise AnalysisError(f"response {response!r} must be 0/1 per trial (or give trials=), "
                                f"got {y[(y != 0) & (y != 1)][0]!r}")
        return y, np.ones_like(y), 0.0
    m = pd.to_numeric(data[trials], errors="coerce").to_numpy(dtype=float)
    if not np.all(np.isfinite(m)) or np.any(m < 0) or np.any(m != np.round(m)):
        raise AnalysisError(f"trials {trials!r} must be non-negative integers")
    if np.any(y < 0) or np.any(y > m) or np.any(y != np.round(y)):
        raise AnalysisError(f"response {response!r} must be integers between 0 and {trials!r}")
    constant = float(np.sum(gammaln(m + 1) - gammaln(y + 1) - gammaln(m - y + 1)))
    return y, m, constant


def group_codes(data: pd.DataFrame, terms: list[RandomTerm], notes: list[str]):
    """The level codes of each term's grouping factor; a factor of one level is dropped."""
    codes, kept = [], []
    for term in terms:
        g = term.group
        column = data[g]
        # a categorical column's levels in its categories' order, any other's sorted
        if isinstance(column.dtype, pd.CategoricalDtype):
            c, levels = pd.factorize(column, sort=True)
            count = len(levels)
        else:
            values = column.to_numpy()
            c, count = factorize(values)
            levels = values[:1]       # the one level, where there is one
        if (c < 0).any():        # factorize codes a missing value -1
            raise AnalysisError(f"group column {g!r} has {int((c < 0).sum())} missing "
                                f"value(s)")
        if count < 2:
            shown = term.shown_group()  # as the report names it: participant
            what = "random intercept" if term.is_intercept else f"random term {term.label()}"
            notes.append(f"grouping factor {shown!r} has a single level ({levels[0]!r}): its "
                         f"variance is not estimable; the {what} was dropped")
            continue
        codes.append(c.astype(np.intp))
        kept.append(term)
    if terms and not kept:
        notes.append("no random effect left: fitted a fixed-effects logistic regression")
    return codes, kept


def term_designs(data: pd.DataFrame, terms: list[RandomTerm], random_design,
                  notes: list[str]) -> tuple[tuple[np.ndarray, ...], list[RandomTerm]]:
    """Each term's design ``Z`` (n, r); a column with no nonzero entry (a condition without
    trials) is dropped from its term, with a note."""
    Z, kept = [], []
    for term in terms:
        if term.is_intercept and term.design is None:
            Z.append(np.ones((len(data), 1)))
            kept.append(term)
            continue
        frame = (patsy_design(data, term.design) if term.design is not None
                 else random_design.loc[data.index, list(term.columns)])
        z = frame.to_numpy(dtype=float)
        if not np.all(np.isfinite(z)):
            raise AnalysisError(f"random term {term.label()}: its design has missing or "
                                f"infinite values")
        empty = [c for c, col in zip(term.columns, z.T, strict=True) if not np.any(col)]
        for column in empty:
            notes.append(f"random term {term.label()}: column {column!r} is zero on every "
                         f"row; dropped from the term")
            term = term.without(column)
        z = z[:, [i for i, c in enumerate(frame.columns) if c not in empty]]
        Z.append(z)
        kept.append(term)
    return tuple(Z), kept


def factorize(column: np.ndarray) -> tuple[np.ndarray, int]:
    """``(codes, distinct)``: each value's index among the column's sorted distinct values
    (``pandas.factorize(sort=True)``'s codes) and their number. A column of small
    non-negative whole numbers (level codes, 0/1 designs: every column a fit pools) is
    counted instead of hashed, several times cheaper on the few thousand rows of a study."""
    if column.dtype.kind in "iuf" and len(column):
        low, high = column.min(), column.max()
        if low >= 0 and high <= 4 * len(column) and (
                column.dtype.kind != "f" or np.array_equal(column, np.floor(column))):
            whole = column.astype(np.intp)
            present = np.bincount(whole) > 0
            return (np.cumsum(present) - 1)[whole], int(present.sum())
    codes, uniques = pd.factorize(column, sort=True)
    return codes, len(uniques)


def _whole_key(columns: np.ndarray) -> np.ndarray | None:
    """Each row's mixed-radix number ``sum_j c_j prod_{l > j} (max_l + 1)`` when every entry
    is a small non-negative whole number (level codes, 0/1 designs): ordered as the rows,
    as the column-wise codes' key is, in one pass; None otherwise."""
    if columns.dtype.kind not in "iuf" or not columns.size:
        return None
    high = columns.max(axis=0)
    if columns.min() < 0 or np.prod(high + 1.0) > 4.0 * len(columns) + 1.0 or \
            not np.array_equal(columns, np.floor(columns)):
        return None
    radix = (high + 1).astype(np.int64)
    weights = np.append(np.cumprod(radix[:0:-1])[::-1], 1)    # prod_{l > j} radix_l
    return columns.astype(np.int64) @ weights


def row_codes(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of each row's distinct value (rows of a 2-D array) and one row per distinct value.

    Column-wise factorisation (:func:`factorize`, sorted codes) combined in mixed radix:
    much faster than ``np.unique(axis=0)``, which sorts rows as opaque byte strings, or
    ``np.unique`` per column; the distinct rows come in sorted key order, as ``np.unique``
    gives them, so the pooled rows do not depend on the order of the data.
    """
    key = _whole_key(columns)
    if key is None:
        key = np.zeros(len(columns), dtype=np.int64)
        for col in columns.T:
            inverse, distinct = factorize(col)
            key = key * distinct + inverse
    inverse, distinct = factorize(key)
    first = np.empty(distinct, dtype=np.intp)
    first[inverse[::-1]] = np.arange(len(key) - 1, -1, -1)
    return inverse.astype(np.intp), columns[first]


def pool(X, y, m, codes, Z) -> BinomialData:
    """Sum successes and trials over rows with equal group levels, design row and random
    designs."""
    k = len(codes)
    widths = [z.shape[1] for z in Z]
    inverse, unique = row_codes(np.column_stack([*(c.astype(float) for c in codes), X,
                                                  *Z]))
    p = X.shape[1]
    ends = k + p + np.cumsum(widths, dtype=int)
    pooled_Z = tuple(unique[:, e - w:e] for e, w in zip(ends, widths, strict=True))
    return BinomialData(unique[:, k:k + p], np.bincount(inverse, y), np.bincount(inverse, m),
                        tuple(unique[:, i].astype(np.intp) for i in range(k)),
                        tuple(int(c.max()) + 1 for c in codes), pooled_Z or None)


def unpooled(X, y, m, codes, Z) -> BinomialData:
    return BinomialData(X, y, m, tuple(codes), tuple(int(c.max()) + 1 for c in codes),
                        tuple(Z) or None)
