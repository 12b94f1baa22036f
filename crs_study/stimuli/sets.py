"""The stimulus sets by name: the shipped ones, a lab's own set file, and the default set.

``load_stimulus_set("digits")`` is the digit set (:mod:`crs_study.stimuli.digits`, the
default: a protocol without ``stimulus.set`` shows digits); ``load_stimulus_set("letters")``
the shipped capital letters (``crs_study/data/letters.toml``, where the choice of letters is
explained); any other value is the path of a set file (``format = 2``,
:mod:`crs_study.stimuli.symbol_set`). A protocol names its set in ``[stimulus] set = ...``
(a path relative to the protocol file).
"""

from __future__ import annotations

from pathlib import Path

from crs_study.errors import ProtocolError
from crs_study.paths import data_dir, is_name
from crs_study.stimuli import digits
from crs_study.stimuli.symbol_set import StimulusSet, load_set_file

#: The set a protocol shows when it names none.
DEFAULT_SET = digits.NAME
#: The shipped sets read from set files: name -> file in ``crs_study/data``.
SHIPPED_SET_FILES = {"letters": "letters.toml"}


def shipped_sets() -> tuple[str, ...]:
    """The names of the shipped sets, the default first."""
    return (DEFAULT_SET, *SHIPPED_SET_FILES)


def load_stimulus_set(name_or_path: str | Path = DEFAULT_SET,
                      strokes_file: str | Path | None = None) -> StimulusSet:
    """A shipped set by name, or a set file by path (module docstring).

    ``strokes_file`` replaces the digit set's strokes (a format-1 file: the digit set's own
    knob, ``stimulus.strokes_file``); another set brings its strokes in its own file.
    """
    text = str(name_or_path)
    if text == DEFAULT_SET:
        return digits.digit_set(strokes_file)
    if strokes_file is not None:
        raise ProtocolError(f"a strokes file replaces the {DEFAULT_SET} set's strokes; the "
                            f"set {text!r} brings its own (copy its set file, edit it and "
                            "name the copy in stimulus.set)", key_path="stimulus.strokes_file")
    if text in SHIPPED_SET_FILES:
        return load_set_file(data_dir() / SHIPPED_SET_FILES[text])
    if is_name(text):
        raise ProtocolError(f"{text!r} is not a shipped stimulus set (shipped: "
                            f"{', '.join(shipped_sets())}); give the path of a set file",
                            key_path="stimulus.set")
    return load_set_file(text)


def set_column(name_or_path: str | Path = DEFAULT_SET) -> str:
    """The dataset column (and key stem) of a set (:attr:`StimulusSet.column`), without reading
    the default set's strokes."""
    return digits.COLUMN if str(name_or_path) == DEFAULT_SET else \
        load_stimulus_set(name_or_path).column


def default_set() -> StimulusSet:
    """The default set (the digits, with the shipped strokes)."""
    return load_stimulus_set(DEFAULT_SET)
