"""Protocol files: what a digit-identification study runs, read strictly and checked on the device.

A protocol is a TOML file with five tables (``protocols/README.md`` documents every key):
``[study]`` (id, version, device, consent form, analysis plan), ``[stimulus]`` (digits, their
size in pixel pitches, the bump, stroke speed, placement, frame rate), ``[conditions]``
(registered display conditions and the experimenter's prompt for each), ``[design]``
(repetitions, blocking, counterbalancing, run constraint, practice, breaks, inter-trial
interval) and ``[responses]`` (keys, time limit, feedback). An optional ``[levels]`` table
varies one stimulus parameter across trials (a psychometric study, :class:`LevelSpec`).

Reading is strict (:mod:`crs_study._toml`): unknown keys, wrong types and out-of-range values
are one-line :class:`~crs_study.errors.ProtocolError` s naming the file, the line where the key
is found, the key path and the value. Then the protocol is checked against its device
(:func:`check_on_device`): the bump centre's path must stay inside the pixel area, the bump
within the pixels' travel, the CRS within its limits (boundary feed within the boundary travel,
no collapse Delta >= 1 by Eq. 4, curvature below yield) and the frame rate within the wire.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crs_study._toml import Section
from crs_study.errors import ConfigError, ConsentError, CrsStudyError, ProtocolError
from crs_study.layout import BUILTIN_DEVICES, Layout, load_layout
from crs_study.responders.base import PAUSE_KEYS

#: Closed choices.
PLACEMENTS = ("centre", "offset")
ORDERINGS = ("blocked", "interleaved")
COUNTERBALANCING = ("none", "alternate", "abba", "latin")
PRACTICE_IN = ("first-block", "every-block")
FEEDBACK = ("none", "practice", "all")

#: Keys that may be left out (with the default used then). Every other key is required.
OPTIONAL_KEYS: dict[str, object] = {
    "study.title": "",
    "stimulus.strokes_file": None,
    "stimulus.offset_mm": (0.0, 0.0),
    "stimulus.stroke_pause_s": 0.4,
    "stimulus.start_hold_s": 0.3,
    "stimulus.end_hold_s": 0.3,
    "conditions.prompts": {},
    "design.practice_in": "first-block",
    "design.break_duration_s": 30.0,
    "responses.time_limit_s": None,
    "responses.expected_response_s": 2.0,
}

#: Slowest stroke speed accepted (mm/s): a 60 mm digit then takes a minute.
#: Slowest frame rate a protocol may ask for (frames/s).
MIN_FRAME_RATE_HZ = 1.0
MIN_STROKE_SPEED_MM_S = 1.0

#: Odd but legal values warn (STYLE rule 5; :func:`protocol_warnings`, protocols/README.md,
#: "Warnings"). A session expected to last longer than this (s):
WARN_SESSION_S = 90 * 60.0
#: ... a stretch of a block longer than this without a break (s):
WARN_UNBROKEN_S = 20 * 60.0
#: ... a time limit longer than this (s, from stimulus offset):
WARN_TIME_LIMIT_S = 60.0
#: ... an inter-trial interval shorter than this (s; about a simple reaction time):
WARN_ITI_S = 0.1
#: ... a digit's stimulus lasting longer than this (s; the shipped 20 mm/s: 2 to 5 s):
WARN_DRAWING_S = 15.0
#: ... a stroke speed at which the device's latency lags the bump by more than this fraction
#: of the digit's height; the latency is the paper's device's (crs-paper.md, Methods: 75 ms).
WARN_LAG_FRACTION = 0.25
PAPER_LATENCY_S = 0.075

#: Stimulus parameters a ``[levels]`` table may vary: key -> (dataset column, units, min, max).
#: The dataset column names are those the analysis looks for
#: (``crs_study.analysis.plan.KNOWN_LEVEL_COLUMNS``); the ranges are those of ``[stimulus]``.
LEVEL_PARAMETERS: dict[str, tuple[str, str, float, float]] = {
    "digit_height_pitch": ("digit_height", "pitch", 0.01, 20.0),
    "stroke_speed_mm_s": ("stroke_speed", "mm/s", MIN_STROKE_SPEED_MM_S, 1000.0),
}
#: Most levels one protocol may declare (each multiplies the number of trials).
MAX_LEVELS = 20

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class StimulusSpec:
    """The ``[stimulus]`` table: what is drawn, how big, how fast. Lengths in mm, times in s."""

    digits: tuple[int, ...]
    strokes_file: str | None  # resolved path, None for the shipped strokes
    digit_height_pitch: float
    digit_width_pitch: float
    bump_diameter_mm: float
    bump_height_mm: float
    stroke_speed_mm_s: float
    placement: str
    offset_mm: tuple[float, float]
    frame_rate_hz: float
    stroke_pause_s: float
    start_hold_s: float
    end_hold_s: float


@dataclass(frozen=True)
class LevelSpec:
    """The optional ``[levels]`` table: one stimulus parameter varied across trials.

    ``parameter`` is a key of :data:`LEVEL_PARAMETERS` (it is then absent from ``[stimulus]``);
    ``values`` are its levels, distinct, in the protocol's order. Varying
    ``digit_height_pitch`` scales the whole digit: its width is ``width_to_height`` times the
    height (the shipped shape 0.49 / 0.81 = 0.605), so ``digit_width_pitch`` is absent too.
    """

    parameter: str
    values: tuple[float, ...]
    width_to_height: float | None = None

    @property
    def column(self) -> str:
        """The dataset column holding a trial's level (``digit_height``, ``stroke_speed``)."""
        return LEVEL_PARAMETERS[self.parameter][0]

    @property
    def units(self) -> str:
        return LEVEL_PARAMETERS[self.parameter][1]


