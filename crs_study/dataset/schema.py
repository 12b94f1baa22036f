"""The stored dataset's vocabulary, shared by the runner (writer) and the analysis (reader).

One row per trial in ``sub-<id>/ses-<n>/beh/sub-<id>_ses-<n>_task-<task>_beh.tsv``; the
descriptions below become the column dictionary ``task-<task>_beh.json`` (BIDS). Missing values
are written ``n/a``. Times are seconds on the runner's monotonic clock, relative to the
session's start, except response times (seconds from stimulus onset or offset). How a value
is written in a cell (:func:`format_value`) is here too, for every TSV the dataset holds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from crs_study.dataset.session_metadata import SIDECAR_KEYS, STATUSES
from crs_study.errors import DatasetError

TASK = "digitid"
MISSING = "n/a"

#: Trial columns in file order: name -> (description, units or levels)
TRIAL_COLUMNS: dict[str, tuple[str, str]] = {
    "trial_index": ("Position of the trial in the session's plan, from 0", "index"),
    "trial_type": ("practice (with feedback, not analysed) or test", "practice|test"),
    "block": ("Block number within the session, from 0", "index"),
    "condition": ("Display condition, e.g. pixel-only or crs", "label"),
    "repetition": ("Repetition of this digit within the condition, from 0", "index"),
    "digit": ("Digit drawn on the display", "0-9"),
    "response": ("Digit the participant reported; n/a when timed out", "0-9"),
    "correct": ("1 when response equals digit, else 0 (n/a when timed out)", "0|1"),
    "response_time": ("Time from stimulus onset to the response", "s"),
    "response_time_from_offset": ("Time from stimulus offset to the response; negative when "
                                  "answered before the stimulus ended", "s"),
    "onset": ("Stimulus onset relative to session start", "s"),
    "stimulus_duration": ("Time from the first frame to the end of the last frame's period "
                          "(the stimulus offset: the display then returns to flat)", "s"),
    "timed_out": ("1 when no response came within the protocol's time limit", "0|1"),
    "device_fault": ("1 when a device fault interrupted an earlier attempt of this trial "
                     "(the session stopped and the trial was rerun on resume)", "0|1"),
    "rerun": ("1 when an earlier attempt of this trial was cut short after its stimulus "
              "began (the pause key, a signal, a device fault or a crash stopped the session), "
              "so the participant may have felt part of it before this run; the cause is in "
              "the session sidecar's Interruptions", "0|1"),
    "frames": ("Frames commanded during the stimulus", "count"),
    "late_frames": ("Frames commanded later than one frame period after their due time",
                    "count"),
    "median_wire_latency": ("Median time from a frame's due time to its last byte on the wire",
                            "s"),
    "responder": ("Who answered: keypad, scripted, random or observer", "label"),
    "trial_end": ("End of the trial, inter-trial interval included, relative to session start "
                  "(a resumed session continues from the last stored trial_end)", "s"),
}

#: Level columns: a session whose protocol has a ``[levels]`` table has the varied
#: parameter's column right after ``digit`` (absent otherwise: BIDS allows extra columns and a
#: constant column would suggest a level was varied). Names are those the analysis looks for
#: (``crs_study.analysis.plan.KNOWN_LEVEL_COLUMNS``); the protocol key that sets each is in
#: ``crs_study.protocol.LEVEL_PARAMETERS``.
LEVEL_COLUMNS: dict[str, tuple[str, str]] = {
    "digit_height": ("Height of the digit's box in pixel pitches, varied across trials by "
                     "the protocol's [levels] (the width scales with it); only in sessions of "
                     "such protocols", "pitch"),
    "stroke_speed": ("Speed of the bump centre along the strokes, varied across trials by the "
                     "protocol's [levels]; only in sessions of such protocols", "mm/s"),
}


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


def trial_columns(level_column: str | None = None, adaptive: bool = False
                  ) -> tuple[str, ...]:
    """A session TSV's columns: :data:`TRIAL_COLUMNS`, with ``level_column`` after ``digit``
    and, for an adaptive protocol, :data:`ADAPTIVE_COLUMNS` after it."""
    names = list(TRIAL_COLUMNS)
    if level_column is None:
        if adaptive:
            raise ValueError("adaptive columns need the level column")
        return tuple(names)
    if level_column not in LEVEL_COLUMNS:
        raise ValueError(f"expected a level column {sorted(LEVEL_COLUMNS)}, got {level_column!r}")
    at = names.index("digit") + 1
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
