"""Secondary tests of a condition against the reference, with effect sizes.

* **Paired t-test** on participant accuracies (``scipy.stats.ttest_1samp`` of the differences,
  the same test as ``ttest_rel``), effect size Cohen's
  ``d_z = mean(diff) / sd(diff)`` (Cohen 1988; Lakens 2013, Front. Psychol. 4:863, Eq. 6).
* **Wilcoxon signed-rank test** on the same differences, rounded to 12 decimals so that
  differences equal in exact arithmetic are tied (``scipy.stats.wilcoxon``, zero differences
  dropped, exact null distribution when small and untied), effect size the matched-pairs
  rank-biserial correlation ``r = (T+ - T-) / (T+ + T-)`` (Kerby 2014, Compr. Psychol. 3:11).
* **McNemar mid-p test** on trials paired by participant, session, symbol and repetition (and
  stimulus level when one varies): ``p_value`` is the mid-p value ``2 [P(X <= min(b, c)) -
  P(X = min(b, c)) / 2]``, ``X ~ Bin(b + c, 1/2)`` (Fagerland, Lydersen & Laake 2013, BMC
  Med. Res. Methodol. 13:91). The mid-p test is not exact (its size may exceed alpha a
  little) but is closer to nominal than the exact conditional test, whose p is kept as
  ``p_exact``. The conditional odds ratio ``c / b`` has the interval from the exact
  (Clopper-Pearson) interval of ``c / (b + c)`` mapped by ``p / (1 - p)`` (Breslow & Day
  1980, sec. 7.2).
* **Per-symbol comparisons**: the McNemar mid-p test within each symbol, corrected for the
  number of symbols with ``statsmodels.stats.multitest.multipletests`` (Holm 1979 by default,
  computed by :func:`adjusted_p_values` to the same bits).

The symbol is the trial table's symbol column (``digit`` in a digit dataset, ``symbol`` in
any other); tables and messages name it so.

Every test returns a :class:`TestResult`; where a method cannot give an answer the result
says what was done instead in ``note`` and never carries a silent NaN or a p of 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.contingency_tables import mcnemar
from statsmodels.stats.multitest import multipletests

from crs_study._display import Display, Displayed
from crs_study.analysis.accuracy import floor_p, symbol_column_of
from crs_study.analysis.jsonable import json_text, records
from crs_study.analysis.plan import KNOWN_LEVEL_COLUMNS, PER_SYMBOL_TESTS
from crs_study.dataset.schema import SYMBOL_COLUMNS, symbol_column

#: What pairs two trials besides the symbol shown (and the level, when one varies).
PAIR_KEYS = ("participant_id", "session", "repetition")
#: Participant differences are rounded to this many decimals before any test. Accuracies are
#: ratios k / n, so a difference that is one number in exact arithmetic can come out of the
#: subtraction as several floats (0.7 - 0.4 = 0.29999999999999993, 0.8 - 0.5 =
#: 0.30000000000000004): the Wilcoxon ranks would split a tie. Rounding error is ~1e-16 here,
#: while two different differences of proportions with up to 1000 trials each are at least
#: 1e-12 apart (their denominators are at most 1000^4), so 12 decimals merge the values
#: that are equal, except in the rare case where the exact value lies half-way between two
#: 12-decimal steps (e.g. m / 40960) and its float copies round to different sides.
DIFFERENCE_DECIMALS = 12


def adjusted_p_values(p_values: np.ndarray, alpha: float, correction: str) -> np.ndarray:
    """The p-values adjusted for their number by ``correction`` (a method name of
    ``statsmodels.stats.multitest.multipletests``, or ``none``).

    Holm's (Holm 1979, Scand. J. Statist. 6:65): the i-th smallest of n p-values times
    ``n - i + 1``, each then the largest of those up to it, at most 1. It is computed here
    with the operations of statsmodels' own branch, so to the same bits (the test compares
    them): that branch (statsmodels 0.14 and 0.15) runs a full ``gc.collect()`` on every
    call, 0.08 s in an analysis process and more in one that holds more objects, once for
    every condition compared. Any other method is statsmodels'.
    """
    if correction == "none":
        return p_values.copy()
    if correction != "holm" or not len(p_values):
        with np.errstate(divide="ignore"):     # Sidak's log1p(-p) at p = 1: -inf, exact
            return multipletests(p_values, alpha=alpha, method=correction)[1]
    order = np.argsort(p_values)
    scaled = p_values[order] * np.arange(len(p_values), 0, -1)
    adjusted = np.minimum(np.maximum.accumulate(scaled), 1.0)
    out = np.empty_like(adjusted)
    out[order] = adjusted
    return out


@dataclass(frozen=True)
class TestResult:
    """A comparison of ``condition`` with ``reference`` (estimate: condition - reference,
    or an odds ratio condition/reference for McNemar). In ``results.json`` it is marked
    ``"primary": false`` (the primary comparisons, :class:`~.primary.Comparison`, ``true``)."""

    condition: str
    reference: str
    method: str
    estimate: float | None
    ci95: tuple[float, float] | None
    p_value: float | None
    statistic: float | None = None
    n: int = 0
    effect_size: float | None = None
    effect_size_name: str = ""
    extra: dict = field(default_factory=dict)
    note: str = ""

    def to_dict(self) -> dict:
        return {"condition": self.condition, "reference": self.reference,
                "method": self.method, "estimate": self.estimate,
                "ci95": None if self.ci95 is None else list(self.ci95),
                "p_value": self.p_value, "statistic": self.statistic, "n": self.n,
                "effect_size": self.effect_size, "effect_size_name": self.effect_size_name,
                **self.extra, "note": self.note, "primary": False}


def participant_differences(by_participant: pd.DataFrame, condition: str,
                            reference: str) -> pd.Series:
    """Accuracy(condition) - accuracy(reference) per participant having both conditions,
    rounded to :data:`DIFFERENCE_DECIMALS` so that equal differences are equal floats (ties
    and zeros for the Wilcoxon test)."""
    wide = by_participant.pivot(index="participant_id", columns="condition", values="accuracy")
    if condition not in wide or reference not in wide:
        return pd.Series(dtype=float)
    return (wide[condition] - wide[reference]).dropna().round(DIFFERENCE_DECIMALS) + 0.0


def paired_t(diffs: pd.Series, condition: str, reference: str, alpha: float = 0.05) -> TestResult:
    """Paired t-test of the participant differences, Cohen's d_z."""
    name = "paired t-test on participant accuracies"
    n = len(diffs)
    if n < 2:
        return TestResult(condition, reference, name, float(diffs.mean()) if n else None, None,
                          None, n=n, note=f"not computed: needs 2 or more participants with "
                          f"both conditions, found {n}; see the GLMM and McNemar results")
    spread = float(np.std(diffs.to_numpy(), ddof=1))
    if spread <= 1e-12 * max(1.0, abs(float(diffs.mean()))):  # equal up to rounding
        return TestResult(condition, reference, name, float(diffs.mean()), None, None, n=n,
                          note=f"not computed: every participant's difference equals "
                          f"{diffs.iloc[0]:+.4g} (no spread, t undefined); see the Wilcoxon "
                          "and McNemar results")
    result = stats.ttest_1samp(diffs.to_numpy(), 0.0)
    ci = result.confidence_interval(1 - alpha)
    return TestResult(condition, reference, name, float(diffs.mean()),
                      (float(ci.low), float(ci.high)), floor_p(result.pvalue),
                      float(result.statistic), n, float(diffs.mean()) / spread, "cohen_dz",
                      {"df": n - 1})


