"""Protocol files: TOML read strictly into the model, then checked on the device.

A protocol is a TOML file with five tables (``protocols/README.md`` documents every key):
``[study]`` (id, version, device, consent form, analysis plan), ``[stimulus]`` (the stimulus
set, its symbols shown, their size in pixel pitches, the bump, stroke speed, placement, frame
rate), ``[conditions]``
(registered display conditions and the experimenter's prompt for each), ``[design]``
(repetitions, blocking, counterbalancing, run constraint, practice, breaks, inter-trial
interval) and ``[responses]`` (keys, time limit, feedback). An optional ``[levels]`` table
varies one stimulus parameter across trials (a psychometric study,
:class:`~crs_study.protocol.model.LevelSpec`); an optional ``[adaptive]`` table lets a
staircase or QUEST+ choose it trial by trial instead
(:class:`~crs_study.adaptive.spec.AdaptiveSpec`).

Reading is strict (:mod:`crs_study._toml`): each table declares its keys
(:func:`~crs_study.protocol.model.table_keys`, spelled by the stimulus set named in
``stimulus.set``, which is read first), so a stray key is refused first, named with
the valid ones and the closest (``design: unknown key 'repetiton' (valid keys: ...); did you
mean 'repetitions'?``); missing keys, wrong types and out-of-range values (checked by the
model's dataclasses) are one-line :class:`~crs_study.errors.ProtocolError` s naming the file,
the line where the key is found, the key path and the value. This module adds what needs the
file's folder or two tables at once: the device file, set file and strokes file the protocol
names, a response key per symbol (the set's own keys when ``responses.keys`` is left out),
prompts only where blocks start. Then :func:`load_protocol` checks
the protocol against its device (:mod:`crs_study.protocol.feasibility`) and notes odd but
legal values (:mod:`crs_study.protocol.odd_values`).
"""

from __future__ import annotations

import hashlib
import os
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

from crs_study._toml import Section, parse_toml, path_problem
from crs_study._toml_lines import locate, one_line
from crs_study.adaptive.spec import AdaptiveSpec, QuestPlusSpec, StaircaseSpec
from crs_study.errors import ConfigError, ProtocolError
from crs_study.geometry.layout import BUILTIN_DEVICES
from crs_study.paths import resolve_protocol
from crs_study.protocol.feasibility import check_on_device
from crs_study.protocol.model import (
    OPTIONAL_KEYS,
    PLACEMENTS,
    DesignSpec,
    LevelSpec,
    Protocol,
    ResponseSpec,
    StimulusSpec,
    adaptive_levels,
    table_keys,
)
from crs_study.protocol.odd_values import protocol_warnings, warning_findings
from crs_study.protocol.writer import protocol_to_toml
from crs_study.stimuli.sets import DEFAULT_SET, load_stimulus_set, shipped_sets
from crs_study.stimuli.symbol_set import StimulusSet, spell


def load_protocol(source: str | os.PathLike[str] | Protocol, *,
                  check_device: bool = True) -> Protocol:
    """Read, validate and check a protocol; every problem is a one-line ProtocolError.

    ``source`` is a protocol file, a shipped protocol's name (``"pilot"``,
    :func:`crs_study.paths.resolve_protocol`), or a :class:`Protocol` object. An object
    whose fields are those of its text (as loaded) comes back as it is, once its device
    checks have run; one changed in Python (:func:`dataclasses.replace`) is written as TOML
    (:func:`crs_study.protocol.writer.protocol_to_toml`) and read back from that text, with
    every check a file gets: the result's ``text`` and ``sha256`` are then those of the
    protocol that runs (a session stores them), its ``path`` still the original file's (for
    the files it names: consent form, analysis plan).

    ``check_device=False`` skips :func:`~crs_study.protocol.feasibility.check_on_device` and
    the warnings (only for tools that inspect a protocol's keys; a runner must never skip
    it).
    """
    if isinstance(source, Protocol):
        return _settled(source, check_device)
    path = resolve_protocol(source)
    source_name = str(path)
    try:
        raw = path.read_bytes()
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise ProtocolError(f"{source_name}: no such protocol file") from None
    except IsADirectoryError:
        raise ProtocolError(f"{source_name}: expected a protocol file, got a directory") \
            from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{source_name}: cannot read: {one_line(exc)}") from None
    return protocol_from_text(text, path, hashlib.sha256(raw).hexdigest(),
                              check_device=check_device)


