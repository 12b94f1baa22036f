"""Accuracy per condition, participant and symbol, with Wilson intervals and tests against chance.

Tables returned here have the columns ``<group keys>, n_trials, n_correct, accuracy, ci_low,
ci_high, p_vs_chance``: ``accuracy = n_correct / n_trials``; ``ci_low, ci_high`` the Wilson
score interval (Wilson 1927; recommended by Brown, Cai & DasGupta 2001, Statist. Sci. 16:101)
at level ``1 - alpha``; ``p_vs_chance`` the exact two-sided binomial test of ``accuracy ==
chance`` (``scipy.stats.binomtest``), never reported as 0 (see :func:`floor_p`).

The Wilson interval of a condition treats its trials as independent: it is the interval of the
pooled (trial-level) proportion, narrower than the uncertainty about the population of
participants when participants differ. ``between_participants`` gives that second view: the
mean of the participants' accuracies with the t interval across participants
(``scipy.stats.t``; clipped to [0, 1] when it reaches past, and then said so).
:func:`headline_accuracy` picks, per condition, the figure the headline and the accuracy
chart show: that participant-level interval, which accounts for the differences between
participants (with 3 participants the pooled Wilson interval was [42.0, 58.0] where the
participant-level one is [22.8, 76.8]: the pooled one claimed a precision the study lacks).

The symbol shown is in the trial table's symbol column (:func:`symbol_column_of`: ``digit``
in digit datasets, ``symbol`` in those of every other stimulus set).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.proportion import proportion_confint

from crs_study._display import Display, Displayed, percent
from crs_study.analysis.jsonable import json_text, records
from crs_study.dataset.schema import SYMBOL_COLUMNS, symbol_column
from crs_study.errors import AnalysisError

#: The smallest p-value reported: below it, a p is shown as this bound with a warning.
P_FLOOR = 1e-300
TABLE_COLUMNS = ("n_trials", "n_correct", "accuracy", "ci_low", "ci_high", "p_vs_chance")


def floor_p(p: float) -> float:
    """Return ``p`` or :data:`P_FLOOR` when it underflows below it (a p is never 0)."""
    return float(max(p, P_FLOOR))


def wilson_interval(n_correct: int | np.ndarray, n_trials: int | np.ndarray,
                    alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval, ``statsmodels proportion_confint(method="wilson")``.

    Notes
    -----
    ``(p + z^2/2n +- z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)`` with ``z = Phi^-1(1-alpha/2)``.
    The bounds are exactly 0 at ``k = 0`` and 1 at ``k = n``, as the formula gives (rounding
    otherwise leaves 1 - 1e-16).
    """
    low, high = proportion_confint(n_correct, n_trials, alpha=alpha, method="wilson")
    k, n = np.asarray(n_correct), np.asarray(n_trials)
    low = np.where(k == 0, 0.0, np.asarray(low, dtype=float))
    high = np.where(k == n, 1.0, np.asarray(high, dtype=float))
    return low, high


def symbol_column_of(trials: pd.DataFrame) -> str:
    """The column of ``trials`` holding the symbol shown (``digit`` or ``symbol``,
    :func:`crs_study.dataset.schema.symbol_column`)."""
    column = symbol_column(trials.columns)
    if column is None:
        raise AnalysisError(f"the trials name no symbol shown: expected a column among "
                            f"{list(SYMBOL_COLUMNS)}, got {list(trials.columns)}")
    return column


def chance_level(trials: pd.DataFrame, chance: float = 0.0) -> float:
    """Chance accuracy: ``chance`` when given, else 1 / number of distinct symbols shown."""
    if chance > 0:
        return chance
    column = symbol_column_of(trials)
    n_symbols = trials[column].nunique()
    if n_symbols < 2:
        raise AnalysisError(f"chance level undefined: the trials show {n_symbols} {column}(s); "
                            "set plan.chance")
    return 1.0 / n_symbols


