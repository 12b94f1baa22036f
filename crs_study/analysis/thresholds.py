"""Thresholds of adaptive sessions: per participant and condition, and their paired comparison.

Sessions of a protocol with ``[adaptive]`` record, on each test trial, the level shown and the
state of the block's procedure after the response (``adaptive_estimate``, its 95 % interval,
``adaptive_reversal``; :data:`crs_study.dataset.schema.ADAPTIVE_COLUMNS`). Every threshold is
the level at which the participant identifies digits at the protocol's target rate ``r``
(a fixed staircase rule implies it: Levitt 1971), read from the stored dataset alone (the
protocol text each sidecar keeps says which procedure, scale and target):

- **procedure**: the track's last state: QUEST+'s posterior mean with its 2.5-97.5 %
  posterior interval (:mod:`crs_study.adaptive.quest_plus`), or the staircase's mean of the
  last reversals on its scale with a Student t interval (:mod:`crs_study.adaptive.staircase`);
- **fit**: a psychometric function fitted to all the participant's test trials in the
  condition (:func:`crs_study.analysis.psychometric.fit_counts`: logistic in ``u``, the
  level on the procedure's scale (log10 of it on a log scale), guess rate one over the
  digits, lapse rate in ``[0, lapse_max]``), its threshold where
  ``psi(u) = r``, i.e. ``F = (r - gamma) / (1 - gamma - lambda)``, with a seeded percentile
  bootstrap interval (counts at each level redrawn from their proportions). A flat fit (no
  effect of the level, likelihood-ratio p >= alpha) has no threshold.

The comparison of each condition with the reference pairs participants: the difference of
their thresholds on the scale (log10 ratio on a log scale, reported as a ratio), its mean
with a t interval and the paired t test (``scipy.stats.ttest_rel``), and the Wilcoxon
signed-rank test (``scipy.stats.wilcoxon``) beside it.
"""

from __future__ import annotations

import re
import tomllib
import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import special, stats

from crs_study._display import Display, Displayed
from crs_study.analysis.jsonable import json_text
from crs_study.analysis.psychometric import fit_counts, level_effect_pvalue

ADAPTIVE_MARKER = "adaptive_estimate"


@dataclass(frozen=True)
class AdaptiveDesign:
    """What the sessions' protocol says of its procedure (its ``[adaptive]`` table)."""

    procedure: str
    level_column: str
    scale: str
    target_rate: float
    easier: int  # +1: a larger level is easier (digit height); -1: a smaller (speed)

    def to_axis(self, levels: np.ndarray) -> np.ndarray:
        levels = np.asarray(levels, float)
        return np.log10(levels) if self.scale == "log" else levels

    def from_axis(self, u: np.ndarray | float) -> np.ndarray | float:
        return 10.0 ** np.asarray(u, float) if self.scale == "log" else np.asarray(u, float)


def rule_target(rule: str | None) -> float | None:
    """The rate a fixed ``1-up-N-down`` rule converges to, ``0.5^(1/N)`` (Levitt 1971,
    Table I); None for another rule (its target rate is in the protocol)."""
    match = re.fullmatch(r"1-up-(\d+)-down", rule or "")
    return 0.5 ** (1.0 / int(match.group(1))) if match else None


def design_from_protocol(text: str) -> AdaptiveDesign | None:
    """The procedure of a protocol's text (None without ``[adaptive]``)."""
    table = tomllib.loads(text).get("adaptive")
    if not table:
        return None
    stair = table.get("staircase") or {}
    rate = rule_target(stair.get("rule")) or table.get("target_rate")
    parameter = table["parameter"]
    # the size is spelled by the stimulus set: digit_height_pitch, symbol_height_pitch
    column = parameter.removesuffix("_pitch") if parameter.endswith("_height_pitch") \
        else "stroke_speed"
    return AdaptiveDesign(table["procedure"], column, table["scale"], float(rate),
                          1 if parameter.endswith("_height_pitch") else -1)


@dataclass(frozen=True)
class ThresholdComparison:
    """A condition's thresholds against the reference's, paired by participant."""

    method: str  # "procedure" or "fit"
    condition: str
    reference: str
    n_pairs: int
    mean_difference: float  # on the scale (log10 units on a log scale)
    ci95: tuple[float, float]
    ratio: float | None  # 10 ** mean_difference on a log scale
    ratio_ci95: tuple[float, float] | None
    t: float
    pvalue: float
    wilcoxon_pvalue: float | None

    def to_dict(self) -> dict:
        return {"method": self.method, "condition": self.condition,
                "reference": self.reference, "n_pairs": self.n_pairs,
                "mean_difference": self.mean_difference, "ci95": list(self.ci95),
                "ratio": self.ratio,
                "ratio_ci95": None if self.ratio_ci95 is None else list(self.ratio_ci95),
                "t": self.t, "df": self.n_pairs - 1, "pvalue": self.pvalue,
                "wilcoxon_pvalue": self.wilcoxon_pvalue}

    def sentence(self, column: str) -> str:
        """One line for the report: by how much, with its interval, and the test."""
        if self.ratio is not None:
            size = (f"{self.ratio:.3g} times the {self.reference} threshold (95 % CI "
                    f"{self.ratio_ci95[0]:.3g} to {self.ratio_ci95[1]:.3g})")
        else:
            size = (f"{self.mean_difference:+.3g} {column} from the {self.reference} "
                    f"threshold (95 % CI {self.ci95[0]:+.3g} to {self.ci95[1]:+.3g})")
        return (f"{self.condition} threshold ({self.method}) is {size}; paired "
                f"t({self.n_pairs - 1}) = {self.t:.3g}, p = {self.pvalue:.3g}, "
                f"{self.n_pairs} participants")


