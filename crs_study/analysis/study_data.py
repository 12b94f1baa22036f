"""The trials of stored datasets as an analysis sees them: :func:`load_dataset`.

Loading (:func:`crs_study.analysis.load.load_datasets`) reads and checks every session;
then, as :func:`crs_study.analysis.report.analyze` does before any test:

1. the sessions are chosen: simulated and human sessions are never pooled silently
   (:mod:`crs_study.analysis.sources`: ``include_simulated``, ``responders``);
2. the analysis plan is found: the one given, else the one the sessions' protocol declares
   (``[study].analysis_plan``), else the shipped ``analysis/digit_identification.toml``;
3. the plan's exclusions are applied (``[exclusions]``: practice trials, device faults,
   time-outs, anticipations, slow answers; the first reason that applies is the trial's).

:attr:`StudyData.trials` is the table the analyses use: the trials kept, with the columns of
:mod:`crs_study.analysis.load` (``dataset, participant, participant_id, session``, the
columns of ``crs_study.dataset.schema.TRIAL_COLUMNS``, level columns, ``excluded``,
``exclusion``).
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import pandas as pd

from crs_study._display import Display, Displayed
from crs_study.analysis.load import LoadedData, load_datasets, with_exclusions
from crs_study.analysis.plan import AnalysisPlan, Exclusions, default_plan_path, load_plan
from crs_study.analysis.sources import select_sources
from crs_study.errors import ConfigError
from crs_study.paths import shipped_file

#: What ``load_dataset(exclude=False)`` applies: no rule but the practice one (when asked);
#: time-outs neither excluded nor counted as errors (``correct`` stays empty).
NO_EXCLUSIONS = Exclusions(practice=False, device_faults=False, timeouts="keep",
                           anticipation_s=0.0, max_response_time_s=0.0)

DatasetPaths = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]


@dataclass(frozen=True, eq=False, repr=False)
class StudyData(Displayed):
    """The trials of one or several datasets as an analysis sees them (:func:`load_dataset`).

    Attributes
    ----------
    trials : pandas.DataFrame
        The trials analysed: every trial the exclusions keep, one row each (columns in the
        module docstring of :mod:`crs_study.analysis.load`). :meth:`to_frame` returns a copy.
    all_trials : pandas.DataFrame
        Every trial of the sessions chosen, with ``excluded`` and ``exclusion`` (the first
        reason: ``practice``, ``device_fault``, ``timeout``, ``anticipation``, ``slow``).
    sessions : pandas.DataFrame
        One row per session: ``dataset, participant, session, file, n_rows`` and the
        sidecar's ``Status, Seed, SoftwareVersion, ..., Protocol``.
    sources : pandas.DataFrame
        One row per session: ``dataset, participant, session, responder, device, kind``
        (``simulated`` or ``human``).
    plan : AnalysisPlan
        The analysis plan whose exclusions were applied (and which ``analyze`` runs).
    plan_path : Path or None
        Its file (None for a plan given as an object).
    exclusion_counts : dict
        ``{reason: {condition: trials}}`` for every rule applied.
    warnings : tuple of str
        Integrity checks that failed, sessions left out, the plan chosen, participants
        without a trial left, exclusions other than the plan's: one sentence each.
    datasets : tuple of Path
        The dataset folders, as given.
    """

    trials: pd.DataFrame
    all_trials: pd.DataFrame
    sessions: pd.DataFrame
    sources: pd.DataFrame
    plan: AnalysisPlan
    plan_path: Path | None
    exclusion_counts: dict[str, dict[str, int]]
    warnings: tuple[str, ...]
    datasets: tuple[Path, ...]
    #: the sources' notes, as results.json's ``sources.notes`` lists them
    source_notes: tuple[str, ...]
    #: every trial of the sessions chosen as stored, before any exclusion (another plan's
    #: exclusions apply to these: :meth:`with_plan`)
    raw: LoadedData = field(repr=False)

    def _display(self) -> Display:
        trials = self.trials
        counts = trials.groupby("condition", sort=False).size() if len(trials) else {}
        return Display("StudyData", (
            ("datasets", ", ".join(os.fspath(d) for d in self.datasets)),
            ("participants", str(trials["participant_id"].nunique() if len(trials) else 0)),
            ("sessions", str(len(self.sessions))),
            ("trials", f"{len(trials)} analysed of {len(self.all_trials)}"),
            ("per condition", ", ".join(f"{c} {n}" for c, n in dict(counts).items())),
            ("plan", self.plan.name)), self.warnings, ".to_frame(), .excluded, .sessions")

    def to_frame(self) -> pd.DataFrame:
        """The trials analysed (a copy of :attr:`trials`)."""
        return self.trials.copy()

    @property
    def excluded(self) -> pd.DataFrame:
        """The trials left out, each with its ``exclusion`` reason."""
        return self.all_trials.loc[self.all_trials["excluded"]].reset_index(drop=True)

    def with_plan(self, plan: str | os.PathLike[str] | AnalysisPlan, *, exclude: bool = True,
                  practice: bool | None = None) -> StudyData:
        """The same sessions under another analysis plan (its exclusions applied afresh to
        every stored trial; ``exclude`` and ``practice`` as :func:`load_dataset` has them)."""
        return _with_plan(self.raw, self.sources, self.source_notes, self.datasets, plan,
                          exclude, practice)


def load_dataset(datasets: DatasetPaths, plan: str | os.PathLike[str] | AnalysisPlan | None
                 = None, *, exclude: bool = True, practice: bool | None = None,
                 strict: bool = False, include_simulated: bool = False,
                 responders: Sequence[str] | None = None) -> StudyData:
    """Load stored datasets as an analysis sees them (see the module docstring).

    Parameters
    ----------
    datasets : a dataset folder or several (analysed together).
    plan : an analysis plan file or :class:`AnalysisPlan` (default: the protocol's, else
        the shipped one).
    exclude : apply the plan's exclusions (default). False: none of them but the practice
        one (see ``practice``): every other trial is kept, time-outs with ``correct`` empty.
    practice : None (default): practice trials are left out or kept as the plan says (the
        shipped plans leave them out); True keeps them, False leaves them out.
    strict : a failed integrity check is a :class:`~crs_study.errors.DatasetError`, not a
        warning.
    include_simulated, responders : which sessions (:func:`~.sources.select_sources`):
        a mixture of simulated and human sessions is refused unless one of these says.

    Returns
    -------
    StudyData
    """
    paths = [Path(datasets)] if isinstance(datasets, str | os.PathLike) else \
        [Path(d) for d in datasets]
    raw = load_datasets(paths, None, strict=strict)
    raw, sources, source_notes = select_sources(raw, include_simulated, responders)
    return _with_plan(raw, sources, tuple(source_notes), tuple(paths), plan, exclude, practice)


def _with_plan(raw: LoadedData, sources: pd.DataFrame, source_notes: tuple[str, ...],
               paths: tuple[Path, ...], plan: str | os.PathLike[str] | AnalysisPlan | None,
               exclude: bool, practice: bool | None) -> StudyData:
    """The sessions chosen (``raw``, every trial as stored) under ``plan``'s exclusions."""
    chosen, plan_path, plan_notes = resolve_plan(raw, plan)
    planned = chosen.exclusions.practice
    leave_out = planned if practice is None else not practice
    loaded = with_exclusions(raw, replace(chosen.exclusions if exclude else NO_EXCLUSIONS,
                                          practice=leave_out))
    notes = [] if exclude else ["the analysis plan's exclusions were not applied "
                                "(load_dataset(exclude=False))"]
    if leave_out != planned:
        notes.append(f"practice trials {'left out' if leave_out else 'kept'}, unlike the "
                     f"analysis plan (load_dataset(practice={practice}))")
    pooled = [n for n in source_notes if "pooled on request" in n]
    warnings = list(loaded.warnings) + pooled + excluded_participants(loaded) + plan_notes \
        + notes
    return StudyData(loaded.analysed, loaded.trials, loaded.sessions, sources, chosen,
                     plan_path, loaded.exclusion_counts, tuple(dict.fromkeys(warnings)),
                     paths, source_notes, raw)


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


def resolve_plan(loaded: LoadedData, plan: str | os.PathLike[str] | AnalysisPlan | None
                 ) -> tuple[AnalysisPlan, Path | None, list[str]]:
    """The plan given, else the one the protocol declares, else the shipped default; its
    file (None for a plan object) and notes on the choice."""
    notes: list[str] = []
    if isinstance(plan, AnalysisPlan):
        return plan, None, notes
    if plan is not None:
        return load_plan(plan), Path(plan), notes
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
