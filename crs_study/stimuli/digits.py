"""The digit set: the digits 0 to 9, the default stimulus set and the paper's experiment.

Everything digit-specific is here; the rest of the pipeline sees a
:class:`~crs_study.stimuli.symbol_set.StimulusSet` (:func:`digit_set`):

* symbols: the ints 0 to 9 (as every dataset and session recorded so far holds them);
* strokes: the shipped ``crs_study/data/digits.toml`` (documented there: unit box, x right,
  y up, strokes in drawing order) or a protocol's own file (``stimulus.strokes_file``) in the
  same format, 1; sizing and motion are :mod:`crs_study.stimuli.strokes`'s. The shipped
  digits have W = 0.8913 and H = 0.9958 (:func:`~crs_study.stimuli.strokes.mean_extent`);
* response keys: the keys 0 to 9 of a keypad;
* dataset column ``digit`` and BIDS task ``digitid``: the names every dataset recorded before
  stimulus sets uses, so those datasets load, analyse and resume as they always did; the
  protocol keys are spelled with it (``digits``, ``digit_height_pitch``,
  ``digit_width_pitch``, ``max_same_digit_run``).

Loading a strokes file is strict: every problem is a one-line
:class:`~crs_study.errors.ProtocolError` naming the file, the line of the offending key or
array element (``my_digits.toml:42: digits.3.strokes[0][5]: ...``), the key path and the
value.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from crs_study._toml import Section, file_version, parse_toml_file
from crs_study.errors import ProtocolError
from crs_study.paths import data_dir
from crs_study.stimuli.strokes import (  # noqa: F401 - the digit module's names since v1
    Glyph,
    arc_lengths,
    frames_for_stroke,
    mean_extent,
    point_at,
    read_strokes,
    resample_by_arc_length,
    sample_stroke,
    sized_glyphs,
)
from crs_study.stimuli.symbol_set import StimulusSet

#: Format number of the strokes file this module reads.
STROKES_FORMAT = 1
#: The digit set's name (the default set: a protocol without ``stimulus.set`` shows digits).
NAME = "digits"
#: One digit in words; also the dataset column and the stem of the protocol keys.
NOUN = COLUMN = "digit"
#: The BIDS task label of digit datasets.
TASK = "digitid"
TITLE = "digit identification"
DESCRIPTION = "Identify the digit drawn by a moving bump on the CRS display"
INSTRUCTIONS = ("Rest your fingertips on the display. A bump will draw a digit from 0 to 9; "
                "press that digit's key as soon as you know it.")
#: The digits, and how a strokes file names them.
DIGITS = tuple(range(10))
DIGIT_NAMES = tuple(str(d) for d in DIGITS)

#: A digit's strokes (the generic glyph; its ``symbol`` is the digit).
Digit = Glyph


def shipped_strokes_path() -> Path:
    """The strokes file that ships with the package."""
    return data_dir() / "digits.toml"


def digit_set(strokes_file: str | Path | None = None) -> StimulusSet:
    """The digit set, with the strokes of ``strokes_file`` (the shipped ones when None).

    One object per strokes file and modification time, so protocols that show the same set
    compare equal and share the caches of their stimuli."""
    path = Path(strokes_file) if strokes_file is not None else shipped_strokes_path()
    load_digits(path)  # the file's errors, one line each
    return _digit_set(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=16)
def _digit_set(path: str, mtime_ns: int) -> StimulusSet:
    return StimulusSet(name=NAME, noun=NOUN, column=COLUMN, task=TASK, title=TITLE,
                       description=DESCRIPTION, instructions=INSTRUCTIONS, symbols=DIGITS,
                       glyphs=_load_cached(path, mtime_ns), keys={d: str(d) for d in DIGITS},
                       source=path)


@lru_cache(maxsize=16)
def _load_cached(path: str, mtime_ns: int) -> dict[int, Glyph]:
    return parse_toml_file(path, "strokes file", _parse, ProtocolError)


def load_digits(path: str | Path | None = None) -> dict[int, Glyph]:
    """Read a strokes file (the shipped one when ``path`` is None), strictly.

    Returns a dict digit -> :class:`~crs_study.stimuli.strokes.Glyph`. Cached per file and
    modification time. Errors name the file and the line: ``PATH:LINE: digits.3.strokes[0][5]:
    expected ...``.
    """
    path = Path(path) if path is not None else shipped_strokes_path()
    return _load_cached(str(path), file_version(path, "strokes file", ProtocolError))


def _parse(data: dict, source: str, text: str | None = None) -> dict[int, Glyph]:
    root = Section(data, source, error=ProtocolError, keys=("format", "digits"), text=text)
    version = root.integer("format")
    if version != STROKES_FORMAT:
        raise root.fail("format", f"expected {STROKES_FORMAT}, got {version!r}")
    strokes_of = read_strokes(root.table("digits"), _digit_name)
    root.done()
    if not strokes_of:
        raise root.fail("digits", "expected at least one digit, got none")
    return sized_glyphs({int(k): v for k, v in sorted(strokes_of.items())}, root, "digits",
                        NOUN)


def _digit_name(name: str) -> str | None:
    """Why ``name`` names no digit (None when it does)."""
    return None if name in DIGIT_NAMES else f"expected a digit 0 to 9 as the key, got {name!r}"
