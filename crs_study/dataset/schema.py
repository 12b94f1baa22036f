"""The stored dataset's vocabulary, shared by the runner (writer) and the analysis (reader).

One row per trial in ``sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.tsv``; the
descriptions below become the column dictionary ``task-<task>_beh.json`` (BIDS). Missing values
are written ``n/a``. Times are seconds on the runner's monotonic clock, relative to the
session's start, except response times (seconds from stimulus onset or offset). How a value
is written in a cell (:func:`format_value`) is here too, for every TSV the dataset holds.

A session's stimulus set is recorded as its :class:`Task`: the BIDS task label, what the
task is, and how the symbol shown is named (its column) and written (its labels, the column
dictionary's ``Levels``). The session stage builds it from the protocol's stimulus set
(:func:`crs_study.session.runner.dataset_task`); this stage knows nothing of strokes, so the
analysis, which reads the stored dataset alone, does not either.

Why two names for the symbol's column: a dataset of any stimulus set but the digits names it
``symbol`` (one name for every set, so plans, tools and analyses read any dataset alike; what
the symbols are is told by the task and the column dictionary's ``Levels``); a digit dataset
keeps ``digit`` (and ``digit_height`` for a varied size), the name of every dataset recorded
before stimulus sets existed, so those datasets, their resumed sessions (whose files already
have that header) and every script written against them read new digit datasets exactly as
old ones. :data:`SYMBOL_COLUMNS` lists both; a reader takes the first present
(:func:`symbol_column`). ``response`` holds a symbol of the same set either way. The default
task (:data:`DEFAULT_TASK`, for a writer or a path given none) is the digit set's, the task of
every dataset recorded so far, written out here because the analysis, which reads this
module, may not import the stimuli (pyproject's contract "The analysis reads the stored
dataset alone"); ``tests/test_symbol_sets.py`` checks it is what the digit set
(:mod:`crs_study.stimuli.digits`) records.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from crs_study.dataset.session_metadata import SIDECAR_KEYS, STATUSES
from crs_study.errors import DatasetError

__all__ = ["DEFAULT_TASK", "LEVEL_COLUMNS", "MISSING", "SESSION_KEYS", "SESSION_STATUSES",
           "SYMBOLS", "SYMBOL_COLUMN", "SYMBOL_COLUMNS", "TASK", "TRIAL_COLUMNS", "Task",
           "format_value", "level_columns", "symbol_column", "symbols_are_numbers",
           "trial_column_docs", "trial_columns", "tsv_line"]

MISSING = "n/a"
#: The symbol column of every stimulus set's datasets but the digit set's ...
SYMBOL_COLUMN = "symbol"
#: ... which keeps the name of every dataset recorded before stimulus sets.
DIGIT_COLUMN = "digit"
SYMBOL_COLUMNS = (SYMBOL_COLUMN, DIGIT_COLUMN)
#: The "units" of the symbol and response columns: their levels are the set's symbols.
SYMBOLS = "symbols"


@dataclass(frozen=True)
class Task:
    """What a dataset records about the stimulus set of its sessions.

    ``label``: the BIDS task label (``task-<label>`` in file names, ``TaskName``);
    ``title``: what the sessions are (``"digit identification"``), for the dataset's name;
    ``description``, ``instructions``: the sidecar's ``TaskDescription`` and
    ``Instructions``; ``noun``: one symbol in words, for column descriptions; ``column``: the
    symbol's column (:data:`SYMBOL_COLUMNS`); ``symbols``: the set's symbols as cells hold
    them, in order (the column dictionary's ``Levels``).
    """

    label: str
    title: str
    description: str
    instructions: str
    noun: str
    column: str
    symbols: tuple[str, ...]

    def __post_init__(self) -> None:
        if self.column not in SYMBOL_COLUMNS:
            raise ValueError(f"expected a symbol column {list(SYMBOL_COLUMNS)}, got "
                             f"{self.column!r}")

    def spelled(self, generic: str) -> str:
        """A column in its general spelling (``symbol_height``) as this task names it."""
        return generic.replace(SYMBOL_COLUMN, self.column)


#: The task of a dataset written or read without one named: the digit set's.
DEFAULT_TASK = Task(
    label="digitid", title="digit identification",
    description="Identify the digit drawn by a moving bump on the CRS display",
    instructions=("Rest your fingertips on the display. A bump will draw a digit from 0 to 9; "
                  "press that digit's key as soon as you know it."),
    noun="digit", column=DIGIT_COLUMN, symbols=tuple(str(d) for d in range(10)))
TASK = DEFAULT_TASK.label


def trial_column_docs(task: Task = DEFAULT_TASK) -> dict[str, tuple[str, str]]:
    """Trial columns of a dataset of ``task``, in file order: name -> (description, units or
    levels); the symbol shown is in the task's column."""
    noun, column = task.noun, task.column
    return {
        "trial_index": ("Position of the trial in the session's plan, from 0", "index"),
        "trial_type": ("practice (with feedback, not analysed) or test", "practice|test"),
        "block": ("Block number within the session, from 0", "index"),
        "condition": ("Display condition, e.g. pixel-only or crs", "label"),
        "repetition": (f"Repetition of this {noun} within the condition, from 0", "index"),
        column: (f"{noun.capitalize()} drawn on the display", SYMBOLS),
        "response": (f"{noun.capitalize()} the participant reported; n/a when timed out",
                     SYMBOLS),
        "correct": (f"1 when response equals {column}, else 0 (n/a when timed out)", "0|1"),
        "response_time": ("Time from stimulus onset to the response", "s"),
        "response_time_from_offset": ("Time from stimulus offset to the response; negative "
                                      "when answered before the stimulus ended", "s"),
        "onset": ("Stimulus onset relative to session start", "s"),
        "stimulus_duration": ("Time from the first frame to the end of the last frame's "
                              "period (the stimulus offset: the display then returns to flat)",
                              "s"),
        "timed_out": ("1 when no response came within the protocol's time limit", "0|1"),
        "device_fault": ("1 when a device fault interrupted an earlier attempt of this trial "
                         "(the session stopped and the trial was rerun on resume)", "0|1"),
        "rerun": ("1 when an earlier attempt of this trial was cut short after its stimulus "
                  "began (the pause key, a signal, a device fault or a crash stopped the "
                  "session), so the participant may have felt part of it before this run; the "
                  "cause is in the session sidecar's Interruptions", "0|1"),
        "frames": ("Frames commanded during the stimulus", "count"),
        "late_frames": ("Frames commanded later than one frame period after their due time",
                        "count"),
        "median_wire_latency": ("Median time from a frame's due time to its last byte on the "
                                "wire", "s"),
        "responder": ("Who answered: keypad, scripted, random or observer", "label"),
        "trial_end": ("End of the trial, inter-trial interval included, relative to session "
                      "start (a resumed session continues from the last stored trial_end)", "s"),
    }


def level_columns(task: Task = DEFAULT_TASK) -> dict[str, tuple[str, str]]:
    """The level columns of a dataset of ``task``: name -> (description, units).

    A session whose protocol has a ``[levels]`` table has the varied parameter's column
    right after the symbol's (absent otherwise: BIDS allows extra columns and a constant
    column would suggest a level was varied). Names are those the analysis looks for
    (``crs_study.analysis.plan.KNOWN_LEVEL_COLUMNS``); the protocol key that sets each is in
    ``crs_study.protocol.model.level_parameters``."""
    return {
        task.spelled("symbol_height"): (
            f"Height of the {task.noun}'s box in pixel pitches, varied across trials by the "
            "protocol's [levels] (the width scales with it); only in sessions of such "
            "protocols", "pitch"),
        "stroke_speed": ("Speed of the bump centre along the strokes, varied across trials by "
                         "the protocol's [levels]; only in sessions of such protocols", "mm/s"),
    }


#: The default task's trial columns.
TRIAL_COLUMNS: dict[str, tuple[str, str]] = trial_column_docs()
#: Every level column a dataset may hold, whatever its task: the digit task's spelling
#: (``digit_height``) and every other's (``symbol_height``).
LEVEL_COLUMNS: dict[str, tuple[str, str]] = {
    **level_columns(), "symbol_height": (
        "Height of the symbol's box in pixel pitches, varied across trials by the protocol's "
        "[levels] (the width scales with it); only in sessions of such protocols", "pitch")}


def symbol_column(columns: Iterable[str]) -> str | None:
    """The column of the symbol shown among ``columns`` (the first of :data:`SYMBOL_COLUMNS`
    present), or None."""
    present = set(columns)
    return next((c for c in SYMBOL_COLUMNS if c in present), None)


def symbols_are_numbers(column: str) -> bool:
    """True when a dataset's symbols, in ``column``, are whole numbers: the digit column's (ints
    in every dataset since the first); every other set's symbols are text."""
    return column == DIGIT_COLUMN


#: Columns added after sessions were first written: a session begun without one is resumed
#: without it (its file keeps the columns it began with).
LATER_COLUMNS: tuple[str, ...] = ("rerun",)


#: Adaptive columns: a session whose protocol has an ``[adaptive]`` table records, after the
#: level column, the state of the block's procedure once the trial's response is given
#: (:mod:`crs_study.adaptive`); n/a on practice trials, which no procedure sees.
ADAPTIVE_COLUMNS: dict[str, tuple[str, str]] = {
    "adaptive_estimate": ("The block's threshold estimate after this trial, in the level's "
                          "units: the level at the protocol's target rate (QUEST+: posterior "
                          "mean; staircase: mean of the last reversals on its scale); n/a "
                          "before there is one", "as the level column"),
    "adaptive_ci_low": ("Lower end of the estimate's 95 % interval (QUEST+: posterior "
                        "quantile; staircase: Student t over the last reversals)",
                        "as the level column"),
    "adaptive_ci_high": ("Upper end of the estimate's 95 % interval", "as the level column"),
    "adaptive_reversal": ("1 when this trial's response reversed the track's direction "
                          "(the staircase's reversal levels are these trials' levels)", "0|1"),
    "adaptive_reversals": ("Reversals of the block's track so far, this trial included",
                           "count"),
}


def trial_columns(level_column: str | None = None, symbol: str = DIGIT_COLUMN,
                  adaptive: bool = False) -> tuple[str, ...]:
    """A session TSV's columns: the trial columns with the symbol in ``symbol`` (one of
    :data:`SYMBOL_COLUMNS`), ``level_column`` right after it and, for an adaptive protocol,
    :data:`ADAPTIVE_COLUMNS` after that."""
    if symbol not in SYMBOL_COLUMNS:
        raise ValueError(f"expected a symbol column {list(SYMBOL_COLUMNS)}, got {symbol!r}")
    names = [symbol if n == DIGIT_COLUMN else n for n in TRIAL_COLUMNS]
    if level_column is None:
        if adaptive:
            raise ValueError("adaptive columns need the level column")
        return tuple(names)
    if level_column not in LEVEL_COLUMNS:
        raise ValueError(f"expected a level column {sorted(LEVEL_COLUMNS)}, got {level_column!r}")
    at = names.index(symbol) + 1
    names[at:at] = [level_column, *(ADAPTIVE_COLUMNS if adaptive else ())]
    return tuple(names)


#: Session sidecar keys (``..._beh.json``), in written order, and the statuses a session
#: has: :class:`crs_study.dataset.session_metadata.SessionMetadata` owns the sidecar's format.
SESSION_KEYS: tuple[str, ...] = SIDECAR_KEYS
SESSION_STATUSES: tuple[str, ...] = STATUSES


def format_value(value: Any) -> str:
    """A TSV cell: ``n/a`` for missing, 0/1 for booleans, floats to the microsecond."""
    if value is None:
        return MISSING
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        if not math.isfinite(value):
            return MISSING
        text = f"{value:.6f}"
        return "0.000000" if text == "-0.000000" else text
    text = str(value)
    if any(c in text for c in "\t\n\r"):
        raise DatasetError(f"a TSV value may not contain tabs or newlines: {text!r}")
    return text


def tsv_line(values: Sequence[Any]) -> str:
    return "\t".join(format_value(v) for v in values) + "\n"