def protocol_from_text(text: str, path: Path, sha256: str | None = None, *,
                       check_device: bool = True) -> Protocol:
    """The protocol of TOML ``text`` read from ``path`` (``sha256``: of its bytes, by default
    of the text as UTF-8), checked as :func:`load_protocol` checks a file."""
    source = str(path)
    data = parse_toml(text, source, ProtocolError)
    sha256 = sha256 or hashlib.sha256(text.encode("utf-8")).hexdigest()
    try:
        protocol = protocol_from_dict(data, path, text, sha256)
        if check_device:
            checks = check_on_device(protocol)
            protocol = replace(protocol, checks=checks, warnings=protocol_warnings(protocol))
    except ConfigError as exc:
        raise as_protocol_error(exc, source, text) from None
    return protocol


def _settled(protocol: Protocol, check_device: bool) -> Protocol:
    """``protocol`` as its own text gives it (see :func:`load_protocol`).

    Problems with a protocol changed in Python name it ``FILE (changed in Python)`` and no
    line: the lines of the written text are in no file the user has."""
    if _is_its_text(protocol):
        if protocol.checks or not check_device:
            return protocol
        return protocol_from_text(protocol.text, protocol.path, protocol.sha256,
                                  check_device=check_device)
    label = f"{protocol.path} (changed in Python)"
    try:
        settled = protocol_from_text(protocol_to_toml(protocol), protocol.path,
                                     check_device=check_device)
    except ConfigError as error:
        error.source, error.line = label, None
        raise
    if settled.warnings:
        settled = replace(settled, warnings=tuple(
            replace(f, line=None).describe(label) for f in warning_findings(settled)))
    return settled


def _is_its_text(protocol: Protocol) -> bool:
    """True when reading ``protocol.text`` gives ``protocol`` (no field changed since)."""
    text = protocol.text
    if hashlib.sha256(text.encode("utf-8")).hexdigest() != protocol.sha256:
        return False
    try:
        data = tomllib.loads(text)
        return protocol_from_dict(data, protocol.path, text, protocol.sha256) == protocol
    except (tomllib.TOMLDecodeError, ConfigError, RecursionError):
        return False


def as_protocol_error(error: ConfigError, source: str, text: str) -> ProtocolError:
    """``error`` as a :class:`ProtocolError` of the protocol ``source``: same reason, key
    path and line; the file and the line of its key filled in when it names none."""
    if not isinstance(error, ProtocolError):
        error = ProtocolError(error.reason, source=error.source, line=error.line,
                              key_path=error.key_path, shown_path=error.shown_path)
    return locate(error, source, text)


def protocol_from_dict(data: dict, path: Path, text: str = "", sha256: str = "") -> Protocol:
    """Build a :class:`Protocol` from parsed TOML, checking every key (no device checks).

    With the file's ``text`` the errors carry the line of their key."""
    source = str(path)
    try:
        return _protocol(data, path, text, sha256)
    except ConfigError as exc:
        raise as_protocol_error(exc, source, text) from None


def _protocol(data: dict, path: Path, text: str, sha256: str) -> Protocol:
    keys_of = table_keys()
    root = Section(data, str(path), error=ProtocolError, keys=keys_of[""], text=text or None)
    set_name = _set_name(root, path)
    if set_name != DEFAULT_SET:
        keys_of = table_keys(set_name)

    def table(name: str) -> Section:
        return root.table(name, keys=keys_of[name])

    study = table("study")
    conditions_table = table("conditions")
    stimulus_table = table("stimulus")
    design_table = table("design")
    responses_table = table("responses")
    levels_table = table("levels") if root.has("levels") else None
    if levels_table is None:
        root.raw("levels", None)
    adaptive_table = table("adaptive") if root.has("adaptive") else None
    if adaptive_table is None:
        root.raw("adaptive", None)
    elif levels_table is not None:
        raise root.fail("adaptive", "a protocol either crosses fixed [levels] with its "
                        "trials or lets [adaptive] choose them: remove one of the two tables")
    root.done()

    study_fields: dict[str, Any] = {
        "study_id": study.raw("id"), "version": study.raw("version"),
        "title": study.raw("title", OPTIONAL_KEYS["study.title"]),
        "device": _device(study, path), "consent_form": study.raw("consent_form"),
        "consent_form_version": study.raw("consent_form_version"),
        "analysis_plan": study.raw("analysis_plan"),
    }
    study.done()

    names = conditions_table.raw("names")
    prompts_table = conditions_table.table("prompts", OPTIONAL_KEYS["conditions.prompts"])
    prompts = tuple((name, prompts_table.raw(name)) for name in list(prompts_table.data))
    prompts_table.done()
    conditions_table.done()
    levels = _levels(levels_table, set_name) if levels_table is not None else None
    adaptive = _adaptive(adaptive_table, set_name) if adaptive_table is not None else None
    stimulus = _stimulus(stimulus_table, path, set_name,
                         levels if adaptive is None else adaptive_levels(adaptive, set_name))
    design = _design(design_table, set_name)
    if design.ordering == "interleaved" and prompts:
        raise conditions_table.fail(
            "prompts", "an interleaved design changes condition from trial to trial, so there "
            "is no block start to prompt at (mount or remove the skeleton); drop "
            "[conditions.prompts] or use ordering = \"blocked\"")
    responses = _responses(responses_table, stimulus)
    return Protocol(path=path, text=text, sha256=sha256, conditions=names,
                    condition_prompts=prompts, stimulus=stimulus, design=design,
                    responses=responses, levels=levels, adaptive=adaptive, **study_fields)