def wilcoxon_signed_rank(diffs: pd.Series, condition: str, reference: str,
                         alpha: float = 0.05) -> TestResult:
    """Wilcoxon signed-rank test of the participant differences, rank-biserial r."""
    name = "Wilcoxon signed-rank test on participant accuracies"
    values = diffs.to_numpy()
    nonzero = values[values != 0]
    n = len(nonzero)
    median = float(np.median(values)) if len(values) else None
    if n == 0:
        return TestResult(condition, reference, name, median, None, 1.0 if len(values) else
                          None, n=len(values), note="no non-zero participant difference: the "
                          "test has no information; reported p = 1" if len(values) else
                          "not computed: no participant has both conditions")
    ranks = stats.rankdata(np.abs(nonzero))
    t_plus, t_minus = float(ranks[nonzero > 0].sum()), float(ranks[nonzero < 0].sum())
    r = (t_plus - t_minus) / (t_plus + t_minus)
    result = stats.wilcoxon(nonzero, zero_method="wilcox", alternative="two-sided")
    smallest = 2.0 / 2**n
    notes = []
    if len(values) - n:
        notes.append(f"{len(values) - n} zero difference(s) dropped (Wilcoxon's zero method)")
    if smallest >= alpha:
        notes.append(f"with {n} non-zero difference(s) the smallest attainable two-sided p is "
                     f"{smallest:.4g} >= alpha {alpha:g}: this test cannot reject; rely on the "
                     "GLMM, which uses every trial")
    note = "; ".join(notes)
    return TestResult(condition, reference, name, median, None, floor_p(result.pvalue),
                      float(result.statistic), n, r, "rank_biserial",
                      {"t_plus": t_plus, "t_minus": t_minus,
                       "smallest_attainable_p": smallest}, note)