@dataclass(frozen=True)
class DesignSpec:
    """The ``[design]`` table: how trials are repeated, ordered and paced."""

    repetitions: int
    ordering: str
    counterbalancing: str
    max_same_digit_run: int
    practice_trials: int
    practice_in: str
    break_every: int
    break_duration_s: float
    inter_trial_interval_s: float


@dataclass(frozen=True)
class ResponseSpec:
    """The ``[responses]`` table. ``keys[i]`` answers ``stimulus.digits[i]``."""

    keys: tuple[str, ...]
    time_limit_s: float | None  # from stimulus offset; None: no limit
    feedback: str
    expected_response_s: float


@dataclass(frozen=True)
class Protocol:
    """A validated protocol. Build with :func:`load_protocol`."""

    path: Path
    text: str
    sha256: str
    study_id: str
    version: str
    title: str
    device: str  # built-in device name, or a resolved device file path
    consent_form: str
    consent_form_version: str
    analysis_plan: str
    conditions: tuple[str, ...]
    condition_prompts: tuple[tuple[str, str], ...]
    stimulus: StimulusSpec
    design: DesignSpec
    responses: ResponseSpec
    levels: LevelSpec | None = None  # None: every trial shows the [stimulus] values
    checks: tuple[str, ...] = field(default=(), compare=False)  # what check_on_device passed
    #: odd but legal values, one line each (``FILE:LINE: key: ...``; :func:`protocol_warnings`)
    warnings: tuple[str, ...] = field(default=(), compare=False)

    @property
    def level_values(self) -> tuple[float | None, ...]:
        """The levels of the varied parameter, or ``(None,)`` when nothing varies."""
        return self.levels.values if self.levels is not None else (None,)

    def stimulus_at(self, level: float | None) -> StimulusSpec:
        """The stimulus of a trial at ``level`` (``None``: the protocol's fixed stimulus)."""
        if level is None or self.levels is None:
            if level is not None:
                raise ProtocolError(f"{self.path}: the protocol varies no level, got "
                                    f"level {level!r}")
            return self.stimulus
        if level not in self.levels.values:
            raise ProtocolError(f"{self.path}: levels.values: expected one of "
                                f"{list(self.levels.values)}, got {level!r}")
        return _spec_at(self.stimulus, self.levels, float(level))

    @property
    def frame_rate_hz(self) -> float:
        return self.stimulus.frame_rate_hz

    @property
    def time_limit_s(self) -> float | None:
        return self.responses.time_limit_s

    @property
    def inter_trial_interval_s(self) -> float:
        return self.design.inter_trial_interval_s

    @property
    def feedback_practice(self) -> bool:
        return self.responses.feedback in ("practice", "all")

    @property
    def feedback_test(self) -> bool:
        return self.responses.feedback == "all"

    @property
    def digits(self) -> tuple[int, ...]:
        return self.stimulus.digits

    def prompt(self, condition: str) -> str | None:
        """The experimenter's prompt before a block of ``condition`` (None when not given)."""
        return dict(self.condition_prompts).get(condition)

    def key_for(self, digit: int) -> str:
        return self.responses.keys[self.stimulus.digits.index(digit)]

    def digit_for_key(self, key: str) -> int | None:
        keys = self.responses.keys
        return self.stimulus.digits[keys.index(key)] if key in keys else None

    def layout(self) -> Layout:
        """The device's layout (cached per device file)."""
        return _layout(self.device)


_LAYOUTS: dict[str, Layout] = {}


def _layout(device: str) -> Layout:
    if device not in _LAYOUTS:
        _LAYOUTS[device] = load_layout(device)
    return _LAYOUTS[device]


# --------------------------------------------------------------------------------------------
# Loading


