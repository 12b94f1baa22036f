"""The whole analysis of stored datasets: ``results.json``, a report with charts, a headline.

:func:`analyze` loads the datasets, applies the analysis plan (given, else the one the
sessions' protocol declares as ``[study].analysis_plan``, else the shipped
``analysis/digit_identification.toml``) and writes into ``out_dir`` (default
``DATASET/derivatives/crs-study``, a BIDS derivative):

* ``results.json``: everything below as plain JSON; rerunning on the same data gives the same
  file apart from ``generated_at`` (every bootstrap is seeded from the plan's seed);
* ``report.md`` or ``report.html`` and ``figures/*.png``.

``results.json`` keys: ``headline``, ``warnings`` (list of sentences), ``conditions``
(per condition ``n_trials, n_correct, accuracy, ci95, p_vs_chance, n_participants``),
``reference``, ``comparisons`` (the primary GLMM comparison(s) first, then the secondary
tests; each ``method, condition, reference, estimate, ci95, p_value`` and ``primary`` (true
for the primary comparisons, which also say their ``test``, ``glmm`` or ``fisher``, and whether
the GLMM was a ``logistic_regression`` without random effect); the GLMM estimate is an odds
ratio), ``primary`` (omnibus test and the fitted model), ``per_digit`` (``per_symbol`` for
a dataset of another stimulus set: the keys name the symbol as its trials do),
``information_transfer`` (per condition ``bits, ci95, ...``), ``speed_accuracy``,
``psychometric``, ``exclusions``, ``chance``, ``alpha``, ``plan``, ``datasets``,
``sessions``, ``software``, ``generated_at``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from crs_study import __version__
from crs_study._files import os_errors, sha256_file, write_atomically
from crs_study.analysis import charts
from crs_study.analysis.accuracy import (
    PARTICIPANT_LEVEL,
    analyse_accuracy,
    chance_level,
    headline_accuracy,
)
from crs_study.analysis.confusion import analyse_confusions
from crs_study.analysis.load import LoadedData, load_datasets, with_exclusions
from crs_study.analysis.plan import AnalysisPlan, default_plan_path, load_plan
from crs_study.analysis.primary import primary_test
from crs_study.analysis.psychometric import analyse_psychometric
from crs_study.analysis.report_text import write_report
from crs_study.analysis.secondary import secondary_tests
from crs_study.analysis.sources import select_sources, summarise_sources
from crs_study.analysis.speed_accuracy import analyse_speed_accuracy
from crs_study.dataset.bids import DERIVATIVES, derivatives_dir
from crs_study.errors import AnalysisError, ConfigError, DatasetError
from crs_study.paths import shipped_file


@dataclass(frozen=True)
class AnalysisResult:
    """What :func:`analyze` produced: the headline, the results dict and the files written."""

    headline: str
    results: dict
    report_path: Path | None
    results_path: Path | None
    warnings: tuple[str, ...] = ()
    charts: tuple[Path, ...] = ()

    def chart(self, name: str) -> Path | None:
        """The PNG named ``name`` (``"accuracy"``, ``"speed_accuracy"``, ``"caf"``, ...)."""
        return next((p for p in self.charts if p.stem == name), None)


def analyze_dataset(dataset_dir: str | Path, plan_path: str | Path | None = None,
                    out_dir: str | Path | None = None) -> AnalysisResult:
    """Analyse one dataset (the library entry point used by ``crs-study demo``)."""
    return analyze([dataset_dir], plan_path, out_dir)


def analyze(datasets: list[str | Path], plan_path: str | Path | None = None,
            out_dir: str | Path | None = None, strict: bool = False,
            write: bool = True, include_simulated: bool = False,
            responders: list[str] | None = None) -> AnalysisResult:
    """Analyse ``datasets`` with a plan; write the report and ``results.json`` when ``write``.

    Simulated and human sessions together are refused unless ``include_simulated`` (pool
    them, with a warning) or ``responders`` keeps one kind (:mod:`.sources`).
    """
    datasets = [Path(d) for d in datasets]
    loaded = load_datasets(datasets, None, strict=strict)
    loaded, sources, source_notes = select_sources(loaded, include_simulated, responders)
    plan, plan_file, plan_notes = resolve_plan(loaded, plan_path)
    loaded = with_exclusions(loaded, plan.exclusions)
    results, parts = run_analyses(loaded, plan)
    kinds = sorted(set(sources["kind"]))
    results["sources"] = {"kind": kinds[0] if len(kinds) == 1 else "mixed",
                          "sessions": summarise_sources(sources),
                          "notes": source_notes}
    pooled = [n for n in source_notes if "pooled on request" in n]
    every = list(loaded.warnings) + pooled + excluded_participants(loaded) + plan_notes \
        + results["warnings"]
    results["warnings"] = list(dict.fromkeys(every))          # each sentence once, in order
    results["plan"] = {"name": plan.name, "path": str(plan_file),
                       "sha256": sha256_file(plan_file)}
    results["datasets"] = [{"path": str(d.resolve()), "name": name} for d, name in
                           zip(datasets, pd.unique(loaded.trials["dataset"]), strict=False)]
    results["sessions"] = _sessions(loaded)
    results["software"] = {"name": "crs-study", "version": __version__}
    results["generated_at"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    results, non_finite = to_jsonable(results)
    if non_finite:
        results["warnings"].append(f"results.json: non-finite values written as null at "
                                   f"{', '.join(non_finite[:5])}")
    if not write:
        return AnalysisResult(results["headline"], results, None, None,
                              tuple(results["warnings"]))
    out = _out_dir(datasets, out_dir)
    with os_errors(AnalysisError, "write the analysis", out):  # disk full, no permission
        figures = out / "figures"
        figures.mkdir(parents=True, exist_ok=True)
        chart_files = draw_charts(parts, plan, figures)
        results["charts"] = [str(p.relative_to(out)) for p in chart_files]
        results_path = out / "results.json"
        write_atomically(results_path, json.dumps(results, indent=2, allow_nan=False) + "\n")
        report_path = write_report(out, results, parts, plan, chart_files)
        _derivative_description(out, datasets)
    return AnalysisResult(results["headline"], results, report_path, results_path,
                          tuple(results["warnings"]), tuple(chart_files))


def excluded_participants(loaded: LoadedData) -> list[str]:
    """A warning naming each participant none of whose trials is analysed, with the reasons."""
    kept = set(loaded.analysed["participant_id"])
    notes = []
    for participant, rows in loaded.trials.groupby("participant_id", sort=True):
        if participant in kept:
            continue
        reasons = rows["exclusion"].replace("", "unanswered").value_counts()
        why = ", ".join(f"{reason} {count}" for reason, count in reasons.items())
        notes.append(f"participant {participant!r} has no analysed trial (all {len(rows)} "
                     f"excluded: {why}): left out of every analysis")
    return notes


def resolve_plan(loaded: LoadedData, plan_path: str | Path | None
                 ) -> tuple[AnalysisPlan, Path, list[str]]:
    """The plan given, else the one the protocol declares, else the shipped default."""
    notes: list[str] = []
    if plan_path is not None:
        return load_plan(plan_path), Path(plan_path), notes
    declared = set()
    for text in loaded.sessions.get("Protocol", pd.Series(dtype=object)).dropna():
        try:
            protocol = tomllib.loads(text)
        except tomllib.TOMLDecodeError:
            continue
        value = protocol.get("study", {}).get("analysis_plan") or protocol.get("analysis_plan")
        if isinstance(value, str):
            declared.add(value)
    if len(declared) > 1:
        notes.append(f"sessions declare different analysis plans {sorted(declared)}; used "
                     f"{sorted(declared)[0]!r}")
    if declared:
        name = sorted(declared)[0]
        try:
            path = shipped_file(name)
        except ConfigError:
            notes.append(f"the protocol's analysis plan {name!r} was not found; used the "
                         "shipped analysis/digit_identification.toml")
        else:
            return load_plan(path), path, notes
    path = default_plan_path()
    return load_plan(path), path, notes


def order_conditions(trials: pd.DataFrame, plan: AnalysisPlan) -> tuple[list[str], str,
                                                                         list[str]]:
    """Conditions present (plan order first), the reference, and notes on mismatches."""
    present = list(pd.unique(trials["condition"]))
    notes = []
    ordered = [c for c in plan.conditions if c in present]
    extra = sorted(c for c in present if c not in plan.conditions)
    missing = [c for c in plan.conditions if c not in present]
    if missing:
        notes.append(f"missing condition(s) {missing}: the plan names them but no analysed "
                     f"trial has them; compared only {ordered + extra}")
    if extra and plan.conditions:
        notes.append(f"condition(s) {extra} are not in the plan; analysed after the planned ones")
    ordered += extra
    if not ordered:
        raise AnalysisError("no trial is left to analyse after the exclusions "
                            "(see the exclusion counts)")
    reference = plan.reference_condition(ordered)
    if reference not in ordered:
        notes.append(f"reference condition {reference!r} has no trials; used {ordered[0]!r} "
                     "as the reference instead")
        reference = ordered[0]
    ordered.remove(reference)
    return [reference, *ordered], reference, notes


def run_analyses(loaded: LoadedData, plan: AnalysisPlan) -> tuple[dict, dict]:
    """Every analysis of the plan on the analysed trials; returns (results, result objects)."""
    trials = loaded.analysed
    warnings: list[str] = []
    conditions, reference, notes = order_conditions(trials, plan)
    warnings += notes
    chance = chance_level(trials, plan.chance)
    alpha = plan.alpha
    n_participants = trials["participant_id"].nunique()
    if n_participants == 1:
        warnings.append("a single participant: no random effect of participant is estimable "
                        "and no participant-level test is possible; trials are treated as "
                        "independent, so the result describes this participant only")
    accuracy = analyse_accuracy(trials, tuple(conditions), chance, alpha)
    warnings += accuracy.warnings
    for _, row in accuracy.by_condition.iterrows():
        if row["n_correct"] in (0, row["n_trials"]):
            warnings.append(f"condition {row['condition']!r} is at {100 * row['accuracy']:.0f} "
                            f"% correct ({row['n_correct']}/{row['n_trials']}): its odds are "
                            "infinite (separation); see the GLMM note on what was done")
    primary = primary_test(trials, conditions, reference, plan.primary.random_effects,
                           plan.primary.method, plan.primary.n_quadrature, alpha)
    warnings += primary.warnings
    secondary = secondary_tests(trials, accuracy.by_participant, conditions, reference,
                                plan.secondary.tests, plan.secondary.correction, alpha)
    warnings += secondary.warnings
    confusions, notes = analyse_confusions(
        trials, conditions, plan.confusion.bias_correction, plan.confusion.bootstrap,
        plan.confusion.bootstrap_unit, plan.seed, alpha)
    warnings += notes
    speed = analyse_speed_accuracy(trials, conditions, plan.exclusions.rt_column,
                                   plan.speed_accuracy.caf_bins, alpha)
    warnings += speed.warnings
    psych_plan = plan.psychometric
    psychometric = analyse_psychometric(
        trials, conditions, chance, psych_plan.level_column, psych_plan.function,
        psych_plan.lapse_max, psych_plan.threshold, psych_plan.bootstrap, plan.seed, alpha)
    warnings += psychometric.warnings
    by_participant = accuracy.by_participant
    between = {r["condition"]: {"mean": r["mean"], "ci95": [r["ci_low"], r["ci_high"]],
                                "n_participants": int(r["n_participants"]),
                                "method": r["method"]}
               for r in records(accuracy.between_participants)}
    shown = {r["condition"]: {"accuracy": r["accuracy"], "ci95": [r["ci_low"], r["ci_high"]],
                              "method": r["method"]}
             for r in records(headline_accuracy(accuracy))}
    results = {
        "alpha": alpha, "chance": chance, "reference": reference,
        "n_participants": int(n_participants),
        "n_trials_total": int(len(loaded.trials)), "n_trials_analysed": int(len(trials)),
        "exclusions": loaded.exclusion_counts,
        "conditions": {
            row["condition"]: {
                "n_trials": int(row["n_trials"]), "n_correct": int(row["n_correct"]),
                "accuracy": float(row["accuracy"]),
                "ci95": [float(row["ci_low"]), float(row["ci_high"])],
                "ci95_method": POOLED_CI_METHOD,
                "p_vs_chance": float(row["p_vs_chance"]),
                "n_participants": int((by_participant["condition"] == row["condition"]).sum()),
                "between_participants": between.get(row["condition"]),
                "headline": shown.get(row["condition"]),
            } for _, row in accuracy.by_condition.iterrows()},
        "accuracy_by_participant": records(by_participant),
        f"accuracy_by_{accuracy.by_symbol.columns[0]}": records(accuracy.by_symbol),
        "comparisons": [c.to_dict() for c in primary.comparisons]
        + [t.to_dict() for t in secondary.tests],
        "primary": {"omnibus": primary.omnibus, "model": primary.model},
        f"per_{accuracy.by_symbol.columns[0]}": {c: records(t)
                                                 for c, t in secondary.per_symbol.items()},
        "information_transfer": {c: r.to_dict() for c, r in confusions.items()},
        "speed_accuracy": {
            "rt_column": speed.rt_column,
            "rt_summary": records(speed.rt_summary),
            "caf": records(speed.caf),
            "efficiency": records(speed.efficiency_summary)},
        "psychometric": {"level_column": psychometric.level_column,
                         "skipped": psychometric.skipped, "note": psychometric.note,
                         "fits": {c: f.to_dict() for c, f in psychometric.fits.items()}},
        "warnings": warnings,
    }
    results["headline"] = headline(results)
    parts = {"accuracy": accuracy, "primary": primary, "secondary": secondary,
             "confusions": confusions, "speed": speed, "psychometric": psychometric,
             "exclusions": loaded.exclusion_counts}
    return results, parts


#: What the ``ci95`` of a condition's accuracy is (results.json ``conditions.<c>.ci95_method``).
POOLED_CI_METHOD = ("Wilson score interval of the pooled trials (trial level: ignores "
                    "differences between participants; see between_participants)")


def format_p(p: float | None) -> str:
    """``p = 0.0123``, ``p = 3.4e-07`` or ``p < 1e-16`` (never ``p = 0``)."""
    if p is None or not math.isfinite(p):
        return "p n/a"
    if p < 1e-16:
        return "p < 1e-16"
    return f"p = {p:.3g}" if p >= 1e-4 else f"p = {p:.2e}"


def headline(results: dict) -> str:
    """One line: each condition's accuracy with an interval that accounts for participants
    (``conditions.<c>.headline``: the mean of participant accuracies with the t interval
    across participants, or the pooled Wilson interval where that has no width, labelled),
    then the primary comparison(s). A separated condition's odds ratio is given as its
    one-sided profile limit ("> 367 ... upper limit infinite"), never as the penalised
    estimate; a logistic regression without participant variance says so."""
    parts, methods = [], []
    reference = results["reference"]
    order = [c for c in results["conditions"] if c != reference] + [reference]
    level = f"{100 * (1 - results['alpha']):g} %"
    for condition in order:
        row = results["conditions"].get(condition)
        if row:
            shown = row.get("headline") or {"accuracy": row["accuracy"], "ci95": row["ci95"],
                                            "method": POOLED_CI_METHOD}
            low, high = shown["ci95"]
            parts.append(f"{condition} {100 * shown['accuracy']:.1f} % "
                         f"[{100 * low:.1f}, {100 * high:.1f}]")
            methods.append(shown["method"])
    text = " vs ".join(parts)
    if parts:
        if set(methods) == {PARTICIPANT_LEVEL}:
            text += (f" (mean of {results['n_participants']} participants, {level} t interval "
                     "across participants)")
        elif len(set(methods)) == 1:
            text += f" ({level} {methods[0]})"
        else:
            text += f" ({level} intervals: {'; '.join(dict.fromkeys(methods))})"
    glmm = [c for c in results["comparisons"] if c["primary"]]
    for c in glmm:
        name = "GLMM odds ratio" if c["test"] == "glmm" else "odds ratio (Fisher)"
        notes = []
        if c["logistic_regression"]:
            notes.append("logistic regression: no participant variance estimable")
        if len(glmm) > 1:
            notes.insert(0, f"{c['condition']} vs {c['reference']}")
        who = f" ({'; '.join(notes)})" if notes else ""
        if c.get("separated"):
            text += f"; {name}{who} {_separated_text(c, level)}, {format_p(c['p_value'])}"
            continue
        low, high = ("0" if v is None and k == 0 else "inf" if v is None else f"{v:.2f}"
                     for k, v in enumerate(c["ci95"]))
        text += f"; {name}{who} {c['estimate']:.2f} [{low}, {high}], {format_p(c['p_value'])}"
    if not glmm:
        text += "; no comparison of conditions (see warnings)"
    return text


def _separated_text(c: dict, level: str) -> str:
    """``> 367 (ML estimate infinite: ...; upper limit infinite)`` for a separated odds ratio."""
    low, high = c["ci95"]
    why = f"ML estimate infinite: a condition at 0 or 100 %; one-sided {level} profile limit"
    if low is not None:
        return f"> {low:.3g} ({why}, upper limit infinite)"
    if high is not None:
        return f"< {high:.3g} ({why}, lower limit 0)"
    return "not estimable (ML estimate infinite, no finite profile limit)"


def draw_charts(parts: dict, plan: AnalysisPlan, folder: Path) -> list[Path]:
    """PNG charts named by the plan's ``report.charts``; returns the files written."""
    wanted = plan.report.charts
    files = []
    if "accuracy" in wanted:
        files.append(charts.save(charts.plot_accuracy(parts["accuracy"]),
                                 folder / "accuracy.png"))
    if "confusion" in wanted:
        for i, result in enumerate(parts["confusions"].values()):
            files.append(charts.save(charts.plot_confusion(result),
                                     folder / f"confusion_{i}_{_slug(result.condition)}.png"))
    if "speed_accuracy" in wanted:
        files.append(charts.save(charts.plot_speed_accuracy(parts["speed"]),
                                 folder / "speed_accuracy.png"))
    if "caf" in wanted:
        files.append(charts.save(charts.plot_caf(parts["speed"]), folder / "caf.png"))
    if "psychometric" in wanted and parts["psychometric"].fits:
        files.append(charts.save(charts.plot_psychometric(parts["psychometric"]),
                                 folder / "psychometric.png"))
    return files


