"""Strict reading of TOML configuration: unknown keys and wrong types are one-line errors.

Shared by device files, protocols, strokes files and analysis plans. Messages name the file,
the key path and the value received, e.g. ``crs2d.toml: geometry.pitch_mm: expected a number
> 0, got -3``; the errors carry them as attributes (:class:`~crs_study.errors.ConfigError`:
``source``, ``key_path``, ``line``). A :class:`Section` given the file's text puts the line of
the key in its errors too (:mod:`crs_study._toml_lines`).

A stray key is named with the valid ones and, when one is close (:func:`difflib.
get_close_matches`), the key it was probably meant to be: ``design: unknown key 'repetiton'
(valid keys: ...); did you mean 'repetitions'?``. A section that declares its keys up front
(``keys=``) reports stray keys before anything else, so a misspelt required key is named as
the stray key it is, not only as a missing one; a section that learns its keys as they are
taken names the close stray key beside the missing one (``missing required key
'repetitions'; is 'repetiton' a misspelling of it?``).

The value checks (:func:`number_problem`, :func:`integer_problem`, :func:`string_problem`)
are also what the protocol's dataclasses check their fields with, so a value refused in a file
and the same value set from Python read alike.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from crs_study._toml_lines import find_line, locate, one_line, syntax_error
from crs_study.errors import ConfigError

#: How alike (difflib's ratio) a stray key and a valid one must be to suggest the valid one
#: (difflib's own default).
CLOSE_MATCH_CUTOFF = 0.6
#: ... and a key present but not yet taken and a missing required key, both ways round, to ask
#: whether the one is the other misspelt. Stricter: the key present may be a valid key read
#: later, and valid keys are alike at times (bootstrap and bootstrap_unit: 0.78;
#: practice_trials and practice_in: 0.77; digit_height_pitch and digit_width_pitch: 0.74, and
#: 0.80 one way round). One edit of a key of 5 or more characters stays at 0.8 or above.
MISSPELLING_CUTOFF = 0.8
#: What a file nested deeper than Python's recursion limit lets tomllib parse is called.
TOO_DEEP = ("not valid here: arrays or tables nested too deeply to read (no file of ours "
            "nests more than a few levels)")


def read_toml(path: str | Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Parse a TOML file; a missing file or a syntax error raises ``error`` in one line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{path}: {TOO_DEEP}") from None


T = TypeVar("T")


def file_version(path: Path, what: str, error: type[ConfigError] = ConfigError) -> int:
    """The modification time (ns) of the regular file ``path``, a cache key for its parsed
    contents; a missing or unreadable file, or a folder, raises ``error`` naming ``what``."""
    try:
        mtime = path.stat().st_mtime_ns
    except FileNotFoundError:
        raise error(f"{path}: no such {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc}") from None
    if not path.is_file():
        raise error(f"{path}: expected a {what}, got a directory")
    return mtime


def parse_toml_file(path: str, what: str, parse: Callable[[dict, str, str], T],
                    error: type[ConfigError] = ConfigError) -> T:
    """``parse(data, path, text)`` of the TOML file ``path``; unreadable bytes, a syntax
    error and any :class:`ConfigError` of ``parse`` raise ``error`` in one line naming the
    file (and the line, where the key has one)."""
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read the {what}: {one_line(exc)}") from None
    data = parse_toml(text, path, error)
    try:
        return parse(data, path, text)
    except ConfigError as exc:
        raise locate(exc, path, text) from None


def parse_toml(text: str, source: str | Path, error: type[ConfigError] = ConfigError
               ) -> dict[str, Any]:
    """Parse TOML ``text`` read from ``source``; a syntax error raises ``error`` naming the
    line (``SOURCE:LINE: not valid TOML: ...``)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise syntax_error(error, source, exc, text) from None
    except RecursionError:  # tomllib recurses once per level of nesting
        raise error(f"{source}: {TOO_DEEP}") from None


def closest_key(key: str, candidates: Iterable[str]) -> str | None:
    """The candidate ``key`` was most probably meant to be, or None when none is close."""
    found = difflib.get_close_matches(key, sorted(candidates), n=1, cutoff=CLOSE_MATCH_CUTOFF)
    return found[0] if found else None