def load_protocol(path: str | Path, *, check_device: bool = True) -> Protocol:
    """Read, validate and check a protocol file; every problem is a one-line ProtocolError.

    ``check_device=False`` skips :func:`check_on_device` (only for tools that inspect a
    protocol's keys; a runner must never skip it).
    """
    import tomllib

    path = Path(path)
    source = str(path)
    try:
        raw = path.read_bytes()
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise ProtocolError(f"{source}: no such protocol file") from None
    except IsADirectoryError:
        raise ProtocolError(f"{source}: expected a protocol file, got a directory") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{source}: cannot read: {_one_line(exc)}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProtocolError(toml_syntax_message(source, exc, text)) from None
    try:
        protocol = protocol_from_dict(data, path, text, hashlib.sha256(raw).hexdigest())
        if check_device:
            checks = check_on_device(protocol)
            protocol = _replace(protocol, checks=checks, warnings=protocol_warnings(protocol))
    except ConfigError as exc:
        raise ProtocolError(locate_message(str(exc), source, text)) from None
    return protocol


def _replace(protocol: Protocol, **changes: object) -> Protocol:
    from dataclasses import replace

    return replace(protocol, **changes)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def protocol_from_dict(data: dict, path: Path, text: str = "", sha256: str = "") -> Protocol:
    """Build a :class:`Protocol` from parsed TOML, checking every key (no device checks)."""
    source = str(path)
    root = Section(data, source, error=ProtocolError)
    study = root.table("study")
    conditions_table = root.table("conditions")
    stimulus_table = root.table("stimulus")
    design_table = root.table("design")
    responses_table = root.table("responses")
    levels_table = root.table("levels") if root.has("levels") else None
    if levels_table is None:
        root.raw("levels", None)
    root.done()

    study_id = _identifier(study, "id")
    version = _nonempty(study, "version")
    title = study.string("title", "")
    device = _device(study, path)
    consent_form = _nonempty(study, "consent_form")
    consent_form_version = _nonempty(study, "consent_form_version")
    analysis_plan = _nonempty(study, "analysis_plan")
    study.done()

    conditions, prompts = _conditions(conditions_table)
    levels = _levels(levels_table) if levels_table is not None else None
    stimulus = _stimulus(stimulus_table, path, levels)
    design = _design(design_table, conditions)
    if design.ordering == "interleaved" and prompts:
        raise conditions_table.fail(
            "prompts", "an interleaved design changes condition from trial to trial, so there "
            "is no block start to prompt at (mount or remove the skeleton); drop "
            "[conditions.prompts] or use ordering = \"blocked\"")
    responses = _responses(responses_table, stimulus.digits)

    return Protocol(
        path=path, text=text, sha256=sha256, study_id=study_id, version=version, title=title,
        device=device, consent_form=consent_form, consent_form_version=consent_form_version,
        analysis_plan=analysis_plan, conditions=conditions, condition_prompts=prompts,
        stimulus=stimulus, design=design, responses=responses, levels=levels,
    )


def _nonempty(section: Section, key: str) -> str:
    value = section.string(key)
    if not value.strip() or "\n" in value:
        raise section.fail(key, f"expected a non-empty one-line string, got {value!r}")
    return value


def _identifier(section: Section, key: str) -> str:
    value = section.string(key)
    if not _ID_RE.match(value):
        raise section.fail(key, "expected letters, digits, '.', '_' or '-' (starting with a "
                           f"letter or digit), got {value!r}")
    return value


def _device(study: Section, path: Path) -> str:
    value = _nonempty(study, "device")
    if value in BUILTIN_DEVICES:
        return value
    device_path = Path(value)
    if not device_path.is_absolute():
        device_path = path.parent / device_path
    if not device_path.is_file():
        raise study.fail("device", f"expected a built-in device ({', '.join(BUILTIN_DEVICES)}) "
                         f"or a device file, got {value!r} (no file at {device_path})")
    return str(device_path)


def _conditions(table: Section) -> tuple[tuple[str, ...], tuple[tuple[str, str], ...]]:
    from crs_study.render import CONDITIONS

    names = table.array("names")
    if len(names) < 1:
        raise table.fail("names", "expected at least one condition, got []")
    for i, name in enumerate(names):
        if not isinstance(name, str) or name not in CONDITIONS:
            raise table.fail(f"names[{i}]", f"expected a registered condition "
                             f"({', '.join(sorted(CONDITIONS))}), got {name!r}")
    if len(set(names)) != len(names):
        raise table.fail("names", f"a condition appears twice in {names!r}")
    prompts_table = table.table("prompts", {})
    prompts = []
    for name in list(prompts_table.data):
        if name not in names:
            raise prompts_table.fail(name, f"expected a prompt for one of the conditions "
                                     f"{names!r}, got a prompt for {name!r}")
        prompts.append((name, _nonempty(prompts_table, name)))
    prompts_table.done()
    table.done()
    return tuple(names), tuple(prompts)


