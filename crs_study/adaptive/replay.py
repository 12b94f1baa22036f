"""A session's adaptive tracks, rebuilt from its recorded responses, and their fingerprint.

The state of every procedure is a pure function of the responses it was given (neither
procedure draws a random number), so a resumed session rebuilds its tracks by replaying the
stored rows (:meth:`AdaptiveRun.replay`): each stored level must be the level the replayed
track chooses at that point (else the file was written by other software or altered), and
the fingerprint of the rebuilt state (:meth:`AdaptiveRun.fingerprint`) must equal the one
the sidecar recorded after the same number of trials.

A timed-out trial (no response) counts as an error: the digit was not identified in time.

The columns a row derives from the state after its response (:data:`DERIVED`: the
procedure's estimate, its interval, the reversal and their count) are derived data, so they
are checked by the same replay (:func:`disagreement`): a stored value that is not the
replayed one was forged or written by other software, even when its file's sha256 was
recomputed to match.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from crs_study.adaptive.quest_plus import QuestPlusTrack
from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.adaptive.staircase import Staircase, TrialUpdate
from crs_study.dataset.schema import ADAPTIVE_COLUMNS
from crs_study.errors import SessionError

Track = Staircase | QuestPlusTrack
#: Stored and chosen levels may differ by this much (the file keeps 6 decimals).
LEVEL_TOLERANCE = 1e-6
#: The columns of a row derived from its track's state after the response.
DERIVED = tuple(ADAPTIVE_COLUMNS)
#: Stored and replayed derived values may differ by this much: the file keeps 6 decimals, so
#: a rounding is worth 5e-7, and a last-bit difference of QUEST+'s posterior sums on another
#: machine may move one rounding by a unit of the sixth decimal.
DERIVED_TOLERANCE = 2e-6


def derived_values(update: TrialUpdate) -> dict[str, float | int]:
    """The :data:`DERIVED` columns of the row of ``update`` (NaN estimates: none yet)."""
    return dict(zip(DERIVED, (update.estimate, update.ci_low, update.ci_high,
                              int(update.reversal), update.reversals), strict=True))


def disagreement(update: TrialUpdate, stored: Mapping[str, object]) -> str | None:
    """Which stored derived value is not the replayed one, in words (None when all agree).

    ``stored`` maps columns to the row's values, as text (``n/a`` for none) or numbers (NaN
    for none); a column it lacks is not compared."""
    for column, replayed in derived_values(update).items():
        if column not in stored:
            continue
        value = stored[column]
        try:
            number = math.nan if value in ("n/a", None) else float(value)
        except (TypeError, ValueError):
            number = None
        if number is not None and (math.isnan(number) and math.isnan(replayed)
                                   or abs(number - replayed) <= DERIVED_TOLERANCE):
            continue
        return (f"{column} {value!r} stored, but replaying the recorded levels and responses "
                f"gives {replayed!r}")
    return None


def make_track(spec: AdaptiveSpec, n_choices: int) -> Track:
    """A new track of the block's procedure."""
    if spec.procedure == "staircase":
        return Staircase(spec)
    return QuestPlusTrack(spec, n_choices)


@dataclass(frozen=True)
class RecordedTrial:
    """What replay needs of a stored row: its block, the level shown and the outcome."""

    block: int
    level: float
    correct: bool | None  # None: timed out
    where: str = ""  # how errors name the row (file and row number)


class AdaptiveRun:
    """The tracks of one session, one per block, created on first use."""

    def __init__(self, spec: AdaptiveSpec, n_choices: int) -> None:
        self.spec = spec
        self.n_choices = int(n_choices)
        self.tracks: dict[int, Track] = {}

    def track(self, block: int) -> Track:
        if block not in self.tracks:
            self.tracks[block] = make_track(self.spec, self.n_choices)
        return self.tracks[block]

    def finished(self, block: int) -> bool:
        return self.track(block).finished

    def next_level(self, block: int) -> float:
        return self.track(block).next_level

    def update(self, block: int, correct: bool | None) -> TrialUpdate:
        """Record the outcome of the trial just shown in ``block`` (None counts as wrong)."""
        return self.track(block).update(bool(correct))

    def replay(self, recorded: Iterable[RecordedTrial]) -> list[TrialUpdate]:
        """Feed stored test trials to their tracks, checking each stored level; what each
        did to its track (for :func:`disagreement`)."""
        updates = []
        for row in recorded:
            track = self.track(row.block)
            if track.finished:
                raise SessionError(f"{row.where}: a trial of block {row.block} after its "
                                   f"{self.spec.procedure} finished ({track.trials} trials); "
                                   "the file does not belong to this protocol")
            chosen = track.next_level
            if abs(chosen - row.level) > LEVEL_TOLERANCE:
                raise SessionError(
                    f"{row.where}: level {row.level!r} stored, but replaying the recorded "
                    f"responses the {self.spec.procedure} chooses {chosen!r}; the session was "
                    "recorded by other software or the file was altered: start another "
                    "--session")
            updates.append(track.update(bool(row.correct)))
        return updates

    def state(self) -> dict:
        """The settings and every track that has had a trial: a track is created when it is
        first asked for its level, and a resume asks before it writes the sidecar while
        :func:`crs_study.session.adaptive.rebuild` checks that fingerprint without asking,
        so a track without trials (the fresh state) is left out."""
        return {"spec": repr(self.spec), "n_choices": self.n_choices,
                "blocks": {str(b): t.state() for b, t in sorted(self.tracks.items())
                           if t.trials}}

    def fingerprint(self) -> str:
        """sha256 of the state of every track (responses, levels, reversals, next level,
        estimate) and of the procedure's settings."""
        text = json.dumps(self.state(), sort_keys=True, allow_nan=False)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()