@dataclass(frozen=True, repr=False)
class ThresholdResult(Displayed):
    """Per-participant thresholds (``thresholds``), the tracks they came from (``tracks``:
    participant, condition, trial within the track, level, correct, reversal) and the paired
    comparisons. ``skipped`` with a ``note`` when no session is adaptive."""

    skipped: bool
    note: str = ""
    design: AdaptiveDesign | None = None
    thresholds: pd.DataFrame = field(default_factory=pd.DataFrame)
    tracks: pd.DataFrame = field(default_factory=pd.DataFrame)
    comparisons: tuple[ThresholdComparison, ...] = ()
    guess: float = 0.1
    warnings: tuple[str, ...] = ()

    def _display(self) -> Display:
        if self.skipped:
            return Display("ThresholdResult (skipped)", (("why", self.note),), self.warnings)
        design = self.design
        rows = [("procedure", f"{design.procedure}, {design.level_column} at "
                              f"{100 * design.target_rate:.3g} % correct"),
                ("thresholds", f"{len(self.thresholds)} (participant x condition)")]
        rows += [(f"{c.condition} vs {c.reference} ({c.method})",
                  f"ratio {c.ratio:.3g}" if c.ratio is not None else
                  f"difference {c.mean_difference:+.3g}") for c in self.comparisons]
        return Display("ThresholdResult", tuple(rows), self.warnings,
                       ".to_frame(), .tracks, .comparisons")

    def to_frame(self) -> pd.DataFrame:
        """One row per participant and condition: ``participant_id, condition, n_trials,
        reversals, procedure_threshold, procedure_ci_low, procedure_ci_high, fit_threshold,
        fit_ci_low, fit_ci_high, fit_alpha, fit_beta, fit_lapse`` (levels in the level
        column's units; ``fit_alpha``/``fit_beta`` on the scale)."""
        return self.thresholds.copy()

    def to_dict(self) -> dict:
        design = self.design
        return {"skipped": self.skipped, "note": self.note,
                "procedure": None if design is None else design.procedure,
                "level_column": None if design is None else design.level_column,
                "scale": None if design is None else design.scale,
                "target_rate": None if design is None else design.target_rate,
                "thresholds": self.thresholds.to_dict(orient="records"),
                "comparisons": [c.to_dict() for c in self.comparisons],
                "warnings": list(self.warnings)}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def fit_threshold(u: np.ndarray, correct: np.ndarray, guess: float, rate: float,
                  lapse_max: float, n_bootstrap: int, rng: np.random.Generator,
                  alpha: float = 0.05) -> dict:
    """The psychometric fit over one track's trials (module docstring): threshold on the
    scale, its bootstrap interval and the parameters (NaN when flat)."""
    table = pd.DataFrame({"u": u, "k": correct}).groupby("u")["k"].agg(["size", "sum"])
    levels, n, k = table.index.to_numpy(float), table["size"].to_numpy(), \
        table["sum"].to_numpy()
    nan = {"fit_threshold": np.nan, "fit_ci_low": np.nan, "fit_ci_high": np.nan,
           "fit_alpha": np.nan, "fit_beta": np.nan, "fit_lapse": np.nan}
    if len(levels) < 3:
        return nan
    a, b, lam, _ = fit_counts(levels, n, k, "logistic", guess, lapse_max)

    def at_rate(a_: float, b_: float, lam_: float) -> float:
        f = (rate - guess) / (1.0 - guess - lam_)
        return float(a_ + special.logit(f) / b_) if 0 < f < 1 else np.nan

    out = {"fit_alpha": a, "fit_beta": b, "fit_lapse": lam, "fit_threshold": np.nan,
           "fit_ci_low": np.nan, "fit_ci_high": np.nan}
    if level_effect_pvalue(levels, n, k) >= alpha:
        return out
    out["fit_threshold"] = at_rate(a, b, lam)
    if n_bootstrap:
        draws = rng.binomial(n, k / n, size=(n_bootstrap, len(n)))
        boot = np.array([at_rate(*fit_counts(levels, n, kk, "logistic", guess, lapse_max,
                                             start=(a, b, lam))[:3]) for kk in draws])
        boot = boot[np.isfinite(boot)]
        if len(boot) >= n_bootstrap // 2:
            out["fit_ci_low"], out["fit_ci_high"] = (float(v) for v in np.quantile(
                boot, [alpha / 2, 1 - alpha / 2]))
    return out