def _levels(table: Section) -> LevelSpec:
    """The ``[levels]`` table (see :class:`LevelSpec` and protocols/README.md)."""
    parameter = table.string("parameter", choices=tuple(LEVEL_PARAMETERS))
    _, units, low, high = LEVEL_PARAMETERS[parameter]
    values = table.array("values")
    if not 2 <= len(values) <= MAX_LEVELS:
        raise table.fail("values", f"expected 2 to {MAX_LEVELS} levels of {parameter} "
                         f"({units}), got {values!r}")
    for i, v in enumerate(values):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                or not low <= v <= high:
            raise table.fail(f"values[{i}]", f"expected a number {low:g} to {high:g} "
                             f"({parameter}), got {v!r}")
    floats = tuple(float(v) for v in values)
    if len(set(floats)) != len(floats):
        raise table.fail("values", f"a level appears twice in {values!r}")
    ratio = None
    if parameter == "digit_height_pitch":
        ratio = table.number("width_to_height", minimum=0.05, maximum=20.0)
        for i, v in enumerate(floats):
            if not 0.01 <= v * ratio <= 20.0:
                raise table.fail(f"values[{i}]", f"the width {v * ratio:g} pitch "
                                 f"(width_to_height {ratio:g} x {v!r}) is outside 0.01-20")
    elif table.has("width_to_height"):
        raise table.fail("width_to_height", "only used with parameter = "
                         f"\"digit_height_pitch\", got parameter = {parameter!r}")
    table.done()
    return LevelSpec(parameter, floats, ratio)


def _check_strokes_file(table: Section, strokes_file: str, digits: list[int]) -> None:
    """Read a protocol's own strokes file now: its errors (``FILE:LINE: key: ...``) come
    under ``stimulus.strokes_file``, and every digit shown must be defined there."""
    from crs_study.digits import load_digits

    try:
        defined = load_digits(strokes_file)
    except ProtocolError as exc:
        raise table.fail("strokes_file", _one_line(exc)) from None
    missing = [d for d in digits if d not in defined]
    if missing:
        raise table.fail("strokes_file", f"{strokes_file} defines no strokes for "
                         f"{'digit' if len(missing) == 1 else 'digits'} "
                         f"{', '.join(map(str, missing))} of stimulus.digits; expected every "
                         f"digit shown, got digits {sorted(defined)}")


def _spec_at(spec: StimulusSpec, levels: LevelSpec, level: float) -> StimulusSpec:
    """``spec`` with the varied parameter set to ``level`` (width follows a varied height)."""
    from dataclasses import replace

    if levels.parameter == "digit_height_pitch":
        return replace(spec, digit_height_pitch=level,
                       digit_width_pitch=level * float(levels.width_to_height or 1.0))
    return replace(spec, **{levels.parameter: level})


def _stimulus(table: Section, path: Path, levels: LevelSpec | None = None) -> StimulusSpec:
    digits = table.array("digits")
    for i, d in enumerate(digits):
        if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= 9:
            raise table.fail(f"digits[{i}]", f"expected a digit 0 to 9, got {d!r}")
    if len(set(digits)) != len(digits):
        raise table.fail("digits", f"a digit appears twice in {digits!r}")
    if len(digits) < 2:
        raise table.fail("digits", f"expected at least 2 digits to choose from, got {digits!r}")
    strokes_file = None
    if table.has("strokes_file"):
        value = _nonempty(table, "strokes_file")
        candidate = Path(value) if Path(value).is_absolute() else path.parent / value
        if not candidate.is_file():
            raise table.fail("strokes_file", f"expected a strokes file, got {value!r} "
                             f"(no file at {candidate})")
        strokes_file = str(candidate)
        _check_strokes_file(table, strokes_file, digits)
    else:
        table.raw("strokes_file", None)

    def positive(key: str, maximum: float) -> float:
        return table.number(key, minimum=0.0, exclusive_minimum=True, maximum=maximum)

    varied = () if levels is None else (levels.parameter,) + (
        ("digit_width_pitch",) if levels.parameter == "digit_height_pitch" else ())
    for key in varied:
        if table.has(key):
            raise table.fail(key, f"set by [levels] (parameter = {levels.parameter!r}): "
                             f"remove it from [stimulus], got {table.data[key]!r}")
    if levels is not None and levels.parameter == "digit_height_pitch":
        height = levels.values[0]  # the spec holds the first level; see Protocol.stimulus_at
        width = height * float(levels.width_to_height or 1.0)
    else:
        height = table.number("digit_height_pitch", minimum=0.01, maximum=20.0)
        width = table.number("digit_width_pitch", minimum=0.01, maximum=20.0)
    diameter = positive("bump_diameter_mm", 1000.0)
    bump_height = positive("bump_height_mm", 100.0)
    if levels is not None and levels.parameter == "stroke_speed_mm_s":
        speed = levels.values[0]
    else:
        speed = table.number("stroke_speed_mm_s", minimum=MIN_STROKE_SPEED_MM_S,
                             maximum=1000.0)
    placement = table.string("placement", choices=PLACEMENTS)
    offset = (0.0, 0.0)
    if table.has("offset_mm"):
        raw = table.array("offset_mm")
        if (len(raw) != 2 or any(isinstance(c, bool) or not isinstance(c, int | float)
                                 or not math.isfinite(c) for c in raw)):
            raise table.fail("offset_mm", f"expected [x, y] in mm, got {raw!r}")
        if placement != "offset":
            raise table.fail("offset_mm", f"only used with placement = \"offset\", "
                             f"got placement = {placement!r}")
        offset = (float(raw[0]), float(raw[1]))
    elif placement == "offset":
        raise table.fail("offset_mm", "missing: placement = \"offset\" needs offset_mm = [x, y]")
    # Below one frame a second a moving bump is a slide show, and the frame count of a stroke
    # (L f / v) loses meaning as f -> 0 (hypothesis found f = 5e-324).
    frame_rate = table.number("frame_rate_hz", minimum=MIN_FRAME_RATE_HZ, maximum=1000.0)
    pause = table.number("stroke_pause_s", 0.4, minimum=0.0, maximum=10.0)
    start_hold = table.number("start_hold_s", 0.3, minimum=0.0, maximum=10.0)
    end_hold = table.number("end_hold_s", 0.3, minimum=0.0, maximum=10.0)
    table.done()
    return StimulusSpec(tuple(digits), strokes_file, height, width, diameter, bump_height, speed,
                        placement, offset, frame_rate, pause, start_hold, end_hold)