def _one_line(section: Section, key: str) -> str:
    """A one-line string that can name a file (``device``, ``strokes_file``)."""
    value = section.raw(key)
    problem = path_problem(value)
    if problem is not None:
        raise section.fail(key, problem)
    return value


def _device(study: Section, path: Path) -> str:
    value = _one_line(study, "device")
    if value in BUILTIN_DEVICES:
        return value
    device_path = Path(value)
    if not device_path.is_absolute():
        device_path = path.parent / device_path
    if not device_path.is_file():
        raise study.fail("device", f"expected a built-in device ({', '.join(BUILTIN_DEVICES)}) "
                         f"or a device file, got {value!r} (no file at {device_path})")
    return str(device_path)


def _file_beside(section: Section, key: str, value: str, path: Path, expected: str) -> str:
    """The file ``value`` names (absolute, or relative to the protocol at ``path``), checked to
    exist: a one-line error under ``key`` saying ``expected`` otherwise."""
    candidate = Path(value) if Path(value).is_absolute() else path.parent / value
    if not candidate.is_file():
        raise section.fail(key, f"expected {expected}, got {value!r} (no file at {candidate})")
    return str(candidate)


def _set_name(root: Section, path: Path) -> str:
    """``stimulus.set``, read first (it spells the other keys): a shipped set's name, or a set
    file's path (relative to the protocol) resolved, its file read now so that its errors come
    under the key."""
    stimulus = root.data.get("stimulus")
    if not isinstance(stimulus, dict) or "set" not in stimulus:
        return DEFAULT_SET
    section = Section(stimulus, root.source, "stimulus", ProtocolError, text=root.text)
    value = _one_line(section, "set")
    name = value
    if value not in shipped_sets():
        name = _file_beside(section, "set", value, path, "a shipped stimulus set or a set file")
    try:
        load_stimulus_set(name)
    except ProtocolError as exc:
        raise section.fail("set", one_line(exc)) from None
    return name


def _levels(table: Section, set_name: str) -> LevelSpec:
    """The ``[levels]`` table (see :class:`LevelSpec` and protocols/README.md)."""
    parameter = table.raw("parameter")
    values = table.raw("values")
    # a varied height needs the symbols' shape; with another parameter the key is refused
    size = LevelSpec.size_parameter(set_name)
    width = table.raw("width_to_height", ... if parameter == size else None)
    table.done()
    return LevelSpec(parameter, values, width, set_name)


def _adaptive(table: Section, set_name: str) -> AdaptiveSpec:
    """The ``[adaptive]`` table and its procedure's sub-table (protocols/README.md)."""
    def sub(name: str, required: tuple[str, ...]) -> dict | None:
        if not table.has(name):
            table.raw(name, None)
            return None
        section = table.table(name, keys=table_keys()[f"adaptive.{name}"])
        for key in required:
            section.raw(key)  # a missing required key is named with its line
        values = {key: section.raw(key) for key in section.data}
        section.done()
        return values

    staircase = sub("staircase", ("rule", "start", "steps"))
    quest_plus = sub("quest_plus", ("thresholds", "slopes", "lapse_rates"))
    parameter = table.raw("parameter")
    spec = AdaptiveSpec(
        parameter, table.raw("procedure"), table.raw("trials"), table.raw("min"),
        table.raw("max"), table.raw("scale"), table.raw("levels"),
        target_rate=table.raw("target_rate", None),
        practice_level=table.raw("practice_level", None),
        # a varied height needs the digits' shape; with another parameter the key is refused
        width_to_height=table.raw("width_to_height",
                                  ... if parameter == LevelSpec.size_parameter(set_name)
                                  else None),
        staircase=StaircaseSpec(**staircase) if staircase is not None else None,
        quest_plus=QuestPlusSpec(**quest_plus) if quest_plus is not None else None)
    table.done()
    return spec