def analyse_thresholds(all_trials: pd.DataFrame, trials: pd.DataFrame,
                       sessions: pd.DataFrame, conditions: list[str], reference: str,
                       guess: float, lapse_max: float = 0.1, n_bootstrap: int = 200,
                       seed: int = 0, alpha: float = 0.05) -> ThresholdResult:
    """Thresholds of every participant and condition, and their paired comparisons.

    ``all_trials`` are the trials as stored (the procedure's estimate is its track's last
    test trial, whatever the plan excludes); ``trials`` those analysed (the fits)."""
    if ADAPTIVE_MARKER not in all_trials or all_trials[ADAPTIVE_MARKER].isna().all():
        return ThresholdResult(True, "no adaptive sessions (no procedure chose the levels): "
                               "thresholds skipped")
    texts = sessions.get("Protocol", pd.Series(dtype=object)).dropna()
    designs = {d for d in (design_from_protocol(t) for t in texts) if d is not None}
    notes: list[str] = []
    if not designs:
        return ThresholdResult(True, "the sessions' protocols have no [adaptive] table: "
                               "thresholds skipped")
    design = sorted(designs, key=repr)[0]
    if len(designs) > 1:
        notes.append(f"sessions ran {len(designs)} different adaptive procedures; "
                     f"thresholds use the first ({design.procedure}, target "
                     f"{design.target_rate:.3g})")
    column = design.level_column
    stored = all_trials[(all_trials["trial_type"] == "test") & all_trials[column].notna()]
    rows, tracks = [], []
    rng = np.random.default_rng([seed, 17])
    for (participant, condition), track in stored.groupby(["participant_id", "condition"],
                                                          sort=True):
        if condition not in conditions:
            continue
        session = track["session"].max()
        if track["session"].nunique() > 1:
            notes.append(f"participant {participant} has {condition!r} tracks in several "
                         f"sessions; the last (session {session}) is used")
            track = track[track["session"] == session]
        track = track.sort_values("trial_index")
        last = track.iloc[-1]
        tracks.append(pd.DataFrame({
            "participant_id": participant, "condition": condition,
            "trial": np.arange(1, len(track) + 1), "level": track[column].to_numpy(float),
            "correct": track["correct"].to_numpy(float),
            "reversal": track["adaptive_reversal"].fillna(0).to_numpy(float) > 0}))
        analysed = trials[(trials["participant_id"] == participant)
                          & (trials["condition"] == condition) & trials[column].notna()
                          & trials["correct"].notna()]
        fit = fit_threshold(design.to_axis(analysed[column].to_numpy(float)),
                            analysed["correct"].to_numpy(float), guess, design.target_rate,
                            lapse_max, n_bootstrap, rng, alpha)
        for key in ("fit_threshold", "fit_ci_low", "fit_ci_high"):
            fit[key] = float(design.from_axis(fit[key])) if np.isfinite(fit[key]) else np.nan
        rows.append({"participant_id": participant, "condition": condition,
                     "n_trials": len(track), "reversals": int(last["adaptive_reversals"]),
                     "procedure_threshold": float(last[ADAPTIVE_MARKER]),
                     "procedure_ci_low": float(last["adaptive_ci_low"]),
                     "procedure_ci_high": float(last["adaptive_ci_high"]), **fit})
    table = pd.DataFrame(rows)
    comparisons = []
    for condition in conditions:
        if condition == reference or table.empty:
            continue
        for method in ("procedure", "fit"):
            comparison = _paired(table, method, condition, reference, design, alpha)
            if comparison is not None:
                comparisons.append(comparison)
    return ThresholdResult(False, "", design, table,
                           pd.concat(tracks, ignore_index=True) if tracks else pd.DataFrame(),
                           tuple(comparisons), guess, tuple(notes))


def _paired(table: pd.DataFrame, method: str, condition: str, reference: str,
            design: AdaptiveDesign, alpha: float) -> ThresholdComparison | None:
    wide = table.pivot(index="participant_id", columns="condition",
                       values=f"{method}_threshold")
    if condition not in wide or reference not in wide:
        return None
    pairs = wide[[reference, condition]].dropna()
    if len(pairs) < 2:
        return None
    ours, theirs = design.to_axis(pairs[condition].to_numpy()), \
        design.to_axis(pairs[reference].to_numpy())
    diff = ours - theirs
    n = len(diff)
    mean, se = float(diff.mean()), float(diff.std(ddof=1) / np.sqrt(n))
    half = float(stats.t.ppf(1 - alpha / 2, n - 1)) * se
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")  # a zero spread makes t infinite: reported as is
        test = stats.ttest_rel(ours, theirs)
        wilcoxon = stats.wilcoxon(diff).pvalue if np.any(diff != 0) and n >= 6 else None
    ratio = ratio_ci = None
    if design.scale == "log":
        ratio, ratio_ci = 10 ** mean, (10 ** (mean - half), 10 ** (mean + half))
    return ThresholdComparison(method, condition, reference, n, mean,
                               (mean - half, mean + half), ratio, ratio_ci,
                               float(test.statistic), float(test.pvalue),
                               None if wilcoxon is None else float(wilcoxon))