def _design(table: Section, conditions: tuple[str, ...]) -> DesignSpec:
    repetitions = table.integer("repetitions", minimum=1, maximum=1000)
    ordering = table.string("ordering", choices=ORDERINGS)
    counterbalancing = table.string("counterbalancing", choices=COUNTERBALANCING)
    if ordering == "interleaved" and counterbalancing != "none":
        raise table.fail("counterbalancing", "interleaved conditions have no block order to "
                         f"counterbalance: expected \"none\", got {counterbalancing!r}")
    if counterbalancing == "abba" and repetitions < 2:
        raise table.fail("counterbalancing", "\"abba\" splits the repetitions over two blocks "
                         f"per condition: needs repetitions >= 2, got {repetitions!r}")
    max_run = table.integer("max_same_digit_run", minimum=1, maximum=1000)
    practice = table.integer("practice_trials", minimum=0, maximum=1000)
    practice_in = table.string("practice_in", "first-block", choices=PRACTICE_IN)
    break_every = table.integer("break_every", minimum=0, maximum=100000)
    break_duration = table.number("break_duration_s", 30.0, minimum=0.0, maximum=3600.0)
    iti = table.number("inter_trial_interval_s", minimum=0.0, maximum=60.0)
    table.done()
    return DesignSpec(repetitions, ordering, counterbalancing, max_run, practice, practice_in,
                      break_every, break_duration, iti)


def _responses(table: Section, digits: tuple[int, ...]) -> ResponseSpec:
    keys = table.array("keys")
    if len(keys) != len(digits):
        raise table.fail("keys", f"expected {len(digits)} keys (one per digit of "
                         f"stimulus.digits), got {keys!r}")
    for i, key in enumerate(keys):
        if not isinstance(key, str) or len(key) != 1 or not key.isprintable() or key == " ":
            raise table.fail(f"keys[{i}]", f"expected a single printable character, got {key!r}")
    if len(set(keys)) != len(keys):
        raise table.fail("keys", f"a key appears twice in {keys!r}")
    paused = sorted(set(keys) & PAUSE_KEYS)
    if paused:
        raise table.fail("keys", f"{paused[0]!r} pauses the session at the keypad (q, Q and "
                         f"Escape do); choose another key, got {keys!r}")
    time_limit = None
    if table.has("time_limit_s"):
        time_limit = table.number("time_limit_s", minimum=0.0, exclusive_minimum=True,
                                  maximum=3600.0)
    else:
        table.raw("time_limit_s", None)
    feedback = table.string("feedback", choices=FEEDBACK)
    expected = table.number("expected_response_s", 2.0, minimum=0.0, maximum=3600.0)
    table.done()
    return ResponseSpec(tuple(keys), time_limit, feedback, expected)


# --------------------------------------------------------------------------------------------
# Semantic checks on the device