def mcnemar_midp(b: int, c: int) -> tuple[float, float]:
    """Exact (conditional binomial) and mid-p McNemar p-values for discordant counts b, c.

    Notes
    -----
    ``p_exact = min(1, 2 P(X <= min(b, c)))`` and ``p_mid = 2 P(X <= min(b, c)) - P(X =
    min(b, c))`` with ``X ~ Bin(b + c, 1/2)``; when ``b == c``, ``p_mid = 1 - P(X = b) / 2``
    (Fagerland, Lydersen & Laake 2013 and their supplement "How to calculate the McNemar
    mid-p test", Eqs. 1-2). The exact p is ``statsmodels``' ``mcnemar(exact=True)``.
    """
    n = b + c
    if n == 0:
        return 1.0, 1.0
    exact = float(mcnemar(np.array([[0, b], [c, 0]]), exact=True).pvalue)
    k = min(b, c)
    if b == c:
        mid = 1.0 - 0.5 * stats.binom.pmf(k, n, 0.5)
    else:
        mid = 2.0 * stats.binom.cdf(k, n, 0.5) - stats.binom.pmf(k, n, 0.5)
    return min(1.0, exact), float(min(1.0, mid))


def paired_table(trials: pd.DataFrame, condition: str, reference: str) -> pd.DataFrame:
    """Trials of the two conditions matched on :data:`PAIR_KEYS`, the symbol shown and any
    stimulus level column (columns ``ref``, ``cond``)."""
    answered = trials.loc[trials["correct"].notna()]
    # A protocol that varies a stimulus level repeats (symbol, repetition) at every level: the
    # level is part of what makes two trials a pair, or pairs would be dropped as duplicates.
    keys = [*PAIR_KEYS[:2], symbol_column_of(trials), *PAIR_KEYS[2:]] + \
        [c for c in KNOWN_LEVEL_COLUMNS if c in answered.columns]
    left = answered.loc[answered["condition"] == reference, [*keys, "correct"]]
    right = answered.loc[answered["condition"] == condition, [*keys, "correct"]]
    left = left.drop_duplicates(keys)
    right = right.drop_duplicates(keys)
    return left.merge(right, on=keys, suffixes=("_ref", "_cond")).rename(
        columns={"correct_ref": "ref", "correct_cond": "cond"})


