"""Stimulus sets: the symbols a study shows, their strokes, response keys and task, by name.

A :class:`StimulusSet` is everything about *what* is identified that the rest of the pipeline
needs, so no other module knows which symbols they are:

* ``symbols``: the set's alphabet, in order (what a protocol may show and a participant may
  answer), with a :class:`~crs_study.stimuli.strokes.Glyph` (strokes in a unit box) for each
  symbol that has strokes;
* ``keys``: each symbol's default response key at the keypad (a single printable character,
  never a pause key: p, P, q, Q, Escape);
* ``task``, ``title``, ``description``, ``instructions``: the BIDS task label of its datasets
  (``task-<task>_beh.tsv``), what the dataset is called, the sidecar's ``TaskDescription``
  and the participant's ``Instructions``;
* ``screens``: the rest of what the participant reads at the keypad
  (:class:`~crs_study.stimuli.screens.ScreenTexts`, English unless the set file's
  ``[set.screens]`` translates it);
* ``noun``: one symbol in words (``"letter"``), for messages and column descriptions;
* ``column``: the dataset column that holds the symbol shown. Every set read from a set file
  uses ``symbol``; the digit set keeps ``digit``, the name every dataset recorded before
  stimulus sets uses (:mod:`crs_study.stimuli.digits`). The protocol keys that name symbols
  are spelled with it too (``symbols``, ``symbol_height_pitch``, ``symbol_width_pitch``,
  ``max_same_symbol_run``; the digit set: ``digits``, ``digit_height_pitch``, ...), see
  :meth:`StimulusSet.spelled`;
* :attr:`~StimulusSet.chance_rate`: 1 / the number of symbols (guessing among all of them).

A set file (TOML, ``format = 2``; the shipped ``crs_study/data/letters.toml`` documents it)
holds a ``[set]`` table (name, noun, task, title, description, instructions, and an optional
``[set.screens]``) and one
``[symbols.NAME]`` table per symbol with its response ``key`` and its ``strokes``
(:func:`crs_study.stimuli.strokes.read_strokes`). Reading is strict: every problem is a
one-line :class:`~crs_study.errors.ProtocolError` naming the file, the line and the key.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

from crs_study._toml import Section, file_version, parse_toml_file, string_problem
from crs_study.errors import ProtocolError
from crs_study.stimuli.screens import FIELDS, ScreenTexts
from crs_study.stimuli.strokes import Glyph, Symbol, read_strokes, sized_glyphs

#: Format number of a set file (format 1 is the digit set's strokes-only file).
SET_FORMAT = 2
#: The dataset column of the symbol shown, for every set but the digit set.
SYMBOL_COLUMN = "symbol"
#: Keys that pause a session at the keypad, so no set or protocol may use them as answers:
#: p pauses in place, q and Escape end the session safely for a later resume.
PAUSE_KEYS = frozenset({"p", "P", "q", "Q", "\x1b"})
#: What a dataset cell may not hold: "n/a" is BIDS' missing value.
MISSING = "n/a"
#: Longest symbol label.
MAX_LABEL = 20

_NAME_RE = re.compile(r"[a-z][a-z0-9_-]*")
_NOUN_RE = re.compile(r"[a-z][a-z -]*[a-z]")
_TASK_RE = re.compile(r"[A-Za-z0-9]+")
_SET_KEYS = ("name", "noun", "task", "title", "description", "instructions", "screens")


def spell(generic: str, column: str) -> str:
    """A protocol key or dataset column in its general spelling (``symbol_height_pitch``) as
    a set whose column is ``column`` spells it (``digit_height_pitch``)."""
    return generic.replace(SYMBOL_COLUMN, column)


@dataclass(frozen=True, eq=False)
class StimulusSet:
    """A named set of symbols (module docstring). Build one with
    :func:`crs_study.stimuli.sets.load_stimulus_set` (by name or set file)."""

    name: str
    noun: str
    column: str
    task: str
    title: str
    description: str
    instructions: str
    symbols: tuple[Symbol, ...]
    glyphs: Mapping[Symbol, Glyph]
    keys: Mapping[Symbol, str]
    source: str = ""
    #: what the participant reads at the keypad, in the set's language
    screens: ScreenTexts = field(default_factory=ScreenTexts)

    @property
    def plural(self) -> str:
        """Several symbols in words (``"letters"``)."""
        return f"{self.noun}s"

    @property
    def chance_rate(self) -> float:
        """Accuracy of guessing among every symbol of the set: 1 / the number of symbols."""
        return 1.0 / len(self.symbols)

    def spelled(self, generic: str) -> str:
        """A protocol key or dataset column as this set spells it: ``symbol`` in the generic
        name becomes :attr:`column` (``symbol_height_pitch`` -> ``digit_height_pitch`` for
        the digit set; unchanged for the others)."""
        return spell(generic, self.column)

    def symbol_of(self, text: str) -> Symbol | None:
        """The symbol written ``text`` (in a dataset cell, a script, a key map), or None."""
        return {str(s): s for s in self.symbols}.get(str(text))

    def glyph(self, symbol: Symbol) -> Glyph:
        """The strokes of ``symbol``; a :class:`ProtocolError` when it has none."""
        if symbol not in self.glyphs:
            raise ProtocolError(f"{self.noun} {symbol!r} has no strokes in {self.source}",
                                key_path=f"stimulus.{self.spelled('symbols')}")
        return self.glyphs[symbol]

    def describe(self, symbols: Iterable[Symbol] | None = None, to: str = " to ") -> str:
        """The symbols in words, runs of 3 or more consecutive characters as ``first<to>last``
        (``"0 to 9"``; ``"0-9"`` with ``to="-"``; ``"A to P, R to Z"``)."""
        labels = [str(s) for s in (self.symbols if symbols is None else symbols)]
        parts: list[str] = []
        run: list[str] = []

        def flush() -> None:
            parts.extend([f"{run[0]}{to}{run[-1]}"] if len(run) >= 3 else run)
            run.clear()

        for label in labels:
            if run and not (len(label) == len(run[-1]) == 1 and ord(label) == ord(run[-1]) + 1):
                flush()
            run.append(label)
        flush()
        return ", ".join(parts)


def symbol_problem(label: str) -> str | None:
    """Why ``label`` cannot name a symbol (None when it can): it is written in dataset cells,
    scripts and BIDS level names, so it is short, printable and without spaces."""
    if not label or len(label) > MAX_LABEL or not label.isprintable() \
            or any(c.isspace() for c in label) or label == MISSING:
        return (f"expected a symbol name of 1 to {MAX_LABEL} printable characters without "
                f"spaces (not {MISSING!r}), got {label!r}")
    return None


def key_problem(key: object) -> str | None:
    """Why ``key`` cannot be a response key (None when it can)."""
    if not isinstance(key, str) or len(key) != 1 or not key.isprintable() or key == " ":
        return f"expected a single printable character, got {key!r}"
    if key in PAUSE_KEYS:
        return (f"{key!r} pauses the session at the keypad (p pauses; q, Q and Escape end "
                "it); choose another")
    return None


@lru_cache(maxsize=16)
def _load_cached(path: str, mtime_ns: int) -> StimulusSet:
    return parse_toml_file(path, "set file", _parse, ProtocolError)


def load_set_file(path: str | Path) -> StimulusSet:
    """Read a set file (module docstring), strictly; cached per file and modification time."""
    path = Path(path)
    return _load_cached(str(path), file_version(path, "stimulus set file", ProtocolError))


def _one_line(section: Section, key: str) -> str:
    value = section.raw(key)
    problem = string_problem(value)
    if problem is None and (not value.strip() or "\n" in value):
        problem = f"expected a non-empty one-line string, got {value!r}"
    if problem is not None:
        raise section.fail(key, problem)
    return value


def _matching(section: Section, key: str, pattern: re.Pattern[str], what: str) -> str:
    value = _one_line(section, key)
    if not pattern.fullmatch(value):
        raise section.fail(key, f"expected {what}, got {value!r}")
    return value


def _parse(data: dict, source: str, text: str) -> StimulusSet:
    root = Section(data, source, error=ProtocolError, keys=("format", "set", "symbols"),
                   text=text)
    version = root.integer("format")
    if version != SET_FORMAT:
        raise root.fail("format", f"expected {SET_FORMAT} (a stimulus set file), got "
                        f"{version!r}")
    head = root.table("set", keys=_SET_KEYS)
    name = _matching(head, "name", _NAME_RE, "a lower-case name (letters, digits, _ or -)")
    noun = _matching(head, "noun", _NOUN_RE, "one symbol in lower-case words, e.g. 'letter'")
    task = _matching(head, "task", _TASK_RE, "a BIDS task label (letters and digits)")
    title, description, instructions = (_one_line(head, k) for k in _SET_KEYS[3:6])
    screens = ScreenTexts.from_section(head.table("screens", {}, keys=FIELDS)) \
        if head.has("screens") else ScreenTexts()
    head.raw("screens", None)
    head.done()
    table = root.table("symbols")
    keys: dict[str, str] = {}

    def read_key(symbol: str, entry: Section) -> None:
        key = entry.raw("key")
        problem = key_problem(key)
        if problem is None and key in keys.values():
            twin = next(s for s, k in keys.items() if k == key)
            problem = f"the key {key!r} already answers {twin!r}; expected one key per symbol"
        if problem is not None:
            raise entry.fail("key", problem)
        keys[symbol] = key

    strokes_of = read_strokes(table, symbol_problem, ("key",), read_key)
    root.done()
    if len(strokes_of) < 2:
        raise root.fail("symbols", f"expected at least 2 symbols to choose from, got "
                        f"{list(strokes_of)}")
    glyphs = sized_glyphs(strokes_of, root, "symbols", noun)
    return StimulusSet(name=name, noun=noun, column=SYMBOL_COLUMN, task=task, title=title,
                       description=description, instructions=instructions,
                       symbols=tuple(glyphs), glyphs=glyphs, keys=keys, source=source,
                       screens=screens)