def check_on_device(protocol: Protocol) -> tuple[str, ...]:
    """Check the protocol against its device; return one line per check passed.

    Raises :class:`ProtocolError` (naming the protocol key) for the first check that fails.
    The heavy part (rendering every frame of every digit) is cached per stimulus and device.
    """
    source = str(protocol.path)
    try:
        layout = protocol.layout()
    except ConfigError as exc:
        raise ProtocolError(f"{source}: study.device: {_one_line(exc)}") from None
    passed = [f"device {layout.name}: {layout.n_pixels} pixels, {len(layout.beams)} beams, "
              f"{layout.n_actuators} actuators"]
    passed += _consent_check(protocol, source)
    from crs_study.stimulus import device_limits

    if protocol.levels is None:
        try:
            _check_shape_keys(protocol.stimulus, protocol.conditions, layout, sized=True)
            passed += device_limits(protocol.stimulus, protocol.conditions, layout)
        except CrsStudyError as exc:
            message = _one_line(exc)
            if not message.startswith(source):
                message = f"{source}: {message}"
            raise ProtocolError(message) from None
        return tuple(passed)
    # Every level is checked like a fixed stimulus; lines shared by all levels are kept once,
    # the others are prefixed with their level.
    levels = protocol.levels
    per_level: list[list[str]] = []
    for i, value in enumerate(levels.values):
        try:
            spec = protocol.stimulus_at(value)
            _check_shape_keys(spec, protocol.conditions, layout,
                              sized=levels.parameter != "digit_height_pitch")
            per_level.append(device_limits(spec, protocol.conditions, layout))
        except CrsStudyError as exc:
            message = _one_line(exc)
            if message.startswith(source):
                message = message[len(source):].lstrip(": ")
            raise ProtocolError(f"{source}: levels.values[{i}]: at {levels.parameter} = "
                                f"{value:g}: {message}") from None
    shared = set.intersection(*(set(lines) for lines in per_level))
    passed += [line for line in per_level[0] if line in shared]
    for value, lines in zip(levels.values, per_level, strict=True):
        passed += [f"{levels.parameter} = {value:g}: {line}" for line in lines
                   if line not in shared]
    return tuple(passed)


def _check_shape_keys(spec: StimulusSpec, conditions: tuple[str, ...], layout: Layout,
                      sized: bool) -> None:
    """Two device checks whose failure depends on two keys at once, made here so that the
    message names the key at fault (:func:`crs_study.stimulus.device_limits` makes them as
    well, naming one key whichever is at fault):

    * the bump's curvature 2 pi^2 z_f / l^2 against the beam's yield curvature (with a
      skeleton condition): both ``bump_height_mm`` and ``bump_diameter_mm`` are named, with
      the bound each would have to meet given the other;
    * the bump centre's path inside the pixel area: ``offset_mm`` when the same digits drawn
      at the display centre fit, else ``digit_width_pitch`` when the digits' horizontal
      extent alone leaves the area, else ``digit_height_pitch`` (its vertical extent alone,
      or both together at a corner). ``sized=False`` (the size is a ``[levels]`` value,
      named by the caller) always names ``digit_height_pitch``.

    Devices other than 2D hexagonal ones are left to ``device_limits`` (digits need 2D).
    """
    if layout.lattice != "hex":
        return
    from crs_study.stimulus import display_centre, inside_convex_hull, stimulus_for
    from crs_study.targets import Bump

    if any(c != "pixel-only" for c in conditions) and layout.beams:
        from crs_study.quality.mechanics import stimulus_limits

        z_f, l_mm = spec.bump_height_mm, spec.bump_diameter_mm
        limits = stimulus_limits(layout, Bump((0.0, 0.0), l_mm, z_f))  # one copy of Eq. 7's
        curvature, limit = limits.curvature, limits.yield_curvature  # curvature and yield
        if curvature > limit:
            raise ProtocolError(
                f"stimulus.bump_height_mm: the bump's curvature {curvature:.4f}/mm "
                f"(2 pi^2 z_f / l^2 with z_f = stimulus.bump_height_mm = {z_f!r} and "
                f"l = stimulus.bump_diameter_mm = {l_mm!r}) exceeds the beam's yield "
                f"curvature {limit:.4f}/mm; expected bump_height_mm <= "
                f"{limit * l_mm ** 2 / (2 * math.pi ** 2):.3g} at this diameter or "
                f"bump_diameter_mm >= {math.sqrt(2 * math.pi ** 2 * z_f / limit):.3g} at this "
                "height")

    centre = display_centre(layout)
    placed = (centre[0] + spec.offset_mm[0], centre[1] + spec.offset_mm[1])
    paths = [stimulus_for(spec, layout.pitch_mm, placed, d) for d in spec.digits]
    drawn = np.concatenate([s.centres_mm[s.drawn] for s in paths]) - np.asarray(placed)
    inside, margin = inside_convex_hull(drawn + np.asarray(placed), layout.pixel_xy)
    if inside.all():
        return
    worst = drawn[np.argmin(inside)] + np.asarray(placed)
    where = (f"the bump centre leaves the pixel area (by {-margin:.1f} mm at "
             f"({worst[0]:.1f}, {worst[1]:.1f}) mm); expected the digit inside the display")
    if spec.placement == "offset" and inside_convex_hull(
            drawn + np.asarray(centre), layout.pixel_xy)[0].all():
        raise ProtocolError(f"stimulus.offset_mm: {where}, got {list(spec.offset_mm)!r} (the "
                            "digits fit at the display centre)")
    if not sized:
        raise ProtocolError(f"stimulus.digit_height_pitch: {where}")
    across = np.column_stack([drawn[:, 0], np.zeros(len(drawn))]) + np.asarray(centre)
    if not inside_convex_hull(across, layout.pixel_xy)[0].all():
        raise ProtocolError(f"stimulus.digit_width_pitch: {where}, got "
                            f"{spec.digit_width_pitch!r} (the digits' width alone leaves it)")
    upright = np.column_stack([np.zeros(len(drawn)), drawn[:, 1]]) + np.asarray(centre)
    alone = "height alone leaves it" if not inside_convex_hull(
        upright, layout.pixel_xy)[0].all() else \
        f"a corner leaves it: height and width {spec.digit_width_pitch!r} together"
    raise ProtocolError(f"stimulus.digit_height_pitch: {where}, got "
                        f"{spec.digit_height_pitch!r} (the digits' {alone})")