def _check_strokes_file(table: Section, strokes_file: str, shown: StimulusSpec) -> None:
    """Read a protocol's own strokes file now: its errors (``FILE:LINE: key: ...``) come
    under ``stimulus.strokes_file``, and every symbol shown must be defined there."""
    try:
        symbol_set = shown.symbol_set
    except ProtocolError as exc:
        raise table.fail("strokes_file", one_line(exc)) from None
    missing = [s for s in shown.symbols if s not in symbol_set.glyphs]
    if missing:
        noun, plural, key = symbol_set.noun, symbol_set.plural, shown.file_key("symbols")
        raise table.fail("strokes_file", f"{strokes_file} defines no strokes for "
                         f"{noun if len(missing) == 1 else plural} "
                         f"{', '.join(map(str, missing))} of stimulus.{key}; expected every "
                         f"{noun} shown, got {plural} {list(symbol_set.glyphs)}")


def _stimulus(table: Section, path: Path, set_name: str, levels: LevelSpec | None = None
              ) -> StimulusSpec:
    def optional(key: str) -> Any:
        return table.raw(key, OPTIONAL_KEYS[f"stimulus.{key}"])

    column = load_stimulus_set(set_name).column
    key_of = {f: spell(f, column) for f in
              ("symbols", "symbol_height_pitch", "symbol_width_pitch")}
    optional("set")  # read first, by _set_name
    symbols = table.raw(key_of["symbols"])
    strokes_file = None
    if table.has("strokes_file"):
        strokes_file = _file_beside(table, "strokes_file", _one_line(table, "strokes_file"),
                                    path, "a strokes file")
    else:
        optional("strokes_file")
    varied = () if levels is None else (levels.parameter,) + (
        (key_of["symbol_width_pitch"],) if levels.varies_size else ())
    for key in varied:
        if table.has(key):
            raise table.fail(key, f"set by [levels] (parameter = {levels.parameter!r}): "
                             f"remove it from [stimulus], got {table.data[key]!r}")
    if levels is not None and levels.varies_size:
        height = levels.values[0]  # the spec holds the first level; see Protocol.stimulus_at
        width = height * float(levels.width_to_height or 1.0)
    else:
        height = table.raw(key_of["symbol_height_pitch"])
        width = table.raw(key_of["symbol_width_pitch"])
    speed = levels.values[0] if levels is not None and \
        levels.parameter == "stroke_speed_mm_s" else table.raw("stroke_speed_mm_s")
    placement = table.raw("placement")
    if placement in PLACEMENTS:  # (another placement is the spec's to refuse)
        if table.has("offset_mm") and placement != "offset":
            raise table.fail("offset_mm", f"only used with placement = \"offset\", "
                             f"got placement = {placement!r}")
        if not table.has("offset_mm") and placement == "offset":
            raise table.fail("offset_mm", "missing: placement = \"offset\" needs "
                             "offset_mm = [x, y]")
    spec = StimulusSpec(
        symbols, strokes_file, height, width, table.raw("bump_diameter_mm"),
        table.raw("bump_height_mm"), speed, placement, optional("offset_mm"),
        table.raw("frame_rate_hz"), optional("stroke_pause_s"), optional("start_hold_s"),
        optional("end_hold_s"), set_name)
    table.done()
    if strokes_file is not None:
        _check_strokes_file(table, strokes_file, spec)
    return spec


def _design(table: Section, set_name: str) -> DesignSpec:
    run_key = spell("max_same_symbol_run", load_stimulus_set(set_name).column)
    spec = DesignSpec(
        table.raw("repetitions"), table.raw("ordering"), table.raw("counterbalancing"),
        table.raw(run_key), table.raw("practice_trials"),
        table.raw("practice_in", OPTIONAL_KEYS["design.practice_in"]),
        table.raw("break_every"),
        table.raw("break_duration_s", OPTIONAL_KEYS["design.break_duration_s"]),
        table.raw("inter_trial_interval_s"), set_name)
    table.done()
    return spec


def _responses(table: Section, stimulus: StimulusSpec) -> ResponseSpec:
    symbols = stimulus.symbols
    keys = table.raw("keys", None)
    if keys is None:  # the set's own key for each symbol shown
        own: StimulusSet = load_stimulus_set(stimulus.set_name)
        keys = [own.keys[s] for s in symbols]
    if isinstance(keys, list) and len(keys) != len(symbols):
        noun = load_stimulus_set(stimulus.set_name).noun
        raise table.fail("keys", f"expected {len(symbols)} keys (one per {noun} of "
                         f"stimulus.{stimulus.file_key('symbols')}), got {keys!r}")
    spec = ResponseSpec(
        keys, table.raw("time_limit_s", OPTIONAL_KEYS["responses.time_limit_s"]),
        table.raw("feedback"),
        table.raw("expected_response_s", OPTIONAL_KEYS["responses.expected_response_s"]))
    table.done()
    return spec
