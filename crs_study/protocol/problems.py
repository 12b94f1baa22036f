"""Every problem of a protocol file in one reading, not one per run.

Reading a protocol stops at its first error (:func:`~crs_study.protocol.load_protocol`): the
model is built table by table, and a value it cannot hold leaves nothing to build on. To list
every error, :func:`protocol_problems` reads the file again and again, each time after
repairing the key at fault in the parsed data (never in the file): a stray key is dropped (or
read under the key it is a misspelling of), a bad element of an array is dropped, and any
other bad or missing value takes the value of the shipped protocol of the same stimulus set
(or is dropped when that protocol has none, so an optional key falls back to its default).
Once the file reads, the device checks run
(:func:`~crs_study.protocol.feasibility.check_feasibility`), which report every check that
fails.

A repair can cause an error of its own (a list of symbols with one dropped no longer matches
the response keys). An error that names a repaired key, in its key path or in its message
(every message names the keys it concerns), or a string element dropped, is such a
consequence and is not reported; the repairs go on. The first problem listed is always the
one loading the file raises.
"""

from __future__ import annotations

import copy
import hashlib
import os
import re
import tomllib
from typing import Any

from crs_study._toml import parse_toml
from crs_study._toml_lines import one_line
from crs_study.errors import ConfigError, ProtocolError
from crs_study.paths import resolve_protocol, shipped_file
from crs_study.protocol.feasibility import check_feasibility
from crs_study.protocol.loader import load_protocol, protocol_from_dict
from crs_study.protocol.model import Protocol

#: The shipped protocol whose values repair a protocol of each shipped stimulus set.
REFERENCES = {"letters": "protocols/letter_identification.toml"}
DEFAULT_REFERENCE = "protocols/digit_identification.toml"
#: Readings at most (a protocol with more errors than this lists the first ones).
MAX_READINGS = 100

_INDEX = re.compile(r"^(?P<base>.+)\[(?P<index>\d+)\]$")
_MEANT = re.compile(r"did you mean '(?P<key>[^']+)'\?")


def protocol_problems(source: str | os.PathLike[str] | Protocol) -> tuple[ProtocolError, ...]:
    """Every problem found in the protocol ``source`` (a file, a shipped protocol's name or
    a :class:`Protocol`), in the order found; empty when it loads and passes every device
    check. See the module docstring for how one reading goes on past an error."""
    try:
        load_protocol(source)
        return ()
    except ProtocolError as error:
        first = error
    if isinstance(source, Protocol):  # changed in Python: no file to read again
        return (first,)
    path = resolve_protocol(source)
    try:
        raw = path.read_bytes()
        text = raw.decode("utf-8")
        data = parse_toml(text, str(path), ProtocolError)
    except (OSError, UnicodeDecodeError, ConfigError):
        return (first,)  # unreadable, or not TOML: nothing past the first error to read
    sha256 = hashlib.sha256(raw).hexdigest()
    reference = _reference(data)
    problems: list[ProtocolError] = []
    repaired: list[str] = []
    dropped: list[str] = []
    protocol = None
    for _ in range(MAX_READINGS):
        try:
            protocol = protocol_from_dict(data, path, text, sha256)
            break
        except ProtocolError as error:  # protocol_from_dict's errors are all of this kind
            if not _follows_from(error, repaired, dropped) and not _seen(error, problems):
                problems.append(error)
            if error.key_path is None or error.key_path in repaired or \
                    not _repair(data, error, reference, dropped):
                break  # nothing left to repair: the rest cannot be read
            repaired.append(error.key_path)
    if protocol is not None:
        for finding in check_feasibility(protocol).errors:
            error = ProtocolError(finding.message, source=str(path), line=finding.line,
                                  key_path=finding.key_path)
            if not _follows_from(error, repaired, dropped) and not _seen(error, problems):
                problems.append(error)
    if not problems or str(problems[0]) != str(first):
        problems = [first] + [p for p in problems if str(p) != str(first)]
    return tuple(problems)


def _reference(data: dict) -> dict:
    """The parsed shipped protocol of the same stimulus set (the digits' by default)."""
    stimulus = data.get("stimulus")
    name = stimulus.get("set") if isinstance(stimulus, dict) else None
    text = shipped_file(REFERENCES.get(name, DEFAULT_REFERENCE)).read_text(encoding="utf-8")
    return tomllib.loads(text)


def _parts(key_path: str) -> list[str | int]:
    """``levels.values[2]`` -> ``["levels", "values", 2]``."""
    parts: list[str | int] = []
    for part in key_path.split("."):
        match = _INDEX.match(part)
        if match:
            parts += [match["base"], int(match["index"])]
        else:
            parts.append(part)
    return parts


def _lookup(data: Any, parts: list[str | int]) -> tuple[bool, Any]:
    for part in parts:
        if isinstance(part, int):
            if not isinstance(data, list) or part >= len(data):
                return False, None
        elif not isinstance(data, dict) or part not in data:
            return False, None
        data = data[part]
    return True, data


def _repair(data: dict, error: ProtocolError, reference: dict, dropped: list[str]) -> bool:
    """Change ``data`` so that reading it again gets past ``error``; False when it cannot.
    The ``repr`` of a string element dropped from an array is added to ``dropped``."""
    parts = _parts(error.key_path)
    found, parent = _lookup(data, parts[:-1])
    if not found or not isinstance(parent, dict | list):
        return False
    key = parts[-1]
    if isinstance(key, int):  # a bad element of an array: without it
        value = parent.pop(key)
        if isinstance(value, str):  # quoted, it names what it belongs to (a prompt's key)
            dropped.append(repr(value))
        return True
    if error.reason.startswith("unknown key"):
        value = parent.pop(key, None)
        meant = _MEANT.search(error.reason)  # a misspelling: read under the key it means
        if meant is not None and meant["key"] not in parent:
            parent[meant["key"]] = value
        return True
    known, value = _lookup(reference, parts)
    if known and isinstance(parent, dict):
        if parent.get(key, object()) == value:
            return False  # the reference's own value fails here: no repair helps
        parent[key] = copy.deepcopy(value)
        return True
    if isinstance(parent, dict) and key in parent:
        del parent[key]  # optional: its default
        return True
    return False


def _follows_from(error: ProtocolError, repaired: list[str], dropped: list[str]) -> bool:
    """True when ``error`` concerns a key already repaired (its path or its message) or
    names an array element dropped."""
    if any(value in error.reason for value in dropped):
        return True
    for key in repaired:
        base = _INDEX.sub(r"\g<base>", key)
        if error.key_path is not None and (error.key_path in (key, base) or
                                           error.key_path.startswith(base + "[")):
            return True
        if re.search(rf"(?<![\w.]){re.escape(base)}(?![\w])", error.reason):
            return True
    return False


def _seen(error: ProtocolError, problems: list[ProtocolError]) -> bool:
    return any(one_line(p) == one_line(error) for p in problems)