def records(table: pd.DataFrame) -> list[dict]:
    """Rows as dicts; an empty cell (NaN: a median of no trials, say) becomes None, which the
    table's own counts explain (``n = 0``, ``n_trials = 0``)."""
    return table.astype(object).where(table.notna(), None).to_dict("records")


def to_jsonable(value, path: str = "") -> tuple[object, list[str]]:
    """Plain JSON types; NaN and infinities become null and their key paths are returned."""
    bad: list[str] = []

    def walk(v, where):
        if isinstance(v, dict):
            return {str(k): walk(x, f"{where}.{k}" if where else str(k)) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]
        if isinstance(v, np.generic):
            v = v.item()
        if v is pd.NA or v is pd.NaT:
            return None
        if isinstance(v, float) and not math.isfinite(v):
            bad.append(where)
            return None
        if isinstance(v, Path):
            return str(v)
        return v

    return walk(value, path), bad


def _sessions(loaded: LoadedData) -> list[dict]:
    columns = ["dataset", "participant", "session", "n_rows", "Status", "Responder",
               "DeviceURL", "Seed", "SoftwareVersion", "TrialsSha256"]
    sessions = loaded.sessions.reindex(columns=columns)
    return sessions.astype(object).where(sessions.notna(), None).to_dict("records")


def _out_dir(datasets: list[Path], out_dir: str | Path | None) -> Path:
    if out_dir is not None:
        return Path(out_dir)
    if len(datasets) > 1:
        raise DatasetError(f"{len(datasets)} datasets and no output directory: give --out DIR")
    return derivatives_dir(datasets[0])


def _derivative_description(out: Path, datasets: list[Path]) -> None:
    """A BIDS derivative's dataset_description.json when writing inside a dataset."""
    if out.parent.name != DERIVATIVES or (out / "dataset_description.json").exists():
        return
    description = {"Name": "crs-study analysis", "BIDSVersion": "1.9.0",
                   "DatasetType": "derivative",
                   "GeneratedBy": [{"Name": "crs-study", "Version": __version__}]}
    (out / "dataset_description.json").write_text(json.dumps(description, indent=2) + "\n")


def _slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in text).strip("-") or "condition"