def mcnemar_test(pairs: pd.DataFrame, condition: str, reference: str,
                 alpha: float = 0.05) -> TestResult:
    """Exact McNemar with mid-p on matched trials; conditional odds ratio c / b."""
    symbol = symbol_column(pairs.columns) or SYMBOL_COLUMNS[0]
    name = ("McNemar mid-p test (p_value the mid-p; p_exact the exact conditional test) on "
            f"trials paired by participant, session, {symbol}, repetition and level")
    ref, cond = pairs["ref"].to_numpy(), pairs["cond"].to_numpy()
    a = int(((ref == 1) & (cond == 1)).sum())
    b = int(((ref == 1) & (cond == 0)).sum())   # reference right, condition wrong
    c = int(((ref == 0) & (cond == 1)).sum())   # reference wrong, condition right
    d = int(((ref == 0) & (cond == 0)).sum())
    table = {"both_correct": a, "reference_only": b, "condition_only": c, "both_wrong": d}
    if len(pairs) == 0:
        return TestResult(condition, reference, name, None, None, None, n=0,
                          extra={"table": table}, note="not computed: no trial of one condition "
                          f"matches a trial of the other on participant, {symbol} and "
                          "repetition")
    p_exact, p_mid = mcnemar_midp(b, c)
    extra = {"table": table, "p_exact": floor_p(p_exact), "p_mid": floor_p(p_mid)}
    if b + c == 0:
        return TestResult(condition, reference, name, None, None, 1.0, float(b), len(pairs),
                          extra=extra, note="no discordant pairs: McNemar's test has no "
                          "information; reported p = 1 and no odds ratio")
    note = ""
    lo_p, hi_p = _clopper_pearson(c, b + c, alpha)
    if b == 0 or c == 0:
        odds = (c + 0.5) / (b + 0.5)
        note = (f"{'b' if b == 0 else 'c'} = 0 discordant pairs: the odds ratio c/b is "
                f"{'infinite' if b == 0 else 'zero'}; reported (c + 0.5)/(b + 0.5) = "
                f"{odds:.4g} with the exact interval"
                + (", whose upper limit is infinite (null in results.json)" if b == 0 else ""))
    else:
        odds = c / b
    ci = (_odds(lo_p), _odds(hi_p))
    return TestResult(condition, reference, name, float(odds), ci, floor_p(p_mid), float(b),
                      len(pairs), float(odds), "conditional_odds_ratio", extra, note)


def _clopper_pearson(k: int, n: int, alpha: float) -> tuple[float, float]:
    interval = stats.binomtest(k, n).proportion_ci(1 - alpha, method="exact")
    return float(interval.low), float(interval.high)


def _odds(p: float) -> float:
    return float(p / (1.0 - p)) if p < 1.0 else float("inf")


def per_symbol(trials: pd.DataFrame, condition: str, reference: str, correction: str = "holm",
               alpha: float = 0.05) -> tuple[pd.DataFrame, list[str]]:
    """McNemar mid-p per symbol, adjusted across symbols; columns documented in the return.

    Returns a table ``<symbol column>, n_pairs, accuracy_reference, accuracy_condition,
    difference, discordant_b, discordant_c, p_value, p_adjusted, reject`` (the first column
    named as the trials name the symbol: ``digit``, ``symbol``) and notes.
    """
    rows, notes = [], []
    column = symbol_column_of(trials)
    pairs = paired_table(trials, condition, reference)
    for symbol, group in pairs.groupby(column, sort=True):
        b = int(((group["ref"] == 1) & (group["cond"] == 0)).sum())
        c = int(((group["ref"] == 0) & (group["cond"] == 1)).sum())
        rows.append({column: symbol.item() if isinstance(symbol, np.generic) else symbol,
                     "n_pairs": len(group),
                     "accuracy_reference": float(group["ref"].mean()),
                     "accuracy_condition": float(group["cond"].mean()),
                     "difference": float(group["cond"].mean() - group["ref"].mean()),
                     "discordant_b": b, "discordant_c": c,
                     "p_value": floor_p(mcnemar_midp(b, c)[1])})
    table = pd.DataFrame(rows, columns=[column, "n_pairs", "accuracy_reference",
                                        "accuracy_condition", "difference", "discordant_b",
                                        "discordant_c", "p_value"])
    if table.empty:
        notes.append(f"per-{column} comparisons of {condition!r}: no matched trials")
        table["p_adjusted"], table["reject"] = [], []
        return table, notes
    table["p_adjusted"] = adjusted_p_values(table["p_value"].to_numpy(float), alpha,
                                            correction)
    table["p_adjusted"] = table["p_adjusted"].map(floor_p)
    table["reject"] = table["p_adjusted"] < alpha
    no_info = table.loc[table["discordant_b"] + table["discordant_c"] == 0, column].tolist()
    if no_info:
        notes.append(f"per-{column} comparisons of {condition!r}: {column}(s) {no_info} have "
                     "no discordant pairs; their p = 1")
    return table, notes