def protocol_warnings(protocol: Protocol) -> tuple[str, ...]:
    """Odd but legal values of a checked protocol, one line each: ``FILE:LINE: key: ...``.

    Each names the key, the value and why it is odd (thresholds ``WARN_*`` above):

    * ``design.repetitions``: the session is expected to last over 1.5 h
      (:func:`crs_study.plan.expected_duration_s`, what ``validate`` prints);
    * ``design.break_every``: a block runs over 20 min without a break;
    * ``responses.time_limit_s``: over 60 s;
    * ``design.inter_trial_interval_s``: under 0.1 s (0 included);
    * ``stimulus.stroke_speed_mm_s`` (or ``levels.values[i]`` when varied): so slow that a
      digit's stimulus lasts over 15 s, or so fast that the device's 75 ms latency lags the bump
      by over a quarter of the digit's height.
    """
    from crs_study.plan import make_plan, trial_seconds
    from crs_study.stimulus import make_stimulus

    layout = protocol.layout()
    found: list[tuple[str, str]] = []  # (key path, message)
    plan = make_plan(protocol, "example", 1, 0)  # durations do not depend on who or which
    seconds = trial_seconds(protocol, plan, layout)
    total = sum(seconds)
    if total > WARN_SESSION_S:
        found.append(("design.repetitions", f"the session is expected to take "
                      f"{total / 3600:.1f} h ({len(plan)} trials at repetitions = "
                      f"{protocol.design.repetitions}; crs-study validate's estimate), over "
                      f"{WARN_SESSION_S / 3600:g} h: attention and touch sensitivity fade; fewer "
                      "repetitions, or the study split over sessions (--session N)"))
    stretch, longest, block = 0.0, (0.0, 0), None
    for trial, s in zip(plan.trials, seconds, strict=True):
        if trial.block != block or trial.break_before:
            stretch, block = 0.0, trial.block
        stretch += s
        if stretch > longest[0]:
            longest = (stretch, trial.block)
    if longest[0] > WARN_UNBROKEN_S:
        every = protocol.design.break_every
        found.append(("design.break_every", f"block {longest[1] + 1} runs "
                      f"{longest[0] / 60:.0f} min without a break ("
                      + ("break_every = 0: no breaks" if not every else
                         f"a break every {every} trials") + f"), over "
                      f"{WARN_UNBROKEN_S / 60:g} min; expected a rest at least that often"))
    limit = protocol.responses.time_limit_s
    if limit is not None and limit > WARN_TIME_LIMIT_S:
        found.append(("responses.time_limit_s", f"{limit!r} s is a long time limit (over "
                      f"{WARN_TIME_LIMIT_S:g} s): a missed digit holds the session that "
                      "long; the shipped protocols use 10 s"))
    iti = protocol.inter_trial_interval_s
    if iti < WARN_ITI_S:
        found.append(("design.inter_trial_interval_s", f"{iti!r} s: the next digit starts "
                      f"less than {WARN_ITI_S:g} s (about a reaction time) after the answer, "
                      "before the hand is back at rest; the shipped protocols use 1 s"))
    for i, level in enumerate(protocol.level_values):
        spec = protocol.stimulus_at(level)
        key = "stimulus.stroke_speed_mm_s"
        if protocol.levels is not None and protocol.levels.parameter == "stroke_speed_mm_s":
            key = f"levels.values[{i}]"
        at = "" if level is None else f"at {protocol.levels.parameter} = {level:g}: "
        speed = spec.stroke_speed_mm_s
        drawing = max(make_stimulus(protocol, layout, d, level).duration_s
                      for d in protocol.digits)
        height_mm = spec.digit_height_pitch * layout.pitch_mm
        lag = speed * PAPER_LATENCY_S
        if drawing > WARN_DRAWING_S:
            found.append((key, f"{at}{speed!r} mm/s is slow: the longest digit takes "
                          f"{drawing:.0f} s to draw, holds included (over {WARN_DRAWING_S:g} s; "
                          "the shipped 20 mm/s: 2 to 5 s)"))
        elif lag > WARN_LAG_FRACTION * height_mm:
            found.append((key, f"{at}{speed!r} mm/s is fast: the device's "
                          f"{PAPER_LATENCY_S * 1e3:g} ms latency (the paper's) lags the bump by "
                          f"{lag:.1f} mm, over a quarter of the digit's {height_mm:.1f} mm "
                          "height (the shipped 20 mm/s: 1.5 mm)"))
    source = str(protocol.path)
    return tuple(locate_message(f"{source}: {key}: {message}", source, protocol.text)
                 for key, message in found)


