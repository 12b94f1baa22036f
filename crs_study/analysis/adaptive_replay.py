"""The adaptive columns of a dataset, checked and recomputed by replaying each session's tracks.

A session of a protocol with ``[adaptive]`` stores, on each test trial, the level its block's
procedure chose and the procedure's state after the response: its threshold estimate, the
estimate's 95 % interval, whether the response was a reversal and how many there were
(``crs_study.dataset.schema.ADAPTIVE_COLUMNS``). Those columns are derived data: neither
procedure draws a random number, so the state after every trial is a pure function of the
protocol's ``[adaptive]`` table (kept in the sidecar's ``Protocol`` text) and the levels and
responses before it. :func:`replay_adaptive` replays every session's tracks from its levels
and ``correct`` column (:class:`crs_study.adaptive.AdaptiveRun`, as a resume does) and
compares each stored value with the replayed one.

A disagreement means the file was edited after the session (its ``TrialsSha256`` recomputed
to match) or written by other software: a problem naming the file, the row and the column
(a :class:`~crs_study.errors.DatasetError` with ``strict``, else a warning), and the replayed
values replace the stored ones, as a ``correct`` that disagrees with the response is
recomputed, so a forged estimate never reaches the thresholds. A level that is not the one
the replayed procedure chooses is a problem of the same kind; that session's columns are then
left as stored (its tracks cannot be replayed past it).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from crs_study.adaptive import AdaptiveRun, RecordedTrial
from crs_study.adaptive.replay import DERIVED, derived_values, disagreement
from crs_study.adaptive.spec import spec_from_table
from crs_study.analysis.thresholds import ADAPTIVE_MARKER, design_from_protocol
from crs_study.errors import CrsStudyError


def replay_adaptive(trials: pd.DataFrame, sessions: list[dict], files: list[Path]
                    ) -> tuple[pd.DataFrame, list[str]]:
    """``trials`` with the adaptive columns of every adaptive session replayed, and one
    problem per session whose stored values disagree (module docstring).

    ``trials`` is the loader's typed table with ``_file`` (the index of the session in
    ``sessions`` and ``files``) and ``_row`` (the line of the trial file).
    """
    if ADAPTIVE_MARKER not in trials:
        return trials, []
    trials = trials.copy()
    problems = []
    for number, session in enumerate(sessions):
        rows = trials.index[(trials["_file"] == number) & (trials["trial_type"] == "test")]
        protocol = session.get("Protocol")
        if len(rows) == 0 or (_adaptive_table(protocol) is None
                              and trials.loc[rows, ADAPTIVE_MARKER].isna().all()):
            continue  # not an adaptive session
        problem = _replay_session(trials, rows, protocol, files[number])
        if problem is not None:
            problems.append(problem)
    return trials, problems


def _adaptive_table(text: object) -> dict | None:
    try:
        table = tomllib.loads(text).get("adaptive") if isinstance(text, str) else None
    except (tomllib.TOMLDecodeError, RecursionError):
        return None
    return table if isinstance(table, dict) else None


def _replay_session(trials: pd.DataFrame, rows: pd.Index, protocol: object, path: Path
                    ) -> str | None:
    """Replay one session's test rows in place; what disagreed (None when all agree)."""
    table = _adaptive_table(protocol)
    if table is None:
        return (f"{path}: adaptive estimates, but no recorded protocol (the sidecar's "
                "Protocol) with an [adaptive] table to replay them with: they are unchecked")
    try:
        stimulus = tomllib.loads(protocol).get("stimulus", {})
        symbols = stimulus.get("digits", stimulus.get("symbols"))
        run = AdaptiveRun(spec_from_table(table), len(symbols))
        column = design_from_protocol(protocol).level_column
    except (CrsStudyError, KeyError, TypeError, ValueError, AttributeError) as exc:
        return (f"{path}: the recorded protocol's [adaptive] table cannot be replayed "
                f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); its "
                "adaptive columns are unchecked")
    order = trials.loc[rows].sort_values("trial_index")
    first, count = None, 0
    for index, row in order.iterrows():
        where = f"{path}: row {int(row['_row'])}"
        correct = None if pd.isna(row["correct"]) else bool(row["correct"])
        try:
            [update] = run.replay([RecordedTrial(int(row["block"]), float(row[column]),
                                                 correct, where)])
        except (CrsStudyError, KeyError, TypeError, ValueError) as exc:
            return f"{str(exc).splitlines()[0]} (possible tampering)"
        stored = {c: row[c] for c in DERIVED if c in row.index}
        problem = disagreement(update, stored)
        if problem is not None:
            first = first or f"{where}: {problem}"
            count += 1
        for name, value in derived_values(update).items():
            if name in trials:
                trials.at[index, name] = value if np.isfinite(value) else np.nan
    if first is None:
        return None
    return (f"{first} ({count} such row(s) in the file; possible tampering); the adaptive "
            "columns are recomputed by replay")
