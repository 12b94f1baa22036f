"""The whole analysis of stored datasets: :func:`analyze` returns an :class:`Analysis`.

:func:`analyze` loads the datasets (:func:`~crs_study.analysis.study_data.load_dataset`:
the sessions chosen, the analysis plan given, else the one the sessions' protocol declares as
``[study].analysis_plan``, else the shipped ``analysis/digit_identification.toml``, and its
exclusions), runs every analysis of the plan and returns them as result objects, each with
``to_frame()`` and ``to_json()``: ``accuracy``, ``primary`` (the GLMM), ``secondary``,
``confusions``, ``speed_accuracy``, ``psychometric``. With ``write`` (or later
:meth:`Analysis.write`) it writes into ``out`` (default ``DATASET/derivatives/crs-study``, a
BIDS derivative):

* ``results.json``: :meth:`Analysis.to_json`; rerunning on the same data gives the same
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
``sessions``, ``software``, ``generated_at`` and, once written, ``charts``. Each section is
its result object's ``to_dict()``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import pandas as pd
from matplotlib.axes import Axes

from crs_study import __version__
from crs_study._files import os_errors, sha256_file, write_atomically
from crs_study.analysis import charts
from crs_study.analysis.accuracy import AccuracyResult, analyse_accuracy, chance_level
from crs_study.analysis.confusion import Confusions, analyse_confusions
from crs_study.analysis.headline import headline
from crs_study.analysis.jsonable import to_jsonable
from crs_study.analysis.plan import AnalysisPlan
from crs_study.analysis.plan_lock import LockCheck, check_plan_lock
from crs_study.analysis.primary import PrimaryResult, primary_test
from crs_study.analysis.psychometric import PsychometricResult, analyse_psychometric
from crs_study.analysis.report_text import write_report
from crs_study.analysis.reproduce import (
    DEFAULT_RTOL,
    ResultsComparison,
    compare_results,
    read_results,
)
from crs_study.analysis.secondary import SecondaryResult, secondary_tests
from crs_study.analysis.sources import summarise_sources
from crs_study.analysis.speed_accuracy import SpeedAccuracyResult, analyse_speed_accuracy
from crs_study.analysis.study_data import DatasetPaths, StudyData, load_dataset
from crs_study.analysis.thresholds import ThresholdResult, analyse_thresholds
from crs_study.dataset.bids import DERIVATIVES, derivatives_dir
from crs_study.dataset.lock_file import PlanLock
from crs_study.dataset.outputs import OutputsRecord, participants_by_dataset
from crs_study.errors import AnalysisError, DatasetError
from crs_study.paths import recorded_path

#: The charts :meth:`Analysis.plot` draws by name (``confusion``: one per condition, through
#: :func:`crs_study.analysis.charts.plot_confusion` and ``Analysis.confusions[condition]``).
PLOTS = ("accuracy", "speed_accuracy", "caf", "psychometric", "tracks", "thresholds")


@dataclass(frozen=True)
class ReportFiles:
    """What :meth:`Analysis.write` wrote: the folder, ``results.json``, the report and the
    PNG charts."""

    folder: Path
    results: Path
    report: Path
    charts: tuple[Path, ...]


@dataclass(frozen=True, eq=False)
class Analysis:
    """Every analysis of the plan on stored datasets (:func:`analyze`).

    Attributes
    ----------
    data : StudyData
        What was analysed: the trials kept (``data.trials``), the sessions, the plan.
    accuracy : AccuracyResult
        Accuracy per condition with Wilson intervals (``accuracy.to_frame()``), per
        participant, per symbol, between participants.
    primary : PrimaryResult
        The primary test (GLMM odds ratios against the reference, or Fisher's test).
    secondary : SecondaryResult
        Paired t, Wilcoxon, McNemar, per-symbol tests, as the plan lists them.
    confusions : Confusions
        Confusion matrices and information transfer per condition.
    speed_accuracy : SpeedAccuracyResult
        Response times, conditional accuracy, efficiency scores.
    psychometric : PsychometricResult
        Psychometric functions when a stimulus level varies (else ``skipped``).
    headline : str
        One line: accuracies with intervals and the primary comparison.
    warnings : tuple of str
        What the reader must know, one sentence each (as ``results.json`` lists them).
    files : ReportFiles or None
        What ``analyze(write=True)`` wrote (:meth:`write` returns its own).
    thresholds : ThresholdResult or None
        Adaptive sessions' thresholds per participant and condition and their paired
        comparison (else ``skipped``).
    plan_lock : LockCheck or None
        The plan analysed against its lock (:mod:`crs_study.analysis.plan_lock`).
    """

    data: StudyData
    accuracy: AccuracyResult
    primary: PrimaryResult
    secondary: SecondaryResult
    confusions: Confusions
    speed_accuracy: SpeedAccuracyResult
    psychometric: PsychometricResult
    headline: str
    warnings: tuple[str, ...]
    content: dict = field(repr=False)  # results.json's, but ``charts``: see to_dict()
    files: ReportFiles | None = None
    thresholds: ThresholdResult | None = None
    plan_lock: LockCheck | None = None

    @property
    def plan(self) -> AnalysisPlan:
        return self.data.plan

    @property
    def results(self) -> dict:
        """``results.json``'s content (:meth:`to_dict`)."""
        return self.to_dict()

    def to_frame(self) -> pd.DataFrame:
        """Every comparison, the primary ones first: ``condition, reference, method,
        estimate, ci_low, ci_high, p_value, primary``."""
        rows = [{"condition": c["condition"], "reference": c["reference"],
                 "method": c["method"], "estimate": c["estimate"],
                 "ci_low": (c["ci95"] or [None, None])[0],
                 "ci_high": (c["ci95"] or [None, None])[1],
                 "p_value": c["p_value"], "primary": c["primary"]}
                for c in self.content["comparisons"]]
        return pd.DataFrame(rows, columns=["condition", "reference", "method", "estimate",
                                           "ci_low", "ci_high", "p_value", "primary"])

    def to_dict(self) -> dict:
        """``results.json``'s content (plain JSON values; see the module docstring)."""
        results = json.loads(json.dumps(self.content))
        if self.files is not None:
            results["charts"] = [p.relative_to(self.files.folder).as_posix()
                                 for p in self.files.charts]
        return results

    def to_json(self) -> str:
        """``results.json``'s text, byte for byte as :meth:`write` writes it."""
        return json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"

    def compare(self, earlier: str | os.PathLike[str] | dict, rtol: float = DEFAULT_RTOL
                ) -> ResultsComparison:
        """This analysis against an earlier one's ``results.json`` (a path, or its content):
        every value that differs beyond a relative ``rtol``, ignoring when, where and with
        which version each ran (:mod:`crs_study.analysis.reproduce`)."""
        if not isinstance(earlier, dict):
            earlier = read_results(earlier)
        return compare_results(earlier, self.to_dict(), rtol)

    def plot(self, chart: str = "accuracy", ax: Axes | None = None) -> Axes:
        """One of the report's charts (:data:`PLOTS`) on ``ax`` (a new figure without);
        returns the Axes (:mod:`crs_study.analysis.charts`)."""
        draw = {"accuracy": lambda: charts.plot_accuracy(self.accuracy, ax),
                "speed_accuracy": lambda: charts.plot_speed_accuracy(self.speed_accuracy, ax),
                "caf": lambda: charts.plot_caf(self.speed_accuracy, ax),
                "psychometric": lambda: charts.plot_psychometric(self.psychometric, ax),
                "tracks": lambda: charts.plot_tracks(self.thresholds, ax),
                "thresholds": lambda: charts.plot_thresholds(self.thresholds, ax)}
        if chart not in draw:
            raise AnalysisError(f"no chart {chart!r}; expected one of {', '.join(PLOTS)} "
                                "(a confusion matrix: charts.plot_confusion("
                                "analysis.confusions[condition]))")
        return draw[chart]()

    def write(self, out: str | os.PathLike[str] | None = None) -> ReportFiles:
        """Write ``results.json``, the report and the plan's charts into ``out`` (default:
        the dataset's ``derivatives/crs-study``; several datasets need ``out``)."""
        folder = _out_dir(list(self.data.datasets), out)
        # every output is recorded in the datasets it holds trials of, wherever it is
        # written, so that a participant's withdrawal reaches it (crs_study.dataset.outputs)
        record = OutputsRecord(participants_by_dataset(
            self.data.datasets, zip(self.data.sessions["participant"],
                                    self.data.sessions["file"], strict=True)), folder)
        record.begin()
        with os_errors(AnalysisError, "write the analysis", folder):  # disk full, no permission
            figures = folder / "figures"
            figures.mkdir(parents=True, exist_ok=True)
            chart_files = draw_charts(self, figures)
            files = ReportFiles(folder, folder / "results.json", folder / "report.md",
                                tuple(chart_files))
            written = replace(self, files=files)
            write_atomically(files.results, written.to_json())
            report = write_report(folder, written.to_dict(), written, chart_files)
            _derivative_description(folder, list(self.data.datasets))
        record.done([files.results, report, *chart_files])
        return replace(files, report=report)

    # the files of analyze(write=True), as earlier versions gave them
    @property
    def report_path(self) -> Path | None:
        return None if self.files is None else self.files.report

    @property
    def results_path(self) -> Path | None:
        return None if self.files is None else self.files.results

    @property
    def charts(self) -> tuple[Path, ...]:
        return () if self.files is None else self.files.charts

    def chart(self, name: str) -> Path | None:
        """The PNG named ``name`` (``"accuracy"``, ``"speed_accuracy"``, ``"caf"``, ...)."""
        return next((p for p in self.charts if p.stem == name), None)


def analyze(datasets: StudyData | DatasetPaths,
            plan: str | os.PathLike[str] | AnalysisPlan | None = None,
            out: str | os.PathLike[str] | None = None, *, write: bool = True,
            strict: bool = False, include_simulated: bool = False,
            responders: Sequence[str] | None = None, map_tasks=None,
            lock: str | os.PathLike[str] | PlanLock | None = None) -> Analysis:
    """Analyse stored datasets as the analysis plan says; write the report when ``write``.

    Parameters
    ----------
    datasets : a dataset folder, several (analysed together), or data already loaded by
        :func:`~crs_study.analysis.study_data.load_dataset` (then ``plan``, when given,
        replaces the one it was loaded with, exclusions included).
    plan : an analysis plan file or :class:`AnalysisPlan` (default: the protocol's, else
        the shipped ``analysis/digit_identification.toml``).
    out : where to write (default: ``DATASET/derivatives/crs-study``).
    write : write ``results.json``, the report and the charts (``Analysis.files``); False
        computes everything and writes nothing (:meth:`Analysis.write` writes later).
    strict, include_simulated, responders : how the datasets are loaded (see
        :func:`~crs_study.analysis.study_data.load_dataset`).
    map_tasks : ``map_tasks(function, tasks)`` runs the units of work of the primary test's
        parametric bootstrap (a process pool's or a Dask cluster's map; default: here).
    lock : a plan lock file (or :class:`~crs_study.protocol.lock.PlanLock`) to check the plan
        against (default: the latest lock the sessions recorded; :mod:`.plan_lock`).

    Returns
    -------
    Analysis
    """
    if lock is not None and not isinstance(lock, PlanLock):
        lock = PlanLock.read(lock)
    if isinstance(datasets, StudyData):
        data = datasets if plan is None else datasets.with_plan(plan)
    else:
        data = load_dataset(datasets, plan, strict=strict, include_simulated=include_simulated,
                            responders=responders)
    analysis = run_analyses(data, map_tasks, lock)
    if write:
        analysis = replace(analysis, files=analysis.write(out))
    return analysis


def analyze_dataset(dataset_dir: str | Path, plan_path: str | Path | None = None,
                    out_dir: str | Path | None = None) -> Analysis:
    """Analyse one dataset and write the report (``analyze([dataset_dir], ...)``)."""
    return analyze([dataset_dir], plan_path, out_dir)


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


def run_analyses(data: StudyData, map_tasks=None, lock: PlanLock | None = None) -> Analysis:
    """Every analysis of the data's plan on its trials, as an :class:`Analysis` (unwritten);
    ``map_tasks`` runs the bootstrap's units of work, ``lock`` is the plan lock to check
    against (:func:`analyze`)."""
    trials, plan = data.trials, data.plan
    plan_lock = check_plan_lock(plan, data.sessions, lock)
    warnings: list[str] = [f"the analysis deviates from the locked plan: {d}"
                           for d in plan_lock.deviations]
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
                           plan.primary.method, plan.primary.n_quadrature, alpha,
                           **plan.primary.test_options(), seed=plan.seed,
                           map_tasks=map_tasks)
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
    thresholds = analyse_thresholds(data.all_trials, trials, data.sessions, conditions,
                                    reference, chance, psych_plan.lapse_max,
                                    psych_plan.bootstrap, plan.seed, alpha)
    warnings += thresholds.warnings
    tables = accuracy.to_dict()
    primary_part, secondary_part = primary.to_dict(), secondary.to_dict()
    # named as the trials name the symbol: accuracy_by_digit and per_digit for digit data
    by_symbol = f"accuracy_by_{accuracy.by_symbol.columns[0]}"
    per_symbol = f"per_{secondary.symbol_column}"
    results = {
        "alpha": alpha, "chance": chance, "reference": reference,
        "n_participants": int(n_participants),
        "n_trials_total": int(len(data.all_trials)), "n_trials_analysed": int(len(trials)),
        "exclusions": data.exclusion_counts,
        "conditions": tables["conditions"],
        "accuracy_by_participant": tables["accuracy_by_participant"],
        by_symbol: tables[by_symbol],
        "comparisons": primary_part["comparisons"] + secondary_part["comparisons"],
        "primary": {"omnibus": primary_part["omnibus"], "model": primary_part["model"]},
        per_symbol: secondary_part[per_symbol],
        "information_transfer": Confusions(confusions).to_dict(),
        "speed_accuracy": speed.to_dict(),
        "psychometric": psychometric.to_dict(),
        "warnings": warnings,
    }
    if not thresholds.skipped:  # (results.json of fixed-level studies is as it was)
        results = {**{k: v for k, v in results.items() if k != "warnings"},
                   "thresholds": thresholds.to_dict(), "warnings": warnings}
        if thresholds.comparisons:
            # the procedure steers accuracy towards its target: the thresholds answer the
            # study's question, the accuracy GLMM is secondary
            for comparison in results["comparisons"]:
                if comparison["primary"]:
                    comparison["primary"] = False
                    comparison["secondary_because"] = (
                        "an adaptive procedure steers accuracy towards its target rate: "
                        "the threshold comparison is the primary result")
    results["headline"] = headline(results)
    kinds = sorted(set(data.sources["kind"]))
    results["sources"] = {"kind": kinds[0] if len(kinds) == 1 else "mixed",
                          "sessions": summarise_sources(data.sources),
                          "notes": list(data.source_notes)}
    # each sentence once, in order
    results["warnings"] = list(dict.fromkeys(list(data.warnings) + results["warnings"]))
    plan_file = data.plan_path
    results["plan"] = {"name": plan.name,
                       "path": None if plan_file is None else recorded_path(plan_file),
                       "sha256": None if plan_file is None else sha256_file(plan_file),
                       "lock": plan_lock.to_dict()}
    results["datasets"] = [{"path": str(d.resolve()), "name": name} for d, name in
                           zip(data.datasets, pd.unique(data.all_trials["dataset"]),
                               strict=False)]
    results["sessions"] = _sessions(data.sessions)
    results["software"] = {"name": "crs-study", "version": __version__}
    results["generated_at"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    results, non_finite = to_jsonable(results)
    if non_finite:
        results["warnings"].append(f"results.json: non-finite values written as null at "
                                   f"{', '.join(non_finite[:5])}")
    return Analysis(data, accuracy, primary, secondary, Confusions(confusions), speed,
                    psychometric, results["headline"], tuple(results["warnings"]), results,
                    thresholds=thresholds, plan_lock=plan_lock)


def draw_charts(analysis: Analysis, folder: Path) -> list[Path]:
    """PNG charts named by the plan's ``report.charts``; returns the files written."""
    wanted = analysis.plan.report.charts
    files = []
    if "accuracy" in wanted:
        files.append(charts.save(charts.plot_accuracy(analysis.accuracy),
                                 folder / "accuracy.png"))
    if "confusion" in wanted:
        for i, result in enumerate(analysis.confusions.values()):
            files.append(charts.save(charts.plot_confusion(result),
                                     folder / f"confusion_{i}_{_slug(result.condition)}.png"))
    if "speed_accuracy" in wanted:
        files.append(charts.save(charts.plot_speed_accuracy(analysis.speed_accuracy),
                                 folder / "speed_accuracy.png"))
    if "caf" in wanted:
        files.append(charts.save(charts.plot_caf(analysis.speed_accuracy), folder / "caf.png"))
    if "psychometric" in wanted and analysis.psychometric.fits:
        files.append(charts.save(charts.plot_psychometric(analysis.psychometric),
                                 folder / "psychometric.png"))
    adaptive = analysis.thresholds is not None and not analysis.thresholds.skipped
    for name in ("tracks", "thresholds"):
        if name in wanted and adaptive:
            draw = charts.plot_tracks if name == "tracks" else charts.plot_thresholds
            files.append(charts.save(draw(analysis.thresholds), folder / f"{name}.png"))
    return files


def _sessions(sessions: pd.DataFrame) -> list[dict]:
    columns = ["dataset", "participant", "session", "n_rows", "Status", "Responder",
               "DeviceURL", "Seed", "SoftwareVersion", "TrialsSha256"]
    sessions = sessions.reindex(columns=columns)
    return sessions.astype(object).where(sessions.notna(), None).to_dict("records")


def _out_dir(datasets: list[Path], out_dir: str | os.PathLike[str] | None) -> Path:
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
