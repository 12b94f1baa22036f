"""A protocol written back as TOML: the loader's inverse, for protocols changed in Python.

A :class:`~crs_study.protocol.model.Protocol` changed with :func:`dataclasses.replace` keeps
the text and sha256 of the file it was read from, which no longer describe it; a session
stores the protocol's text and resumes only under the same sha256. So before such a protocol
runs, :func:`protocol_to_toml` writes its fields as a protocol file, and
:func:`crs_study.protocol.loader.load_protocol` reads that text back as it reads any file
(every check, the device's included). Reading the text gives the same protocol:
``load(protocol_to_toml(p))`` equals ``p`` field for field (a property test holds it).

The text is written here, not by a TOML library, because its bytes are a fingerprint: a
session begun from a changed protocol resumes only if the same protocol is written to the
same bytes, whatever library versions are installed then (as the trial plan draws only
``Generator.random()`` so that numpy's sampling algorithms cannot change a plan).

What is written, table by table, in the loader's key order (``table_keys``: the keys naming
symbols spelled by the protocol's stimulus set, ``digits`` or ``symbols``):

* ``stimulus.set`` first, and only for a set other than the default (the digits), so a digit
  protocol is written as before stimulus sets; a set file relative to the protocol's folder;

* a value of ``None`` is left out (the loader's default for that key is ``None``);
* ``stimulus.offset_mm`` only with ``placement = "offset"``; the parameter ``[levels]``
  varies (and the width, ``digit_width_pitch`` for digits, with a varied height) is left
  out of ``[stimulus]``,
  as the loader asks;
* ``conditions.prompts`` as a table, left out when there is none;
* a device file and a strokes file relative to the protocol's folder (the loader resolves
  them from there), a built-in device by its name;
* a header comment: the sha256 of the text the protocol was read from and the keys that
  differ from it (``design.repetitions``), or that it was built in Python.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import fields
from pathlib import Path
from typing import Any

from crs_study.adaptive.spec import AdaptiveSpec
from crs_study.errors import ProtocolError
from crs_study.geometry.layout import BUILTIN_DEVICES
from crs_study.protocol.model import Protocol, table_keys
from crs_study.stimuli.sets import DEFAULT_SET, shipped_sets

#: ``[study]`` keys whose Protocol field has another name.
STUDY_FIELDS = {"id": "study_id"}

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def protocol_to_toml(protocol: Protocol) -> str:
    """The protocol file whose loading gives ``protocol`` (see the module docstring)."""
    tables = protocol_tables(protocol)
    lines = _header(protocol, tables)
    for name, table in tables.items():
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        lines += ["", f"[{name}]"]
        lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items()
                  if k not in nested]
        for key, sub in nested.items():
            lines += ["", f"[{name}.{toml_key(key)}]"]
            lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in sub.items()]
    return "\n".join(lines) + "\n"


def protocol_tables(protocol: Protocol) -> dict[str, dict[str, Any]]:
    """The protocol's tables as the loader reads them: ``{table: {key: value}}``, the keys
    spelled by the protocol's stimulus set (``digits``, ``symbols``; :func:`table_keys`)."""
    folder = protocol.path.parent
    set_name = protocol.stimulus.set_name
    keys_of = table_keys(set_name)

    def table(name: str, spec: Any) -> dict[str, Any]:
        names = [f.name for f in fields(spec) if f.name != "set_name" or name == "stimulus"]
        return dict(zip(keys_of[name], (getattr(spec, n) for n in names), strict=True))

    study = {key: getattr(protocol, STUDY_FIELDS.get(key, key)) for key in keys_of["study"]}
    if study["device"] not in BUILTIN_DEVICES:
        study["device"] = _relative(study["device"], folder)
    stimulus = table("stimulus", protocol.stimulus)
    chosen = stimulus.pop("set")  # first, as it spells the other keys; absent for the default
    if chosen != DEFAULT_SET:
        stimulus = {"set": chosen if chosen in shipped_sets() else _relative(chosen, folder),
                    **stimulus}
    if stimulus.get("strokes_file") is not None:
        stimulus["strokes_file"] = _relative(stimulus["strokes_file"], folder)
    if stimulus.get("placement") != "offset":
        stimulus.pop("offset_mm", None)
    for key in _varied(protocol):
        stimulus.pop(key, None)
    conditions: dict[str, Any] = {"names": protocol.conditions}
    if protocol.condition_prompts:
        conditions["prompts"] = dict(protocol.condition_prompts)
    tables = {
        "study": study, "stimulus": stimulus, "conditions": conditions,
        "design": table("design", protocol.design),
        "responses": table("responses", protocol.responses),
    }
    if protocol.adaptive is not None:
        tables["adaptive"] = adaptive_table(protocol.adaptive)
    elif protocol.levels is not None:
        tables["levels"] = table("levels", protocol.levels)
    return {name: {k: v for k, v in table.items() if v is not None}
            for name, table in tables.items()}


