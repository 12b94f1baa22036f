"""Speed against accuracy: response times, conditional accuracy and combined scores.

* ``rt_summary``: per condition and outcome (``all``, ``correct``, ``error``): ``n``,
  ``median``, ``q1``, ``q3`` (IQR = q3 - q1), ``mean`` of the response time (s).
* ``caf`` (conditional accuracy function): each participant's trials of a condition are cut
  into ``bins`` response-time quantile bins (by rank, equal counts), then pooled per
  condition and bin: ``n_trials``, ``n_correct``, ``accuracy`` with Wilson ``ci_low``,
  ``ci_high``, and ``mean_rt`` (s).
* ``efficiency`` per participant and condition, then ``efficiency_summary`` per condition
  of

  - inverse efficiency ``IES = mean correct RT / PC`` (Townsend & Ashby 1983; s),
  - rate-correct score ``RCS = n correct / sum of all RTs`` (Woltz & Was 2006, Eq. 1;
    correct responses per second),
  - balanced integration score ``BIS = z(PC) - z(mean correct RT)`` with both z-scores taken
    across every participant x condition cell (Liesefeld & Janczyk 2019, Behav. Res.
    Methods 51:40, Eq. 1; unitless, higher is better).

Summary estimates and intervals respect each measure's range (column ``<measure>_method``):

- ``accuracy``: the pooled proportion correct with its Wilson interval (within [0, 1]);
- ``mean_correct_rt``, ``ies``, ``rcs``: positive and right-skewed, so the geometric mean
  across participants with the t interval of the mean log, exponentiated (never negative;
  exact for log-normal scores). Response times counted from stimulus offset can be 0 or
  negative: then the arithmetic mean with a t interval, as the method says;
- ``bis``: unbounded, the mean with a t interval (``scipy.stats.t``).

With one participant, or no spread, an interval collapses to the estimate (said in the
warnings).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats

from crs_study._display import Display, Displayed, percent
from crs_study.analysis.accuracy import wilson_interval
from crs_study.analysis.jsonable import json_text, records

MEASURES = ("accuracy", "mean_correct_rt", "ies", "rcs", "bis")
#: Measures summarised on the log scale when every participant's value is positive.
POSITIVE_MEASURES = ("mean_correct_rt", "ies", "rcs")


@dataclass(frozen=True, repr=False)
class SpeedAccuracyResult(Displayed):
    """Tables described in the module docstring, the response-time column used, warnings."""

    rt_summary: pd.DataFrame
    caf: pd.DataFrame
    efficiency: pd.DataFrame
    efficiency_summary: pd.DataFrame
    conditions: tuple[str, ...]
    rt_column: str
    alpha: float = 0.05
    warnings: tuple[str, ...] = field(default=())

    def _display(self) -> Display:
        rows = []
        for condition in self.conditions:
            row = self.efficiency_summary.loc[self.efficiency_summary["condition"] == condition]
            if row.empty:
                continue
            rt, accuracy = row.iloc[0]["mean_correct_rt"], row.iloc[0]["accuracy"]
            rt_text = "n/a" if rt is None or rt != rt else f"{float(rt):.3g} s"
            rows.append((condition, f"correct {self.rt_column.replace('_', ' ')} {rt_text}, "
                                    f"accuracy {percent(accuracy)}"))
        return Display("SpeedAccuracyResult", tuple(rows), self.warnings,
                       ".to_frame(), .rt_summary, .caf, .efficiency")

    def to_frame(self) -> pd.DataFrame:
        """The efficiency summary: one row per condition and measure."""
        return self.efficiency_summary.copy()

    def to_dict(self) -> dict:
        """``results.json``'s ``speed_accuracy``: the response-time column, the rows of the
        response-time summary, the conditional accuracy function and the efficiency
        summary."""
        return {"rt_column": self.rt_column, "rt_summary": records(self.rt_summary),
                "caf": records(self.caf), "efficiency": records(self.efficiency_summary)}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def rt_summary(trials: pd.DataFrame, rt: str, conditions: list[str]) -> pd.DataFrame:
    rows = []
    for condition in conditions:
        subset = trials.loc[trials["condition"] == condition]
        for outcome, mask in (("all", subset["correct"].notna()),
                              ("correct", subset["correct"] == 1),
                              ("error", subset["correct"] == 0)):
            values = subset.loc[mask, rt].dropna().to_numpy()
            q1, median, q3 = (np.quantile(values, [0.25, 0.5, 0.75]) if len(values)
                              else (None, None, None))
            rows.append({"condition": condition, "outcome": outcome, "n": len(values),
                         "median": _num(median), "q1": _num(q1), "q3": _num(q3),
                         "mean": _num(values.mean()) if len(values) else None})
    return pd.DataFrame(rows)


def conditional_accuracy(trials: pd.DataFrame, rt: str, conditions: list[str], bins: int = 5,
                         alpha: float = 0.05) -> pd.DataFrame:
    """Conditional accuracy function (see module docstring)."""
    data = trials.loc[trials["correct"].notna() & trials[rt].notna(),
                      ["participant_id", "condition", "correct", rt]].copy()
    data = data.loc[data["condition"].isin(conditions)]
    columns = ["condition", "bin", "n_trials", "n_correct", "accuracy", "ci_low", "ci_high",
               "mean_rt"]
    if data.empty:
        return pd.DataFrame(columns=columns)
    grouped = data.groupby(["participant_id", "condition"], sort=False)[rt]
    rank = grouped.rank(method="first")
    count = grouped.transform("size")
    data["bin"] = ((rank - 1) * bins // count).astype(int)
    table = data.groupby(["condition", "bin"], sort=False).agg(
        n_trials=("correct", "size"), n_correct=("correct", "sum"),
        mean_rt=(rt, "mean")).reset_index()
    table["n_correct"] = table["n_correct"].round().astype(int)
    table["accuracy"] = table["n_correct"] / table["n_trials"]
    table["ci_low"], table["ci_high"] = wilson_interval(table["n_correct"].to_numpy(),
                                                        table["n_trials"].to_numpy(), alpha)
    order = {c: i for i, c in enumerate(conditions)}
    table = table.sort_values(["condition", "bin"], key=lambda s: s.map(order)
                              if s.name == "condition" else s)
    return table[columns].reset_index(drop=True)


def efficiency_scores(trials: pd.DataFrame, rt: str, conditions: list[str]
                      ) -> tuple[pd.DataFrame, list[str]]:
    """IES, RCS and BIS per participant and condition (see module docstring)."""
    data = trials.loc[trials["correct"].notna() & trials[rt].notna()
                      & trials["condition"].isin(conditions)]
    warnings = []
    rows = []
    for (participant, condition), group in data.groupby(["participant_id", "condition"],
                                                        sort=True):
        correct = group["correct"].to_numpy()
        times = group[rt].to_numpy()
        n_correct = int(correct.sum())
        pc = n_correct / len(correct)
        mean_correct_rt = float(times[correct == 1].mean()) if n_correct else None
        rows.append({"participant_id": participant, "condition": condition,
                     "n_trials": len(correct), "n_correct": n_correct, "accuracy": pc,
                     "mean_correct_rt": mean_correct_rt,
                     "ies": mean_correct_rt / pc if n_correct else None,
                     "rcs": n_correct / float(times.sum()) if times.sum() > 0 else None})
    table = pd.DataFrame(rows, columns=["participant_id", "condition", "n_trials", "n_correct",
                                        "accuracy", "mean_correct_rt", "ies", "rcs"])
    none_correct = table.loc[table["ies"].isna(), ["participant_id", "condition"]]
    if len(none_correct):
        warnings.append(f"{len(none_correct)} participant x condition cell(s) have no correct "
                        "response: their inverse efficiency and BIS are undefined and left out "
                        "of the condition means")
    rt_values = table["mean_correct_rt"].astype(float)
    table["bis"] = _z(table["accuracy"].astype(float)) - _z(rt_values)
    table.loc[rt_values.isna(), "bis"] = None
    return table, warnings


def _z(values: pd.Series) -> pd.Series:
    """Standard scores across all cells (population sd, as Liesefeld & Janczyk 2019)."""
    spread = values.std(ddof=0)
    if not np.isfinite(spread) or spread == 0:
        return values * 0.0
    return (values - values.mean()) / spread


def summarise_efficiency(table: pd.DataFrame, conditions: list[str],
                         alpha: float = 0.05) -> pd.DataFrame:
    """Per condition and measure: estimate, interval and method (see module docstring)."""
    rows = []
    for condition in conditions:
        subset = table.loc[table["condition"] == condition]
        row: dict[str, object] = {"condition": condition, "n_participants": len(subset)}
        n_trials, n_correct = int(subset["n_trials"].sum()), int(subset["n_correct"].sum())
        if n_trials:
            low, high = wilson_interval(n_correct, n_trials, alpha)
            row["accuracy"] = n_correct / n_trials
            row["accuracy_ci_low"], row["accuracy_ci_high"] = float(low), float(high)
        else:
            row["accuracy"] = row["accuracy_ci_low"] = row["accuracy_ci_high"] = None
        row["accuracy_method"] = "pooled trials, Wilson interval"
        for measure in MEASURES[1:]:
            values = subset[measure].dropna().astype(float).to_numpy()
            positive = measure in POSITIVE_MEASURES and len(values) and (values > 0).all()
            estimate, low, high = _t_summary(np.log(values) if positive else values, alpha)
            if positive:
                estimate, low, high = (None if v is None else float(np.exp(v))
                                       for v in (estimate, low, high))
            row[measure], row[f"{measure}_ci_low"], row[f"{measure}_ci_high"] = \
                estimate, low, high
            row[f"{measure}_method"] = ("geometric mean, t interval on the log scale"
                                        if positive else "mean, t interval")
        rows.append(row)
    return pd.DataFrame(rows)


def _t_summary(values: np.ndarray, alpha: float
               ) -> tuple[float | None, float | None, float | None]:
    """Mean and t interval (``scipy.stats.t.interval``); a point without spread or n < 2."""
    if not len(values):
        return None, None, None
    mean = float(values.mean())
    if len(values) < 2 or values.std(ddof=1) == 0:
        return mean, mean, mean
    low, high = stats.t.interval(1 - alpha, len(values) - 1, loc=mean,
                                 scale=stats.sem(values))
    return mean, float(low), float(high)


def analyse_speed_accuracy(trials: pd.DataFrame, conditions: list[str],
                           rt: str = "response_time", bins: int = 5,
                           alpha: float = 0.05) -> SpeedAccuracyResult:
    """Response-time summaries, conditional accuracy functions and efficiency scores."""
    warnings = []
    if trials[rt].notna().sum() == 0:
        warnings.append(f"no response times in column {rt!r}: speed-accuracy analysis empty")
    efficiency, notes = efficiency_scores(trials, rt, conditions)
    warnings += notes
    single = efficiency.groupby("condition")["participant_id"].nunique()
    if len(single) and single.max() < 2:
        warnings.append("one participant only: condition means of the speed-accuracy scores "
                        "have no interval (shown as a point)")
    return SpeedAccuracyResult(
        rt_summary(trials, rt, conditions), conditional_accuracy(trials, rt, conditions, bins,
                                                                 alpha),
        efficiency, summarise_efficiency(efficiency, conditions, alpha), tuple(conditions), rt,
        alpha, tuple(warnings))


def _num(value) -> float | None:
    return None if value is None else float(value)