def misspelling_of(key: str, candidates: Iterable[str]) -> str | None:
    """The candidate that may be ``key`` misspelt: alike both ways round (difflib's ratio is
    not symmetric) at :data:`MISSPELLING_CUTOFF` or more; None when none is."""
    def alike(other: str) -> float:
        return min(difflib.SequenceMatcher(None, key, other).ratio(),
                   difflib.SequenceMatcher(None, other, key).ratio())

    scored = sorted((-alike(c), c) for c in candidates)
    return scored[0][1] if scored and -scored[0][0] >= MISSPELLING_CUTOFF else None


def unknown_key_reason(key: str, valid: Iterable[str]) -> str:
    """``unknown key 'x' (valid keys: a, b); did you mean 'a'?`` (the last part when close)."""
    valid = sorted(valid)
    guess = closest_key(key, valid)
    return (f"unknown key {key!r} (valid keys: {', '.join(valid)})"
            + (f"; did you mean {guess!r}?" if guess else ""))


def shown(value: Any, limit: int = 120) -> str:
    """``repr(value)``, cut to ``limit`` characters (a 5000-deep array is named, not echoed)."""
    try:
        text = repr(value)
    except RecursionError:
        text = f"<{type(value).__name__} nested too deeply to show>"
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def number_problem(value: Any, *, minimum: float | None = None, maximum: float | None = None,
                   exclusive_minimum: bool = False) -> str | None:
    """Why ``value`` is not a finite number in range (None when it is)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return f"expected a number, got {shown(value)}"
    value = float(value)
    if not math.isfinite(value):
        return f"expected a finite number, got {shown(value)}"
    if minimum is not None:
        if exclusive_minimum and value <= minimum:
            return f"expected a number > {minimum:g}, got {shown(value)}"
        if not exclusive_minimum and value < minimum:
            return f"expected a number >= {minimum:g}, got {shown(value)}"
    if maximum is not None and value > maximum:
        return f"expected a number <= {maximum:g}, got {shown(value)}"
    return None


def integer_problem(value: Any, *, minimum: int | None = None, maximum: int | None = None
                    ) -> str | None:
    """Why ``value`` is not a whole number in range (None when it is)."""
    if isinstance(value, bool) or not isinstance(value, int):
        return f"expected a whole number, got {shown(value)}"
    if minimum is not None and value < minimum:
        return f"expected a whole number >= {minimum}, got {shown(value)}"
    if maximum is not None and value > maximum:
        return f"expected a whole number <= {maximum}, got {shown(value)}"
    return None


def string_problem(value: Any, *, choices: Iterable[str] | None = None) -> str | None:
    """Why ``value`` is not a string (among ``choices``, when given); None when it is."""
    if not isinstance(value, str):
        return f"expected a string, got {shown(value)}"
    if choices is not None:
        options = list(choices)
        if value not in options:
            return f"expected one of {options}, got {shown(value)}"
    return None


class Section:
    """A view of one TOML table that checks each key as it is taken and rejects leftovers.

    ``source`` names the file and ``path`` the table's dotted key path (empty for the root), so
    messages read ``protocol.toml: stimulus.speed_mm_s: expected ...``. Call :meth:`done` after
    taking every known key: any key left is reported with the list of valid ones.

    ``keys``, when given, declares every key the table may hold: a key outside it is refused
    at once, before any value is read. ``text`` is the file's text: errors then carry the line
    of their key (sub-tables inherit it).
    """

    def __init__(
        self, data: Any, source: str | Path, path: str = "",
        error: type[ConfigError] = ConfigError, *, keys: Iterable[str] | None = None,
        text: str | None = None,
    ) -> None:
        self.source = str(source)
        self.path = path
        self.error = error
        self.text = text
        self.keys = None if keys is None else frozenset(keys)
        if not isinstance(data, Mapping):
            raise self._error(f"expected a table, got {data!r}", path or None)
        self.data = dict(data)
        self._taken: set[str] = set()
        if self.keys is not None:
            stray = sorted(set(self.data) - self.keys)
            if stray:
                raise self._unknown(stray[0], self.keys)

    @property
    def where(self) -> str:
        return f"{self.source}: {self.path}" if self.path else self.source

    def key_path(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def _error(self, reason: str, key_path: str | None, shown_path: str | None = None
               ) -> ConfigError:
        line = find_line(self.text, key_path) if self.text is not None and key_path else None
        return self.error(reason, source=self.source, line=line, key_path=key_path,
                          shown_path=shown_path)

    def _unknown(self, key: str, valid: Iterable[str]) -> ConfigError:
        return self._error(unknown_key_reason(key, valid), self.key_path(key), self.path)

    def fail(self, key: str, message: str) -> ConfigError:
        """An error naming this section's ``key`` (to be raised by the caller)."""
        return self._error(message, self.key_path(key))

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = ...) -> Any:
        self._taken.add(key)
        if key in self.data:
            return self.data[key]
        if default is ...:
            reason = f"missing required key {key!r}"
            if self.keys is None:  # a stray key not yet known as one may be this key misspelt
                guess = misspelling_of(key, set(self.data) - self._taken)
                if guess is not None:
                    reason += f"; is {guess!r} a misspelling of it?"
            raise self._error(reason, self.key_path(key), self.path)
        return default

    def _checked(self, key: str, value: Any, problem: str | None) -> Any:
        if problem is not None:
            raise self.fail(key, problem)
        return value

    def number(
        self,
        key: str,
        default: Any = ...,
        *,
        minimum: float | None = None,
        maximum: float | None = None,
        exclusive_minimum: bool = False,
    ) -> float:
        value = self.raw(key, default)
        problem = number_problem(value, minimum=minimum, maximum=maximum,
                                 exclusive_minimum=exclusive_minimum)
        return float(self._checked(key, value, problem))

    def integer(
        self, key: str, default: Any = ..., *, minimum: int | None = None,
        maximum: int | None = None,
    ) -> int:
        value = self.raw(key, default)
        return self._checked(key, value, integer_problem(value, minimum=minimum,
                                                         maximum=maximum))

    def string(self, key: str, default: Any = ..., *, choices: Iterable[str] | None = None) -> str:
        value = self.raw(key, default)
        return self._checked(key, value, string_problem(value, choices=choices))

    def boolean(self, key: str, default: Any = ...) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"expected true or false, got {shown(value)}")
        return value

    def array(self, key: str, default: Any = ...) -> list[Any]:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.fail(key, f"expected an array, got {shown(value)}")
        return value

    def table(self, key: str, default: Any = ..., *, keys: Iterable[str] | None = None
              ) -> Section:
        value = self.raw(key, default)
        return Section(value, self.source, self.key_path(key), self.error, keys=keys,
                       text=self.text)

    def done(self) -> None:
        """Raise if the table holds keys nobody took (a typo must never pass silently)."""
        extra = sorted(set(self.data) - self._taken - (self.keys or set()))
        if extra:
            raise self._unknown(extra[0], self.keys or self._taken)


def one_line_problem(value: Any) -> str | None:
    """Why ``value`` is not a non-empty one-line string (None when it is)."""
    problem = string_problem(value)
    if problem is None and (not value.strip() or "\n" in value):
        problem = f"expected a non-empty one-line string, got {value!r}"
    return problem


#: Longest file name (one path component) and path every common file system takes (NAME_MAX,
#: PATH_MAX on Linux); a longer value can name no file.
NAME_MAX, PATH_MAX = 255, 4096


def path_problem(value: Any) -> str | None:
    """Why ``value`` is not a one-line string that can name a file (None when it is)."""
    problem = one_line_problem(value)
    if problem is None:
        longest = max(len(part.encode("utf-8", "surrogatepass")) for part in value.split("/"))
        if longest > NAME_MAX or len(value.encode("utf-8", "surrogatepass")) > PATH_MAX:
            problem = (f"expected a file name of at most {NAME_MAX} bytes a component and "
                       f"{PATH_MAX} in all, got {len(value)} characters ({value[:40]!r}...)")
    return problem
