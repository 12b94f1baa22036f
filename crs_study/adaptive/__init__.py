"""Adaptive procedures: a staircase or QUEST+ chooses each trial's digit size or speed.

- :mod:`~crs_study.adaptive.spec`: the protocol's ``[adaptive]`` table
  (:class:`AdaptiveSpec`) and every level a procedure can show;
- :mod:`~crs_study.adaptive.staircase`: up/down staircases with PsychoPy's rules;
- :mod:`~crs_study.adaptive.quest_plus`: QUEST+ through the ``questplus`` package;
- :mod:`~crs_study.adaptive.replay`: a session's tracks rebuilt from its recorded responses,
  and the fingerprint a resume checks.
"""

from crs_study.adaptive.quest_plus import QuestPlusDesign, QuestPlusEngine, QuestPlusTrack
from crs_study.adaptive.replay import AdaptiveRun, RecordedTrial, Track, make_track
from crs_study.adaptive.spec import (
    EASIER,
    PROCEDURES,
    RULE_TARGETS,
    RULES,
    SCALES,
    AdaptiveSpec,
    QuestPlusSpec,
    StaircaseSpec,
    round_level,
)
from crs_study.adaptive.staircase import Staircase, TrialUpdate

__all__ = [
    "EASIER", "PROCEDURES", "RULES", "RULE_TARGETS", "SCALES", "AdaptiveRun", "AdaptiveSpec",
    "QuestPlusDesign", "QuestPlusEngine", "QuestPlusSpec", "QuestPlusTrack", "RecordedTrial",
    "Staircase", "StaircaseSpec", "Track", "TrialUpdate", "make_track", "round_level",
]