def emit_warnings(protocol: Protocol) -> None:
    """Issue each of ``protocol.warnings`` as a :class:`~crs_study.errors.CrsStudyWarning`
    (the command line prints ``crs-study COMMAND: warning: ...``)."""
    import warnings

    from crs_study.errors import CrsStudyWarning

    for message in protocol.warnings:
        warnings.warn(message, CrsStudyWarning, stacklevel=2)


def consent_form_path(protocol: Protocol) -> Path:
    """The protocol's consent form: beside the protocol file, else shipped with crs-study."""
    from crs_study.paths import shipped_file

    candidate = protocol.path.parent / protocol.consent_form
    return candidate if candidate.is_file() else shipped_file(protocol.consent_form)


def _consent_check(protocol: Protocol, source: str) -> list[str]:
    from crs_study.consent import read_form

    try:
        form = read_form(consent_form_path(protocol))
    except (ConfigError, ConsentError) as exc:
        raise ProtocolError(f"{source}: study.consent_form: {_one_line(exc)}") from None
    if form.version != protocol.consent_form_version:
        raise ProtocolError(
            f"{source}: study.consent_form_version: expected the form's version "
            f"{form.version!r} ({protocol.consent_form}), got {protocol.consent_form_version!r}"
        )
    return [f"consent form {protocol.consent_form} version {form.version}"]


def analysis_plan_path(protocol: Protocol) -> Path | None:
    """The analysis plan's path when it exists (beside the protocol or shipped), else None."""
    from crs_study.paths import shipped_file

    candidate = protocol.path.parent / protocol.analysis_plan
    if candidate.is_file():
        return candidate
    try:
        return shipped_file(protocol.analysis_plan)
    except ConfigError:
        return None


# --------------------------------------------------------------------------------------------
# Line numbers for messages (protocols, strokes files)

_KEY_PATH = r"[A-Za-z0-9_\-]+(?:\[\d+\])*(?:\.[A-Za-z0-9_\-]+(?:\[\d+\])*)*"


def toml_syntax_message(source: str | Path, error: Exception, text: str = "") -> str:
    """``SOURCE:LINE: not valid TOML: ...`` for a :class:`tomllib.TOMLDecodeError` (the last
    line of ``text`` for an error at the end of the document)."""
    reason = _one_line(error)
    match = re.search(r"\(at line (\d+), column \d+\)$", reason)
    if match:
        line: int | None = int(match.group(1))
    elif reason.endswith("(at end of document)") and text:
        line = max(1, len(text.splitlines()))
    else:
        line = None
    where = f"{source}:{line}" if line else f"{source}"
    return f"{where}: not valid TOML: {reason}"


def locate_message(message: str, source: str | Path, text: str) -> str:
    """Insert the TOML line of the key a message names: ``file:LINE: key: ...``.

    ``message`` starts with ``source: `` then a key path (``design.repetitions: ...``,
    ``digits.3.strokes[0][2]: ...``, ``stimulus: missing required key 'digits'``,
    ``design: unknown key 'x'``); the line is that of the key, of the array element the
    indices name, or else of the key's table (:func:`find_line`). Other messages are
    returned unchanged.
    """
    source = str(source)
    prefix = f"{source}: "
    if not message.startswith(prefix):
        return message
    rest = message[len(prefix):]
    key_path = None
    match = re.match(rf"^({_KEY_PATH}): (unknown key|missing required key) '([^']*)'", rest)
    if match:
        key_path = f"{match.group(1)}.{match.group(3)}" if match.group(2) == "unknown key" \
            else match.group(1)
    else:
        match = re.match(r"^(unknown key|missing required key) '([^']*)'", rest)
        if match:
            key_path = match.group(2) if match.group(1) == "unknown key" else None
        else:
            match = re.match(rf"^({_KEY_PATH}): ", rest)
            key_path = match.group(1) if match else None
    line = find_line(text, key_path) if key_path else None
    return f"{source}:{line}: {rest}" if line else message




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
