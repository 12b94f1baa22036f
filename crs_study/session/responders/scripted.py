"""Responses read from a file: for tests, demonstrations and replaying a known session.

File format (UTF-8 text), one line per trial in plan order (line k answers trial k; blank
lines and lines starting with ``#`` are skipped; a first line ``symbol<TAB>rt``, or
``digit<TAB>rt``, is a header)::

    7            the symbol 7 (a digit), answered 0.5 s after the stimulus offset (the default)
    3<TAB>1.25   the symbol 3, answered 1.25 s after the stimulus offset
    n/a          no answer: a time-out

A symbol is written as the dataset writes it (``7`` for a digit, ``C`` for a letter) and must
be one of the protocol's stimulus set (the default set's when the script is read without
one).

The second column, when present, is the response time in seconds **from stimulus offset**
(so a script does not depend on stimulus durations); it may be negative (an answer during the
stimulus) but not before the onset. Because line k belongs to trial k, a resumed session
continues with the right line.
"""

from __future__ import annotations

import math
from pathlib import Path

from crs_study.clock import Clock
from crs_study.dataset.schema import MISSING, SYMBOL_COLUMNS
from crs_study.errors import ConfigError, SessionError
from crs_study.protocol.plan import PlannedTrial
from crs_study.session.responders.base import Responder, Response, StimulusRecord, respond_at
from crs_study.stimuli.sets import default_set
from crs_study.stimuli.strokes import Symbol
from crs_study.stimuli.symbol_set import StimulusSet

DEFAULT_RT_AFTER_OFFSET_S = 0.5


def parse_script(text: str, source: str = "<script>", symbol_set: StimulusSet | None = None
                 ) -> list[tuple[Symbol | None, float]]:
    """Lines of a response script as ``(symbol or None, rt from offset)`` pairs; the
    symbols are those of ``symbol_set`` (the default set when None)."""
    symbol_set = symbol_set if symbol_set is not None else default_set()
    column = symbol_set.column
    headers = [[c] for c in SYMBOL_COLUMNS] + [[c, "rt"] for c in SYMBOL_COLUMNS]
    entries: list[tuple[Symbol | None, float]] = []
    lines = text.splitlines()
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        if not entries and [f.lower() for f in fields] in headers:
            continue  # header
        if len(fields) > 2:
            raise ConfigError(f"{source}:{number}: expected '{column}' or '{column}<TAB>rt', "
                              f"got {raw!r}")
        label = fields[0]
        symbol = None if label == MISSING else symbol_set.symbol_of(label)
        if label != MISSING and symbol is None:
            raise ConfigError(f"{source}:{number}: expected a {symbol_set.noun} "
                              f"{symbol_set.describe(to='-')} or {MISSING}, got {label!r}")
        rt = DEFAULT_RT_AFTER_OFFSET_S
        if len(fields) == 2:
            try:
                rt = float(fields[1])
            except ValueError:
                raise ConfigError(f"{source}:{number}: expected a response time in seconds, "
                                  f"got {fields[1]!r}") from None
            if not math.isfinite(rt):
                raise ConfigError(f"{source}:{number}: response time must be finite, "
                                  f"got {fields[1]!r}")
        entries.append((symbol, rt))
    return entries


class ScriptedResponder(Responder):
    """Answers trial k with line k of a script (see the module docstring)."""

    name = "scripted"

    def __init__(self, path: str | Path, symbol_set: StimulusSet | None = None) -> None:
        self.path = Path(path)
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError(f"scripted responses: no such file {str(self.path)!r}") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"scripted responses: cannot read {str(self.path)!r}: "
                              f"{exc}") from None
        self.entries = parse_script(text, str(self.path), symbol_set)

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        if trial.index >= len(self.entries):
            raise SessionError(f"scripted responses {str(self.path)!r} have "
                               f"{len(self.entries)} entries; trial {trial.index} needs one more")
        symbol, after_offset = self.entries[trial.index]
        if symbol is not None and symbol not in stimulus.symbol_choices:
            raise SessionError(f"scripted responses {str(self.path)!r}: entry {trial.index + 1} "
                               f"answers {symbol!r}, not one of {stimulus.symbol_choices}")
        rt = max(0.0, stimulus.duration_s + after_offset)
        if symbol is None:
            limit = time_limit_s if time_limit_s is not None else after_offset
            deadline = max(0.0, stimulus.duration_s + limit)
            clock.sleep_until(stimulus.onset_time + deadline)
            return Response(None, deadline)
        return respond_at(clock, stimulus, rt, time_limit_s, symbol)
