"""What the participant reads on the keypad's screen, in the stimulus set's language.

The participant's screens are the instruction (the set's ``instructions``) and the lines of
:class:`ScreenTexts`: the stimulus playing, the call to answer and its countdown, the answer
received, the feedback of a practice trial, a key that answers nothing, the waits for the
experimenter, a break's rest and its end, the end of practice, the pause and the thanks at
the end. Each has an English default; a set file translates any of them in its optional
``[set.screens]`` table (``crs_study/data/letters.toml`` lists the keys), so a lab that runs
the study in another language copies the set file and translates its texts. The
experimenter's lines stay in English.

Texts may hold the fields named in :data:`FIELDS` (``{seconds}``, ``{symbol}``, ...); a field
a text may not use, a key that is not a screen, and a text that is not one non-empty line are
one-line errors naming the key.
"""

from __future__ import annotations

import string
from dataclasses import dataclass, fields

from crs_study._toml import Section, string_problem


@dataclass(frozen=True)
class ScreenTexts:
    """The participant's screen texts (module docstring), English by default."""

    stimulus: str = "Stimulus playing: feel the shape"
    answer: str = "ANSWER NOW: press the key of what you felt"
    time_left: str = "{seconds} s left to answer"
    no_answer: str = "No answer in time"
    received: str = "Answer received: {key}"
    correct: str = "correct"
    wrong: str = "{answer} is wrong: it was {symbol}"
    too_late: str = "no answer in time: it was {symbol}"
    unmapped: str = "the key {key} answers nothing here: press one of {keys}"
    wait: str = "Waiting for the experimenter"
    rest: str = "Break: rest {time} left"
    rest_over: str = "Break over: continue when ready"
    practice_over: str = "Practice is over: now the test begins, without feedback"
    paused: str = "PAUSED: please wait, the session goes on soon"
    thank_you: str = "Thank you! The session is complete."

    @classmethod
    def from_section(cls, section: Section) -> ScreenTexts:
        """The texts of a set file's ``[set.screens]`` table (every key optional; the
        section is made with ``keys=FIELDS``, so a stray key is refused with the valid
        ones)."""
        texts = {}
        for name in FIELDS:
            if not section.has(name):
                continue
            value = section.raw(name)
            problem = string_problem(value)
            if problem is None and (not value.strip() or "\n" in value):
                problem = f"expected a non-empty one-line string, got {value!r}"
            if problem is None:
                problem = _field_problem(value, FIELDS[name])
            if problem is not None:
                raise section.fail(name, problem)
            texts[name] = value
        section.done()
        return cls(**texts)


#: The fields each text may use.
FIELDS: dict[str, tuple[str, ...]] = {f.name: () for f in fields(ScreenTexts)}
FIELDS.update(time_left=("seconds",), received=("key",), wrong=("answer", "symbol"),
              too_late=("symbol",), unmapped=("key", "keys"), rest=("time",))


def _field_problem(text: str, allowed: tuple[str, ...]) -> str | None:
    """Why ``text`` cannot be filled in with ``allowed`` fields (None when it can)."""
    try:
        used = [name for _, name, _, _ in string.Formatter().parse(text) if name is not None]
    except ValueError as exc:
        return f"expected a text with {{field}} placeholders, got {text!r} ({exc})"
    wrong = [name for name in used if name not in allowed]
    if wrong:
        may = ", ".join("{" + name + "}" for name in allowed) or "no field"
        return f"the field {{{wrong[0]}}} is not known here (this text may use {may}), " \
               f"got {text!r}"
    return None
