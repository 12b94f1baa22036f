"""Adaptive trials in a session: the block's procedure chooses the level, resume replays it.

A protocol with ``[adaptive]`` plans its test trials without a level
(:func:`crs_study.protocol.plan.make_plan`); when one comes, :func:`choose` asks the block's
track (:class:`crs_study.adaptive.AdaptiveRun`) for the level, or skips the trial when the
track has finished (a staircase stopped by its reversals): a skipped trial is never shown
nor stored, so a session's rows are the plan's trials minus the skipped ones, in order.

:func:`rebuild` makes the tracks of a stored session by replaying its rows in plan order:
every stored level must be the one the replayed track chooses, every trial missing from the
file must be one its finished track skips, and after the sidecar's ``TrialsCompleted`` rows
the state's fingerprint must be the sidecar's ``AdaptiveStateSha256``, and each row's
derived columns (the estimate, its interval, the reversals) the replayed ones (a forged
estimate with a recomputed ``TrialsSha256`` is refused here). Anything else is a
one-line :class:`~crs_study.errors.SessionError`: the file is not what this software and
protocol would have written.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from crs_study.adaptive import AdaptiveRun, RecordedTrial, TrialUpdate
from crs_study.adaptive.replay import derived_values, disagreement
from crs_study.dataset.schema import ADAPTIVE_COLUMNS
from crs_study.dataset.session_metadata import SessionMetadata
from crs_study.errors import SessionError
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import PlannedTrial, TrialPlan


def adaptive_run(protocol: Protocol) -> AdaptiveRun | None:
    """Fresh tracks for ``protocol`` (None when it has no ``[adaptive]`` table)."""
    if protocol.adaptive is None:
        return None
    return AdaptiveRun(protocol.adaptive, len(protocol.symbols))


def is_adaptive(trial: PlannedTrial, run: AdaptiveRun | None) -> bool:
    """A test trial whose level the block's procedure chooses."""
    return run is not None and trial.trial_type == "test"


def choose(trial: PlannedTrial, run: AdaptiveRun | None) -> PlannedTrial | None:
    """``trial`` with its level chosen by its block's track, itself when it is not adaptive,
    None when its track has finished (the trial is skipped)."""
    if not is_adaptive(trial, run):
        return trial
    if run.finished(trial.block):
        return None
    return replace(trial, level=run.next_level(trial.block))


def next_to_play(plan: TrialPlan, rows: list[dict[str, str]], run: AdaptiveRun | None) -> int:
    """The plan index of the next trial to play after the stored ``rows`` (``len(rows)``
    unless finished staircases skip trials; ``len(plan.trials)`` when none is left)."""
    k = int(rows[-1]["trial_index"]) + 1 if rows else 0
    while k < len(plan.trials) and is_adaptive(plan.trials[k], run) \
            and run.finished(plan.trials[k].block):
        k += 1
    return k


def row_fields(update: TrialUpdate | None) -> dict[str, object]:
    """The adaptive columns of a row (None for a practice trial, written n/a)."""
    if update is None:
        return dict.fromkeys(ADAPTIVE_COLUMNS)
    return derived_values(update)


def _correct(row: dict[str, str]) -> bool | None:
    value = row.get("correct", "n/a")
    return None if value == "n/a" else value == "1"


def rebuild(protocol: Protocol, plan: TrialPlan, rows: list[dict[str, str]],
            stored: SessionMetadata | None, tsv: Path, sidecar: Path, *,
            complete: bool = False) -> AdaptiveRun | None:
    """The tracks after the stored ``rows`` (see the module docstring).

    ``complete``: the session is marked complete, so every planned trial after the last row
    must be one a finished track skips."""
    run = adaptive_run(protocol)
    if run is None:
        return None
    column = protocol.levels.column
    by_index = {int(row["trial_index"]): (k, row) for k, row in enumerate(rows)}
    last = int(rows[-1]["trial_index"]) if rows else -1
    checked_at = stored.trials_completed if stored is not None and \
        stored.adaptive_state_sha256 is not None else None
    done = 0
    if checked_at == 0:
        _check_fingerprint(run, stored, sidecar)
    for trial in plan.trials if complete else plan.trials[:last + 1]:
        found = by_index.get(trial.index)
        if not is_adaptive(trial, run):
            if found is None:
                raise SessionError(f"{tsv}: trial {trial.index} ({trial.trial_type}) is "
                                   "missing; the file does not belong to this plan")
        elif found is None:
            if not run.finished(trial.block):
                raise SessionError(
                    f"{tsv}: trial {trial.index} is missing but the {protocol.adaptive.procedure}"
                    f" of block {trial.block} had not finished; the file does not belong to "
                    "this plan")
            continue
        else:
            k, row = found
            try:
                level = float(row[column])
            except (KeyError, ValueError):
                raise SessionError(f"{tsv}: row {k + 1} has no {column} level "
                                   f"({row.get(column)!r})") from None
            [update] = run.replay([RecordedTrial(trial.block, level, _correct(row),
                                                 f"{tsv}: row {k + 1}")])
            forged = disagreement(update, row)
            if forged is not None:
                raise SessionError(f"{tsv}: row {k + 1}: {forged}; the session was recorded "
                                   "by other software or the file was altered: start another "
                                   "--session")
        done += 1
        if done == checked_at:
            _check_fingerprint(run, stored, sidecar)
    return run


def _check_fingerprint(run: AdaptiveRun, stored: SessionMetadata, sidecar: Path) -> None:
    now = run.fingerprint()
    if now != stored.adaptive_state_sha256:
        raise SessionError(
            f"{sidecar}: cannot resume: the adaptive procedures' state after "
            f"{stored.trials_completed} trials differs (AdaptiveStateSha256 stored "
            f"{stored.adaptive_state_sha256!r}, replayed {now!r}); the session was recorded "
            "by other software: use the original software or start another --session")
