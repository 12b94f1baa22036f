"""A session's adaptive tracks, rebuilt from its recorded responses, and their fingerprint.

The state of every procedure is a pure function of the responses it was given (neither
procedure draws a random number), so a resumed session rebuilds its tracks by replaying the
stored rows (:meth:`AdaptiveRun.replay`): each stored level must be the level the replayed
track chooses at that point (else the file was written by other software or altered), and
the fingerprint of the rebuilt state (:meth:`AdaptiveRun.fingerprint`) must equal the one
the sidecar recorded after the same number of trials.

A timed-out trial (no response) counts as an error: the digit was not identified in time.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import dataclass

from crs_study.adaptive.quest_plus import QuestPlusTrack
from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.adaptive.staircase import Staircase, TrialUpdate
from crs_study.errors import SessionError

Track = Staircase | QuestPlusTrack
#: Stored and chosen levels may differ by this much (the file keeps 6 decimals).
LEVEL_TOLERANCE = 1e-6


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

    def replay(self, recorded: Iterable[RecordedTrial]) -> None:
        """Feed stored test trials to their tracks, checking each stored level."""
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
            track.update(bool(row.correct))

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