def accuracy_table(trials: pd.DataFrame, by: list[str], chance: float,
                   alpha: float = 0.05) -> pd.DataFrame:
    """Accuracy of the answered trials grouped ``by`` the given columns (see module doc)."""
    answered = trials.loc[trials["correct"].notna()]
    if answered.empty:
        return pd.DataFrame(columns=[*by, *TABLE_COLUMNS])
    grouped = answered.groupby(by, sort=False, observed=True)["correct"]
    table = pd.DataFrame({"n_trials": grouped.size(), "n_correct": grouped.sum()}).reset_index()
    table["n_correct"] = table["n_correct"].round().astype(int)
    table["n_trials"] = table["n_trials"].astype(int)
    table["accuracy"] = table["n_correct"] / table["n_trials"]
    table["ci_low"], table["ci_high"] = wilson_interval(table["n_correct"].to_numpy(),
                                                        table["n_trials"].to_numpy(), alpha)
    table["p_vs_chance"] = [
        floor_p(stats.binomtest(int(k), int(n), chance).pvalue)
        for k, n in zip(table["n_correct"], table["n_trials"], strict=True)
    ]
    return table


@dataclass(frozen=True, repr=False)
class AccuracyResult(Displayed):
    """Accuracy tables and the inputs that made them.

    ``by_condition``: one row per condition (in ``conditions`` order); ``by_participant``:
    participant_id x condition; ``by_symbol``: symbol x condition (its first column named as
    the trials name the symbol: ``digit``, ``symbol``); ``chance``: the chance level;
    ``alpha``: 1 - interval level; ``warnings``: what was noted along the way.
    """

    by_condition: pd.DataFrame
    by_participant: pd.DataFrame
    by_symbol: pd.DataFrame
    conditions: tuple[str, ...]
    chance: float
    alpha: float
    warnings: tuple[str, ...] = field(default=())
    between_participants: pd.DataFrame = field(default_factory=pd.DataFrame)

    def _display(self) -> Display:
        rows = tuple((r["condition"], f"{percent(r['accuracy'])} [{percent(r['ci_low'])}, "
                      f"{percent(r['ci_high'])}] ({r['method']})")
                     for _, r in headline_accuracy(self).iterrows())
        return Display(f"AccuracyResult, {len(self.conditions)} conditions",
                       (*rows, ("chance", percent(self.chance))), self.warnings,
                       ".to_frame(), .by_participant, .by_symbol")

    def to_frame(self) -> pd.DataFrame:
        """The accuracy table: one row per condition (``by_condition``)."""
        return self.by_condition.copy()

    def to_dict(self) -> dict:
        """The accuracy sections of ``results.json``: ``conditions`` (per condition the
        pooled counts, accuracy and Wilson interval, ``p_vs_chance``, the participants, the
        between-participant mean and interval, and what the headline shows),
        ``accuracy_by_participant`` and ``accuracy_by_<symbol column>`` (the tables' rows:
        ``accuracy_by_digit`` for digit data, as before stimulus sets)."""
        between = {r["condition"]: {"mean": r["mean"], "ci95": [r["ci_low"], r["ci_high"]],
                                    "n_participants": int(r["n_participants"]),
                                    "method": r["method"]}
                   for r in records(self.between_participants)}
        shown = {r["condition"]: {"accuracy": r["accuracy"], "ci95": [r["ci_low"], r["ci_high"]],
                                  "method": r["method"]}
                 for r in records(headline_accuracy(self))}
        by_participant = self.by_participant
        conditions = {
            row["condition"]: {
                "n_trials": int(row["n_trials"]), "n_correct": int(row["n_correct"]),
                "accuracy": float(row["accuracy"]),
                "ci95": [float(row["ci_low"]), float(row["ci_high"])],
                "ci95_method": POOLED_CI_METHOD,
                "p_vs_chance": float(row["p_vs_chance"]),
                "n_participants": int((by_participant["condition"] == row["condition"]).sum()),
                "between_participants": between.get(row["condition"]),
                "headline": shown.get(row["condition"]),
            } for _, row in self.by_condition.iterrows()}
        return {"conditions": conditions, "accuracy_by_participant": records(by_participant),
                f"accuracy_by_{self.by_symbol.columns[0]}": records(self.by_symbol)}

    def to_json(self) -> str:
        return json_text(self.to_dict())

    def condition_row(self, condition: str) -> pd.Series:
        rows = self.by_condition.loc[self.by_condition["condition"] == condition]
        if rows.empty:
            raise AnalysisError(f"no accuracy for condition {condition!r}; "
                                f"have {list(self.by_condition['condition'])}")
        return rows.iloc[0]