@dataclass(frozen=True, repr=False)
class SecondaryResult(Displayed):
    """The tests of every condition against the reference; ``per_symbol``: condition -> the
    :func:`per_symbol` table; ``symbol_column``: the trials' column of the symbol shown
    (``digit``, ``symbol``), which names the tables' first column and their key in
    ``results.json``."""

    tests: tuple[TestResult, ...]
    per_symbol: dict[str, pd.DataFrame]
    warnings: tuple[str, ...] = ()
    symbol_column: str = SYMBOL_COLUMNS[0]

    def _display(self) -> Display:
        rows = tuple((f"{t.method} ({t.condition} vs {t.reference})",
                      ("n/a" if t.estimate is None else f"{t.estimate:.3g}") + ", "
                      + ("p n/a" if t.p_value is None else f"p = {t.p_value:.3g}"))
                     for t in self.tests)
        return Display(f"SecondaryResult, {len(self.tests)} tests", rows, self.warnings,
                       ".to_frame(), .per_symbol")

    def to_frame(self) -> pd.DataFrame:
        """One row per test (the fields of :class:`TestResult`)."""
        return pd.DataFrame([t.to_dict() for t in self.tests])

    def to_dict(self) -> dict:
        """``comparisons`` (the secondary ones of ``results.json``) and
        ``per_<symbol column>`` (per condition, the rows of its per-symbol table;
        ``per_digit`` for digit data, as before stimulus sets)."""
        return {"comparisons": [t.to_dict() for t in self.tests],
                f"per_{self.symbol_column}": {c: records(t)
                                              for c, t in self.per_symbol.items()}}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def secondary_tests(trials: pd.DataFrame, by_participant: pd.DataFrame, conditions: list[str],
                    reference: str, tests: tuple[str, ...], correction: str = "holm",
                    alpha: float = 0.05) -> SecondaryResult:
    """Run the plan's secondary tests for every condition against ``reference``."""
    results, symbol_tables, warnings = [], {}, []
    for condition in conditions:
        if condition == reference:
            continue
        diffs = participant_differences(by_participant, condition, reference)
        if "paired_t" in tests:
            results.append(paired_t(diffs, condition, reference, alpha))
        if "wilcoxon" in tests:
            results.append(wilcoxon_signed_rank(diffs, condition, reference, alpha))
        if "mcnemar" in tests:
            results.append(mcnemar_test(paired_table(trials, condition, reference), condition,
                                        reference, alpha))
        if any(t in tests for t in PER_SYMBOL_TESTS):
            table, notes = per_symbol(trials, condition, reference, correction, alpha)
            symbol_tables[condition] = table
            warnings += notes
    for result in results:
        if result.note:
            warnings.append(f"{result.method} ({result.condition} vs {result.reference}): "
                            f"{result.note}")
    return SecondaryResult(tuple(results), symbol_tables, tuple(warnings),
                           symbol_column_of(trials))