def adaptive_table(spec: AdaptiveSpec) -> dict[str, Any]:
    """The ``[adaptive]`` table of ``spec`` (its procedure's sub-table nested, None left
    out)."""
    attributes = {"min": "minimum", "max": "maximum"}
    table = {key: getattr(spec, attributes.get(key, key)) for key in table_keys()["adaptive"]}
    for name in ("staircase", "quest_plus"):
        sub = table.pop(name)
        if sub is not None:
            table[name] = {f.name: getattr(sub, f.name) for f in fields(sub)}
    return {k: v for k, v in table.items() if v is not None}


def changed_keys(before: dict[str, Any], after: dict[str, Any], prefix: str = "") -> list[str]:
    """Key paths whose values differ between two parsed TOML documents (numbers compared as
    numbers, arrays as lists), in ``after``'s order, then the keys only ``before`` has."""
    found = []
    for key in [*after, *(k for k in before if k not in after)]:
        path = f"{prefix}{key}"
        old, new = before.get(key), after.get(key)
        if isinstance(old, dict) and isinstance(new, dict):
            found += changed_keys(old, new, f"{path}.")
        elif _plain(old) != _plain(new):
            found.append(path)
    return found


def toml_key(key: str) -> str:
    """A bare key when TOML allows one, else a quoted key."""
    return key if _BARE_KEY.fullmatch(key) else toml_string(key)


def toml_value(value: Any) -> str:
    """A TOML value: a string, boolean, integer, float or array of them."""
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)  # the shortest text that reads back as the same double
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML value for {value!r}")


def toml_string(text: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for char in text:
        if char in '"\\':
            out.append("\\" + char)
        elif char < " " or char == "\x7f":
            out.append(f"\\u{ord(char):04x}")
        elif "\ud800" <= char <= "\udfff":
            raise ProtocolError(f"expected text a file can hold, got {text!r} (a lone "
                                "surrogate)")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'


def _header(protocol: Protocol, tables: dict[str, dict[str, Any]]) -> list[str]:
    try:
        before = tomllib.loads(protocol.text) if protocol.text else None
    except tomllib.TOMLDecodeError:
        before = None
    if before is None:
        return ["# Written by crs-study from a protocol built in Python."]
    changed = changed_keys(before, _plain(tables))
    return ["# Written by crs-study (crs_study.protocol.protocol_to_toml) from the protocol",
            f"# of sha256 {protocol.sha256};",
            "# changed in Python: " + (", ".join(changed) if changed else "no key") + "."]


def _varied(protocol: Protocol) -> tuple[str, ...]:
    """The ``[stimulus]`` keys a ``[levels]`` table sets (the loader refuses them there)."""
    levels = protocol.levels
    if levels is None:
        return ()
    if levels.varies_size:
        return (levels.parameter, protocol.stimulus.file_key("symbol_width_pitch"))
    return (levels.parameter,)


def _relative(path: str, folder: Path) -> str:
    """``path`` relative to ``folder`` where it can be (absolute on another drive)."""
    try:
        return Path(os.path.relpath(path, folder)).as_posix()
    except ValueError:
        return str(Path(path).resolve())


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value