def analyse_accuracy(trials: pd.DataFrame, conditions: tuple[str, ...], chance: float,
                     alpha: float = 0.05) -> AccuracyResult:
    """Accuracy per condition, per participant and condition, per symbol and condition."""
    warnings = []
    order = {c: i for i, c in enumerate(conditions)}
    by_condition = accuracy_table(trials, ["condition"], chance, alpha)
    by_condition = by_condition.sort_values("condition", key=lambda s: s.map(order))
    by_participant = accuracy_table(trials, ["participant_id", "condition"], chance, alpha)
    column = symbol_column_of(trials)
    by_symbol = accuracy_table(trials, [column, "condition"], chance, alpha)
    by_participant = by_participant.sort_values(
        ["participant_id", "condition"], key=lambda s: s.map(order) if s.name == "condition"
        else s).reset_index(drop=True)
    by_symbol = by_symbol.sort_values(
        [column, "condition"], key=lambda s: s.map(order) if s.name == "condition"
        else s).reset_index(drop=True)
    return AccuracyResult(by_condition.reset_index(drop=True), by_participant, by_symbol,
                          conditions, chance, alpha, tuple(warnings),
                          between_participant_table(by_participant, conditions, alpha))


def between_participant_table(by_participant: pd.DataFrame, conditions: tuple[str, ...],
                              alpha: float = 0.05) -> pd.DataFrame:
    """Mean participant accuracy per condition with the t interval across participants."""
    rows = []
    for condition in conditions:
        values = by_participant.loc[by_participant["condition"] == condition,
                                    "accuracy"].to_numpy(dtype=float)
        row = {"condition": condition, "n_participants": len(values),
               "mean": float(values.mean()) if len(values) else None,
               "ci_low": None, "ci_high": None,
               "method": "t interval on participant accuracies"}
        if len(values) < 2:
            row["method"] = f"no interval: {len(values)} participant(s)"
        elif values.std(ddof=1) == 0:
            row["ci_low"] = row["ci_high"] = row["mean"]
            row["method"] += " (no spread: every participant equal)"
        else:
            low, high = stats.t.interval(1 - alpha, len(values) - 1, loc=values.mean(),
                                         scale=stats.sem(values))
            row["ci_low"], row["ci_high"] = max(float(low), 0.0), min(float(high), 1.0)
            if low < 0 or high > 1:
                row["method"] += ", clipped to [0, 1]"
        rows.append(row)
    return pd.DataFrame(rows, columns=["condition", "n_participants", "mean", "ci_low",
                                       "ci_high", "method"])


#: What the ``ci95`` of a condition's accuracy is (results.json ``conditions.<c>.ci95_method``).
POOLED_CI_METHOD = ("Wilson score interval of the pooled trials (trial level: ignores "
                    "differences between participants; see between_participants)")
#: What the headline and the accuracy chart show for a condition (participant level).
PARTICIPANT_LEVEL = "mean of participant accuracies, t interval across participants"


def headline_accuracy(result: AccuracyResult) -> pd.DataFrame:
    """Per condition: ``condition, accuracy, ci_low, ci_high, method`` for the headline.

    The mean of the participants' accuracies with the t interval across participants
    (:func:`between_participant_table`): it accounts for the differences between
    participants, which the pooled Wilson interval ignores. Where that interval is not
    defined (one participant) or has no width (every participant alike, a chance event that
    would state a precision the trials do not have), the pooled Wilson interval of the
    condition's trials is shown instead, and ``method`` says so.
    """
    rows = []
    between = result.between_participants.set_index("condition")
    for _, pooled in result.by_condition.iterrows():
        condition = pooled["condition"]
        row = between.loc[condition] if condition in between.index else None
        usable = (row is not None and row["ci_low"] is not None
                  and not pd.isna(row["ci_low"]) and row["ci_high"] > row["ci_low"])
        if usable:
            rows.append({"condition": condition, "accuracy": float(row["mean"]),
                         "ci_low": float(row["ci_low"]), "ci_high": float(row["ci_high"]),
                         "method": PARTICIPANT_LEVEL})
            continue
        why = ("one participant" if row is None or row["n_participants"] < 2
               else "every participant alike")
        rows.append({"condition": condition, "accuracy": float(pooled["accuracy"]),
                     "ci_low": float(pooled["ci_low"]), "ci_high": float(pooled["ci_high"]),
                     "method": f"Wilson interval of the pooled trials; {why}, so no "
                               "participant-level interval"})
    return pd.DataFrame(rows, columns=["condition", "accuracy", "ci_low", "ci_high", "method"])
