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
its result object's ``to_dict()`` (:mod:`crs_study.analysis.results_json`); the report is
written from the same objects.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd
from matplotlib.axes import Axes

from crs_study import __version__
from crs_study._display import Display, Displayed
from crs_study._files import os_errors, sha256_file, write_atomically
from crs_study.analysis import charts, results_json
from crs_study.analysis.accuracy import AccuracyResult, analyse_accuracy, chance_level
from crs_study.analysis.confusion import Confusions, analyse_confusions
from crs_study.analysis.headline import headline
from crs_study.analysis.jsonable import to_jsonable
from crs_study.analysis.plan import AnalysisPlan, order_conditions
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
from crs_study.analysis.speed_accuracy import SpeedAccuracyResult, analyse_speed_accuracy
from crs_study.analysis.study_data import DatasetPaths, StudyData, load_dataset
from crs_study.analysis.thresholds import ThresholdResult, analyse_thresholds
from crs_study.dataset.bids import DERIVATIVES, derivatives_dir
from crs_study.dataset.lock_file import PlanLock
from crs_study.dataset.outputs import OutputsRecord, participants_by_dataset
from crs_study.errors import AnalysisError, DatasetError

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


@dataclass(frozen=True, eq=False, repr=False)
class Analysis(Displayed):
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
    generated_at : str
        When the analysis ran (UTC, ISO 8601), as ``results.json`` records it.
    plan_sha256 : str or None
        The sha256 of the plan's file when the analysis read it (None: a plan object).
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
    files: ReportFiles | None = None
    thresholds: ThresholdResult | None = None
    plan_lock: LockCheck | None = None
    generated_at: str = ""
    plan_sha256: str | None = None

    @property
    def plan(self) -> AnalysisPlan:
        return self.data.plan

    @property
    def reference(self) -> str:
        """The reference condition (every comparison is against it)."""
        return self.accuracy.conditions[0]

    @property
    def n_participants(self) -> int:
        """Participants with a trial analysed."""
        return int(self.data.trials["participant_id"].nunique())

    def warning_groups(self) -> dict[str, tuple[str, ...]]:
        """The warnings by what they concern (each group's in the order found), in the order
        a reader checks them: the data, the design (conditions, participants, separation),
        then each analysis; the group of a warning is the result object that raised it."""
        thresholds = self.thresholds.warnings if self.thresholds is not None else ()
        sources = {"data": self.data.warnings, "accuracy": self.accuracy.warnings,
                   "primary test": self.primary.warnings,
                   "secondary tests": self.secondary.warnings,
                   "speed and accuracy": self.speed_accuracy.warnings,
                   "psychometric functions": self.psychometric.warnings,
                   "adaptive thresholds": thresholds}
        groups: dict[str, list[str]] = {}
        for warning in self.warnings:
            group = next((name for name, raised in sources.items() if warning in raised),
                         "design and other")
            groups.setdefault(group, []).append(warning)
        order = ["data", "design and other", *list(sources)[1:]]
        return {name: tuple(groups[name]) for name in order if name in groups}

    def _display(self) -> Display:
        accuracy = self.accuracy._display().rows[:-1]
        return Display(f"Analysis of {self.n_participants} participants ({self.plan.name})",
                       (("headline", self.headline), *accuracy,
                        ("report", "written: " + str(self.files.report) if self.files
                         else "not written (.write())")),
                       self.warnings, f".to_frame(), .plot(name): {', '.join(self.plots())}")

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
                for c in to_jsonable(results_json.comparisons(self))[0]]
        return pd.DataFrame(rows, columns=["condition", "reference", "method", "estimate",
                                           "ci_low", "ci_high", "p_value", "primary"])

    def to_dict(self) -> dict:
        """``results.json``'s content (plain JSON values; see the module docstring)."""
        results = to_jsonable(results_json.content(self))[0]
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

    @property
    def colours(self) -> dict[str, str]:
        """Each condition's colour in every chart: by its place in the plan's order."""
        present = self.accuracy.conditions
        return charts.condition_colours(
            [c for c in self.plan.conditions if c in present] + list(present))

    def plots(self) -> tuple[str, ...]:
        """The charts this analysis has (:meth:`plot`): a psychometric chart needs fitted
        functions, the tracks and thresholds an adaptive study."""
        adaptive = self.thresholds is not None and not self.thresholds.skipped
        return tuple(name for name in PLOTS
                     if (name != "psychometric" or self.psychometric.fits)
                     and (name not in ("tracks", "thresholds") or adaptive))

    def plot(self, chart: str = "accuracy", ax: Axes | None = None) -> Axes:
        """One of the report's charts (:meth:`plots` names those this analysis has) on
        ``ax`` (a new figure without, which a notebook shows as a picture); returns the Axes
        (:mod:`crs_study.analysis.charts`)."""
        available = self.plots()
        if chart not in available:
            why = "" if chart not in PLOTS else " (not in this analysis: " + (
                "no stimulus level varies" if chart == "psychometric" else
                "no session is adaptive") + ")"
            raise AnalysisError(f"no chart {chart!r}{why}; this analysis has "
                                f"{', '.join(available)} (a confusion matrix: "
                                "charts.plot_confusion(analysis.confusions[condition]))")
        return _draw(self, chart, ax)

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
            report = write_report(folder, written, chart_files)
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
            lock: str | os.PathLike[str] | PlanLock | None = None,
            progress: Callable[[str], None] | None = None) -> Analysis:
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
    progress : ``progress(step)`` as each step begins (``crs-study analyze`` shows them).

    Returns
    -------
    Analysis
    """
    if lock is not None and not isinstance(lock, PlanLock):
        lock = PlanLock.read(lock)
    step = progress or (lambda _: None)
    step("loading the datasets")
    if isinstance(datasets, StudyData):
        data = datasets if plan is None else datasets.with_plan(plan)
    else:
        data = load_dataset(datasets, plan, strict=strict, include_simulated=include_simulated,
                            responders=responders)
    analysis = run_analyses(data, map_tasks, step, lock)
    if write:
        step("writing the report and charts")
        analysis = replace(analysis, files=analysis.write(out))
    return analysis


def analyze_dataset(dataset_dir: str | Path, plan_path: str | Path | None = None,
                    out_dir: str | Path | None = None) -> Analysis:
    """Analyse one dataset and write the report (``analyze([dataset_dir], ...)``)."""
    return analyze([dataset_dir], plan_path, out_dir)


#: The steps of :func:`run_analyses`, as ``progress`` names them.
STEPS = ("accuracy", "primary test", "secondary tests", "confusions", "speed and accuracy",
         "psychometric functions", "adaptive thresholds")


def run_analyses(data: StudyData, map_tasks=None,
                 progress: Callable[[str], None] | None = None,
                 lock: PlanLock | None = None) -> Analysis:
    """Every analysis of the data's plan on its trials, as an :class:`Analysis` (unwritten);
    ``map_tasks`` runs the bootstrap's units of work, ``progress(step)`` is told of each of
    :data:`STEPS` as it begins, ``lock`` is the plan lock to check against (:func:`analyze`)."""
    step = progress or (lambda _: None)
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
    step("accuracy")
    accuracy = analyse_accuracy(trials, tuple(conditions), chance, alpha)
    warnings += accuracy.warnings
    for _, row in accuracy.by_condition.iterrows():
        if row["n_correct"] in (0, row["n_trials"]):
            warnings.append(f"condition {row['condition']!r} is at {100 * row['accuracy']:.0f} "
                            f"% correct ({row['n_correct']}/{row['n_trials']}): its odds are "
                            "infinite (separation); see the GLMM note on what was done")
    step("primary test")
    primary = primary_test(trials, conditions, reference, plan.primary.random_effects,
                           plan.primary.method, plan.primary.n_quadrature, alpha,
                           **plan.primary.test_options(), seed=plan.seed,
                           map_tasks=map_tasks)
    warnings += primary.warnings
    step("secondary tests")
    secondary = secondary_tests(trials, accuracy.by_participant, conditions, reference,
                                plan.secondary.tests, plan.secondary.correction, alpha)
    warnings += secondary.warnings
    step("confusions")
    confusions, notes = analyse_confusions(
        trials, conditions, plan.confusion.bias_correction, plan.confusion.bootstrap,
        plan.confusion.bootstrap_unit, plan.seed, alpha)
    warnings += notes
    step("speed and accuracy")
    speed = analyse_speed_accuracy(trials, conditions, plan.exclusions.rt_column,
                                   plan.speed_accuracy.caf_bins, alpha)
    warnings += speed.warnings
    step("psychometric functions")
    psych_plan = plan.psychometric
    psychometric = analyse_psychometric(
        trials, conditions, chance, psych_plan.level_column, psych_plan.function,
        psych_plan.lapse_max, psych_plan.threshold, psych_plan.bootstrap, plan.seed, alpha)
    warnings += psychometric.warnings
    step("adaptive thresholds")
    thresholds = analyse_thresholds(data.all_trials, trials, data.sessions, conditions,
                                    reference, chance, psych_plan.lapse_max,
                                    psych_plan.bootstrap, plan.seed, alpha)
    warnings += thresholds.warnings
    warnings = list(dict.fromkeys(list(data.warnings) + warnings))  # each sentence once
    plan_file = data.plan_path
    analysis = Analysis(data, accuracy, primary, secondary, Confusions(confusions), speed,
                        psychometric, "", tuple(warnings), thresholds=thresholds,
                        generated_at=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                        plan_sha256=None if plan_file is None else sha256_file(plan_file),
                        plan_lock=plan_lock)
    content = results_json.content(analysis)
    line = headline(content)  # from the file's sections, so a reader can rebuild it
    non_finite = to_jsonable(content)[1]
    if non_finite:
        warnings.append(f"results.json: non-finite values written as null at "
                        f"{', '.join(non_finite[:5])}")
    return replace(analysis, headline=line, warnings=tuple(warnings))


def _draw(analysis: Analysis, chart: str, ax: Axes | None = None) -> Axes:
    """Chart ``chart`` of :data:`PLOTS`, in the analysis's condition colours."""
    result = {"accuracy": analysis.accuracy, "speed_accuracy": analysis.speed_accuracy,
              "caf": analysis.speed_accuracy, "psychometric": analysis.psychometric,
              "tracks": analysis.thresholds, "thresholds": analysis.thresholds}[chart]
    return getattr(charts, f"plot_{chart}")(result, ax, colours=analysis.colours)


def draw_charts(analysis: Analysis, folder: Path) -> list[Path]:
    """PNG charts named by the plan's ``report.charts`` that the analysis has; returns the
    files written."""
    wanted, available = analysis.plan.report.charts, analysis.plots()
    files = []
    for name in PLOTS:
        if name in wanted and name in available:
            files.append(charts.save(_draw(analysis, name), folder / f"{name}.png"))
        if name == "accuracy" and "confusion" in wanted:
            for i, result in enumerate(analysis.confusions.values()):
                files.append(charts.save(charts.plot_confusion(result), folder /
                                         f"confusion_{i}_{_slug(result.condition)}.png"))
    return files


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
