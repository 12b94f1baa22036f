"""Where a key is in a TOML text: the line locator behind ``FILE:LINE: key: ...`` messages.

Loaders raise :class:`~crs_study.errors.ConfigError` s that carry the key path at fault
(``key_path``); :func:`locate` adds the file and the line of that key in the text read, so no
message is ever parsed for its key path or line. :func:`find_line` works on the text alone
(tomllib keeps no positions): it walks the lines, follows table headers and (dotted, quoted)
keys, and skips whole values that span lines, so their contents never pass for keys.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import TypeVar

from crs_study.errors import ConfigError

E = TypeVar("E", bound=ConfigError)


def locate(error: E, source: str | Path, text: str) -> E:
    """Set ``error``'s file (when it has none) and its line: that of its ``key_path`` in
    ``text`` (:func:`find_line`), when it names none yet. Returns ``error`` (to raise)."""
    if error.source is None:
        error.source = str(source)
    if error.line is None and error.key_path and error.source == str(source):
        error.line = find_line(text, error.key_path)
    return error


def syntax_line(error: tomllib.TOMLDecodeError, text: str = "") -> int | None:
    """The line a TOML syntax error is on: ``error.lineno`` where tomllib gives it (Python
    3.14+), else the ``(at line N, column M)`` that tomllib's own message ends with; the last
    line of ``text`` for an error at the end of the document."""
    line = getattr(error, "lineno", None)
    if isinstance(line, int):
        return line
    reason = one_line(error)
    match = re.search(r"\(at line (\d+), column \d+\)$", reason)
    if match:
        return int(match.group(1))
    if reason.endswith("(at end of document)") and text:
        return max(1, len(text.splitlines()))
    return None


def syntax_error(kind: type[E], source: str | Path, error: tomllib.TOMLDecodeError,
                 text: str = "") -> E:
    """``SOURCE:LINE: not valid TOML: ...`` as an error of class ``kind``."""
    return kind(f"not valid TOML: {one_line(error)}", source=str(source),
                line=syntax_line(error, text))


def toml_syntax_message(source: str | Path, error: tomllib.TOMLDecodeError, text: str = ""
                        ) -> str:
    """The message of :func:`syntax_error` (``SOURCE:LINE: not valid TOML: ...``)."""
    return str(syntax_error(ConfigError, source, error, text))


def one_line(error: BaseException) -> str:
    """An exception's message on one line (runs of white space made one space)."""
    return " ".join(str(error).split())


def find_line(text: str, key_path: str) -> int | None:
    """1-based line of ``key_path`` (``design.repetitions``, ``stimulus.digits[2]``,
    ``digits.3.strokes[0][5]``) in a TOML text: the line where the indexed array element
    starts (for a path ending in indices), else the key's own line, else its table's
    header, else None. Keys may be bare, quoted or dotted (``a.b = 1``); values spanning
    several lines (arrays, strings) are skipped whole, so their contents never pass for
    keys or headers."""
    trailing = re.search(r"((?:\[\d+\])+)$", key_path)
    indices = [int(i) for i in re.findall(r"\[(\d+)\]", trailing.group(1))] if trailing else []
    parts = re.sub(r"\[\d+\]", "", key_path).split(".")
    table: list[str] = []
    best: int | None = None
    position = 0
    while True:
        position = _skip_blank(text, position)
        if position >= len(text):
            return best
        number = text.count("\n", 0, position) + 1
        end = text.find("\n", position)
        end = len(text) if end < 0 else end
        header = _HEADER.match(text, position, end)
        if header:
            table = _key_names(header.group(1))
            if table == parts:
                return number
            if best is None and (table == parts[: len(table)]
                                 or table[: len(parts)] == parts):
                best = number  # the key's table, or the first table inside it
            position = end
            continue
        key = _KEY.match(text, position, end)
        if not key:
            position = end  # not a key line (a TOML error elsewhere): go on
            continue
        names = table + _key_names(key.group(1))
        if names == parts:
            element = _element_line(text, key.end(), indices) if indices else None
            return element or number
        if len(parts) > len(names) and names == parts[: len(names)]:
            best = number  # a key inside an inline table
        position = _skip_value(text, _skip_blank(text, key.end()))


_NAME = r"""(?:"[^"\n]*"|'[^'\n]*'|[A-Za-z0-9_\-]+)"""
_DOTTED = rf"{_NAME}(?:[ \t]*\.[ \t]*{_NAME})*"
_HEADER = re.compile(rf"\[\[?[ \t]*({_DOTTED})[ \t]*\]\]?")
_KEY = re.compile(rf"({_DOTTED})[ \t]*=")


def _key_names(dotted: str) -> list[str]:
    return [n.strip("\"'") for n in re.findall(_NAME, dotted)]


def _element_line(text: str, position: int, indices: list[int]) -> int | None:
    """Line where the array element ``value[i][j]..`` starts, the value beginning at
    ``position`` (just after ``=``); None when the value has no such element."""
    for index in indices:
        position = _skip_blank(text, position)
        if position >= len(text) or text[position] != "[":
            return None
        position += 1
        for _ in range(index):
            position = _skip_blank(text, position)
            if position >= len(text) or text[position] == "]":
                return None
            position = _skip_blank(text, _skip_value(text, position))
            if position >= len(text) or text[position] != ",":
                return None
            position += 1
        position = _skip_blank(text, position)
        if position >= len(text) or text[position] == "]":
            return None
    return text.count("\n", 0, position) + 1


def _skip_blank(text: str, position: int) -> int:
    """Past spaces, newlines and comments."""
    while position < len(text):
        char = text[position]
        if char in " \t\r\n":
            position += 1
        elif char == "#":
            end = text.find("\n", position)
            position = len(text) if end < 0 else end + 1
        else:
            break
    return position


def _skip_value(text: str, position: int) -> int:
    """Past one TOML value (an array or inline table with everything inside, a string, or a
    bare token) starting at ``position``."""
    depth = 0
    while position < len(text):
        char = text[position]
        if char in "\"'":
            quote = text[position:position + 3] if text[position:position + 3] in \
                ('"""', "'''") else char
            position += len(quote)
            while position < len(text) and not text.startswith(quote, position):
                position += 2 if char == '"' and text[position] == "\\" else 1
            position += len(quote)
            if depth == 0:
                return position
            continue
        if char == "#":
            if depth == 0:
                return position
            position = _skip_blank(text, position)
            continue
        if char in "[{":
            depth += 1
        elif char in "]}":
            if depth == 0:
                return position
            depth -= 1
            if depth == 0:
                return position + 1
        elif char == "," and depth == 0:
            return position
        elif char == "\n" and depth == 0:
            return position
        position += 1
    return position
