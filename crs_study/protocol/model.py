"""The protocol model: frozen dataclasses, their closed choices and the checks of their fields.

A :class:`Protocol` holds one table of the file per part: ``[study]`` (its own fields),
``[stimulus]`` (:class:`~crs_study.stimuli.stimulus.StimulusSpec`, from the stimulus layer),
``[conditions]``, ``[design]`` (:class:`DesignSpec`), ``[responses]`` (:class:`ResponseSpec`)
and the optional ``[levels]`` (:class:`LevelSpec`) or ``[adaptive]`` (an ``AdaptiveSpec``;
``levels`` then lists every level its procedure can show). Every dataclass checks its fields on
construction: a wrong type or a value out of range is a one-line
:class:`~crs_study.errors.ProtocolError` carrying the protocol key at fault (``key_path``),
whether the value came from a file (:mod:`crs_study.protocol.loader` adds the file and the
line) or from Python (``dataclasses.replace(protocol.design, repetitions=0)``). Checks that
join two tables (a key per symbol, prompts only for listed conditions) and those that need the
file's folder (device files, set and strokes files) are the loader's.

The symbols shown come from a stimulus set (:mod:`crs_study.stimuli.sets`, the digits unless
``stimulus.set`` names another), which also spells the keys that name symbols
(:func:`table_keys`): ``digits``, ``digit_height_pitch``, ``digit_width_pitch`` and
``max_same_digit_run`` for the digit set, ``symbols``, ``symbol_height_pitch``, ... for every
other. The dataclasses hold the general names (``symbols``, ``symbol_height_pitch``) and the
set's name, so their errors name the key as the file spells it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal, get_args

from crs_study._toml import (
    integer_problem,
    number_problem,
    one_line_problem,
    path_problem,
    string_problem,
)
from crs_study.adaptive.spec import ADAPTIVE_TABLE_KEYS, WIDTH_TO_HEIGHT_RANGE, AdaptiveSpec
from crs_study.errors import ConfigError, ProtocolError
from crs_study.geometry.layout import Layout, load_layout
from crs_study.paths import shipped_file
from crs_study.rendering.render import CONDITIONS
from crs_study.stimuli.sets import DEFAULT_SET, set_column
from crs_study.stimuli.stimulus import (
    MIN_FRAME_RATE_HZ,
    MIN_STROKE_SPEED_MM_S,
    NUMBER_RANGES,
    PLACEMENTS,
    StimulusSpec,
)
from crs_study.stimuli.strokes import Symbol
from crs_study.stimuli.symbol_set import PAUSE_KEYS, StimulusSet, spell

__all__ = [
    "COUNTERBALANCING", "FEEDBACK", "LEVEL_PARAMETERS", "MAX_LEVELS", "MIN_FRAME_RATE_HZ",
    "MIN_STROKE_SPEED_MM_S", "OPTIONAL_KEYS", "ORDERINGS", "PAUSE_KEYS", "PLACEMENTS",
    "PRACTICE_IN", "TABLE_KEYS", "DesignSpec", "LevelSpec", "Protocol", "ResponseSpec",
    "StimulusSpec", "analysis_plan_path", "consent_form_path", "level_parameters",
    "one_line_problem", "table_keys",
]

Ordering = Literal["blocked", "interleaved"]
Counterbalancing = Literal["none", "alternate", "abba", "latin"]
PracticeIn = Literal["first-block", "every-block"]
Feedback = Literal["none", "practice", "all"]

#: Closed choices (``PLACEMENTS`` is the stimulus layer's).
ORDERINGS: tuple[str, ...] = get_args(Ordering)
COUNTERBALANCING: tuple[str, ...] = get_args(Counterbalancing)
PRACTICE_IN: tuple[str, ...] = get_args(PracticeIn)
FEEDBACK: tuple[str, ...] = get_args(Feedback)

#: Keys that may be left out (with the default used then). Every other key is required.
#: ``responses.keys`` left out: the set's own key for each symbol shown.
OPTIONAL_KEYS: dict[str, object] = {
    "study.title": "",
    "stimulus.set": DEFAULT_SET,
    "stimulus.strokes_file": None,
    "stimulus.offset_mm": (0.0, 0.0),
    "stimulus.stroke_pause_s": 0.4,
    "stimulus.start_hold_s": 0.3,
    "stimulus.end_hold_s": 0.3,
    "conditions.prompts": {},
    "design.practice_in": "first-block",
    "design.break_duration_s": 30.0,
    "responses.keys": None,
    "responses.time_limit_s": None,
    "responses.expected_response_s": 2.0,
}

#: The stimulus parameters a ``[levels]`` table may vary, in their general names: field ->
#: (dataset column, units). Both are spelled by the set (:func:`level_parameters`).
_LEVEL_FIELDS = {"symbol_height_pitch": ("symbol_height", "pitch"),
                 "stroke_speed_mm_s": ("stroke_speed", "mm/s")}


def level_parameters(set_name: str = DEFAULT_SET) -> dict[str, tuple[str, str, float, float]]:
    """The parameters a ``[levels]`` table of a protocol showing the set ``set_name`` may vary,
    as its file spells them: key -> (dataset column, units, min, max). The columns are those
    the analysis looks for (``crs_study.analysis.plan.KNOWN_LEVEL_COLUMNS``); the ranges are
    those of ``[stimulus]``."""
    column = set_column(set_name)
    return {spell(f, column): (spell(c, column), units, *NUMBER_RANGES[f][:2])
            for f, (c, units) in _LEVEL_FIELDS.items()}


#: :func:`level_parameters` of the default set (``digit_height_pitch``, ``stroke_speed_mm_s``).
LEVEL_PARAMETERS = level_parameters()
#: Most levels one protocol may declare (each multiplies the number of trials).
MAX_LEVELS = 20

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _fail(key_path: str, problem: str | None) -> None:
    if problem is not None:
        raise ProtocolError(problem, key_path=key_path)


def _freeze(instance: object, **values: object) -> None:
    """Store normalised field values (floats, tuples) on a frozen dataclass."""
    for name, value in values.items():
        object.__setattr__(instance, name, value)


@dataclass(frozen=True)
class LevelSpec:
    """The optional ``[levels]`` table: one stimulus parameter varied across trials.

    ``parameter`` is a key of :func:`level_parameters` of the protocol's set ``set_name``
    (it is then absent from ``[stimulus]``); ``values`` are its levels, distinct, in the
    protocol's order. Varying the size (``digit_height_pitch`` for the digit set,
    ``symbol_height_pitch`` for the others) scales the whole symbol: its width is
    ``width_to_height`` times the height (the shipped digits' shape 0.49 / 0.81 = 0.605), so
    the width key is absent too.
    """

    parameter: str
    values: tuple[float, ...]
    width_to_height: float | None = None
    set_name: str = DEFAULT_SET

    def __post_init__(self) -> None:
        parameters = level_parameters(self.set_name)
        _fail("levels.parameter", string_problem(self.parameter, choices=tuple(parameters)))
        _, units, low, high = parameters[self.parameter]
        values = self.values
        if not isinstance(values, list | tuple):
            _fail("levels.values", f"expected an array, got {values!r}")
        if not 2 <= len(values) <= MAX_LEVELS:
            _fail("levels.values", f"expected 2 to {MAX_LEVELS} levels of {self.parameter} "
                  f"({units}), got {list(values)!r}")
        for i, v in enumerate(values):
            if number_problem(v, minimum=low, maximum=high):
                _fail(f"levels.values[{i}]", f"expected a number {low:g} to {high:g} "
                      f"({self.parameter}), got {v!r}")
        floats = tuple(float(v) for v in values)
        if len(set(floats)) != len(floats):
            _fail("levels.values", f"a level appears twice in {list(values)!r}")
        ratio = self.width_to_height
        if self.varies_size:
            low_ratio, high_ratio = WIDTH_TO_HEIGHT_RANGE
            _fail("levels.width_to_height", number_problem(ratio, minimum=low_ratio,
                                                           maximum=high_ratio))
            ratio = float(ratio)
            for i, v in enumerate(floats):
                if not low <= v * ratio <= high:
                    _fail(f"levels.values[{i}]", f"the width {v * ratio:g} pitch "
                          f"(width_to_height {ratio:g} x {values[i]!r}) is outside "
                          f"{low:g}-{high:g}")
        elif ratio is not None:
            size = self.size_parameter(self.set_name)
            _fail("levels.width_to_height", f"only used with parameter = \"{size}\", got "
                  f"parameter = {self.parameter!r}")
        _freeze(self, values=floats, width_to_height=ratio)

    @staticmethod
    def size_parameter(set_name: str = DEFAULT_SET) -> str:
        """The parameter that varies the symbols' size, as the set spells it
        (``digit_height_pitch``, ``symbol_height_pitch``)."""
        return next(iter(level_parameters(set_name)))

    @property
    def varies_size(self) -> bool:
        """True when the levels are the symbols' height (the width follows)."""
        return self.parameter == self.size_parameter(self.set_name)

    @property
    def column(self) -> str:
        """The dataset column holding a trial's level (``digit_height``, ``stroke_speed``)."""
        return level_parameters(self.set_name)[self.parameter][0]

    @property
    def units(self) -> str:
        return level_parameters(self.set_name)[self.parameter][1]

    def spec_at(self, spec: StimulusSpec, level: float) -> StimulusSpec:
        """``spec`` with the varied parameter set to ``level`` (a varied height scales the
        width by ``width_to_height``)."""
        if self.varies_size:
            return replace(spec, symbol_height_pitch=level,
                           symbol_width_pitch=level * float(self.width_to_height or 1.0))
        return replace(spec, **{self.parameter: level})


@dataclass(frozen=True)
class DesignSpec:
    """The ``[design]`` table: how trials are repeated, ordered and paced. ``set_name`` is
    the protocol's stimulus set, which spells ``max_same_symbol_run`` in the file
    (``max_same_digit_run`` for the digit set)."""

    repetitions: int
    ordering: Ordering
    counterbalancing: Counterbalancing
    max_same_symbol_run: int
    practice_trials: int
    practice_in: PracticeIn
    break_every: int
    break_duration_s: float
    inter_trial_interval_s: float
    set_name: str = DEFAULT_SET

    def __post_init__(self) -> None:
        _fail("design.repetitions", integer_problem(self.repetitions, minimum=1, maximum=1000))
        _fail("design.ordering", string_problem(self.ordering, choices=ORDERINGS))
        _fail("design.counterbalancing", string_problem(self.counterbalancing,
                                                        choices=COUNTERBALANCING))
        if self.ordering == "interleaved" and self.counterbalancing != "none":
            _fail("design.counterbalancing", "interleaved conditions have no block order to "
                  f"counterbalance: expected \"none\", got {self.counterbalancing!r}")
        if self.counterbalancing == "abba" and self.repetitions < 2:
            _fail("design.counterbalancing", "\"abba\" splits the repetitions over two blocks "
                  f"per condition: needs repetitions >= 2, got {self.repetitions!r}")
        run_key = spell("max_same_symbol_run", set_column(self.set_name))
        _fail(f"design.{run_key}", integer_problem(self.max_same_symbol_run, minimum=1,
                                                   maximum=1000))
        _fail("design.practice_trials", integer_problem(self.practice_trials, minimum=0,
                                                        maximum=1000))
        _fail("design.practice_in", string_problem(self.practice_in, choices=PRACTICE_IN))
        _fail("design.break_every", integer_problem(self.break_every, minimum=0,
                                                    maximum=100000))
        _fail("design.break_duration_s", number_problem(self.break_duration_s, minimum=0.0,
                                                        maximum=3600.0))
        _fail("design.inter_trial_interval_s", number_problem(
            self.inter_trial_interval_s, minimum=0.0, maximum=60.0))
        _freeze(self, break_duration_s=float(self.break_duration_s),
                inter_trial_interval_s=float(self.inter_trial_interval_s))


@dataclass(frozen=True)
class ResponseSpec:
    """The ``[responses]`` table. ``keys[i]`` answers ``stimulus.symbols[i]``."""

    keys: tuple[str, ...]
    time_limit_s: float | None  # from stimulus offset; None: no limit
    feedback: Feedback
    expected_response_s: float

    def __post_init__(self) -> None:
        keys = self.keys
        if not isinstance(keys, list | tuple):
            _fail("responses.keys", f"expected an array, got {keys!r}")
        for i, key in enumerate(keys):
            if not isinstance(key, str) or len(key) != 1 or not key.isprintable() or key == " ":
                _fail(f"responses.keys[{i}]", f"expected a single printable character, got "
                      f"{key!r}")
        if len(set(keys)) != len(keys):
            _fail("responses.keys", f"a key appears twice in {list(keys)!r}")
        paused = sorted(set(keys) & PAUSE_KEYS)
        if paused:
            _fail("responses.keys", f"{paused[0]!r} pauses the session at the keypad (p pauses; "
                  f"q, Q and Escape end it); choose another key, got {list(keys)!r}")
        limit = self.time_limit_s
        if limit is not None:
            _fail("responses.time_limit_s", number_problem(limit, minimum=0.0,
                                                           exclusive_minimum=True,
                                                           maximum=3600.0))
            limit = float(limit)
        _fail("responses.feedback", string_problem(self.feedback, choices=FEEDBACK))
        _fail("responses.expected_response_s", number_problem(
            self.expected_response_s, minimum=0.0, maximum=3600.0))
        _freeze(self, keys=tuple(keys), time_limit_s=limit,
                expected_response_s=float(self.expected_response_s))


@dataclass(frozen=True)
class Protocol:
    """A validated protocol. Build with :func:`crs_study.protocol.load_protocol`.

    The ``[study]`` fields are checked here (``study.id``: letters, digits, ``.``, ``_``,
    ``-``; the others non-empty one-line strings), as are the conditions (registered in
    :data:`crs_study.rendering.render.CONDITIONS`, each once) and the prompts (non-empty, one per
    listed condition at most)."""

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
    #: a procedure chooses each test trial's level (``levels`` is then derived from it)
    adaptive: AdaptiveSpec | None = None
    #: what the device checks passed (:func:`crs_study.protocol.feasibility.check_on_device`)
    checks: tuple[str, ...] = field(default=(), compare=False)
    #: odd but legal values, one line each (``FILE:LINE: key: ...``;
    #: :func:`crs_study.protocol.odd_values.protocol_warnings`)
    warnings: tuple[str, ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        _fail("study.id", string_problem(self.study_id))
        if not _ID_RE.match(self.study_id):
            _fail("study.id", "expected letters, digits, '.', '_' or '-' (starting with a "
                  f"letter or digit), got {self.study_id!r}")
        _fail("study.version", one_line_problem(self.version))
        _fail("study.title", string_problem(self.title))
        for key in ("device", "consent_form", "consent_form_version", "analysis_plan"):
            check = one_line_problem if key == "consent_form_version" else path_problem
            _fail(f"study.{key}", check(getattr(self, key)))
        names = self.conditions
        if not isinstance(names, list | tuple):
            _fail("conditions.names", f"expected an array, got {names!r}")
        if len(names) < 1:
            _fail("conditions.names", "expected at least one condition, got []")
        for i, name in enumerate(names):
            if not isinstance(name, str) or name not in CONDITIONS:
                _fail(f"conditions.names[{i}]", f"expected a registered condition "
                      f"({', '.join(sorted(CONDITIONS))}), got {name!r}")
        if len(set(names)) != len(names):
            _fail("conditions.names", f"a condition appears twice in {list(names)!r}")
        for name, prompt in self.condition_prompts:
            if name not in names:
                _fail(f"conditions.prompts.{name}", f"expected a prompt for one of the "
                      f"conditions {list(names)!r}, got a prompt for {name!r}")
            _fail(f"conditions.prompts.{name}", one_line_problem(prompt))
        shown = self.stimulus.set_name
        for table, spec in (("design", self.design), ("levels", self.levels)):
            if spec is not None and spec.set_name != shown:
                _fail(f"{table}.set_name", f"expected the stimulus set {shown!r} (the key "
                      f"names follow it), got {spec.set_name!r}")
        _freeze(self, conditions=tuple(names),
                condition_prompts=tuple((n, p) for n, p in self.condition_prompts))
        if self.adaptive is not None:
            _check_adaptive(self)
            _freeze(self, levels=adaptive_levels(self.adaptive, self.stimulus.set_name))

    @property
    def level_values(self) -> tuple[float | None, ...]:
        """The levels of the varied parameter, or ``(None,)`` when nothing varies."""
        return self.levels.values if self.levels is not None else (None,)

    def stimulus_at(self, level: float | None) -> StimulusSpec:
        """The stimulus of a trial at ``level`` (``None``: the protocol's fixed stimulus)."""
        if level is None or self.levels is None:
            if level is not None:
                raise ProtocolError(f"the protocol varies no level, got level {level!r}",
                                    source=str(self.path))
            return self.stimulus
        if level not in self.levels.values:
            raise ProtocolError(f"expected one of {list(self.levels.values)}, got {level!r}",
                                source=str(self.path), key_path="levels.values")
        return self.levels.spec_at(self.stimulus, float(level))

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
    def symbols(self) -> tuple[Symbol, ...]:
        """The symbols trials show (``stimulus.symbols``; ``stimulus.digits`` in a digit
        protocol's file)."""
        return self.stimulus.symbols

    @property
    def symbol_set(self) -> StimulusSet:
        """The stimulus set drawn (:class:`~crs_study.stimuli.symbol_set.StimulusSet`)."""
        return self.stimulus.symbol_set

    @property
    def chance_rate(self) -> float:
        """Accuracy of guessing among the symbols shown: 1 / their number."""
        return 1.0 / len(self.symbols)

    def prompt(self, condition: str) -> str | None:
        """The experimenter's prompt before a block of ``condition`` (None when not given)."""
        return dict(self.condition_prompts).get(condition)

    def key_for(self, symbol: Symbol) -> str:
        """The response key of ``symbol``."""
        return self.responses.keys[self.symbols.index(symbol)]

    def symbol_for_key(self, key: str) -> Symbol | None:
        """The symbol that ``key`` answers, or None."""
        keys = self.responses.keys
        return self.symbols[keys.index(key)] if key in keys else None

    def layout(self) -> Layout:
        """The device's layout (cached per device file)."""
        return _layout(self.device)


def adaptive_levels(spec: AdaptiveSpec, set_name: str = DEFAULT_SET) -> LevelSpec:
    """Every level an adaptive procedure can show, as the :class:`LevelSpec` the pipeline reads
    (checked by the adaptive spec, so not by ``LevelSpec``: it may hold over MAX_LEVELS)."""
    levels = object.__new__(LevelSpec)
    _freeze(levels, parameter=spec.parameter, values=spec.shown_levels(),
            width_to_height=spec.width_to_height, set_name=set_name)
    return levels


def _check_adaptive(protocol: Protocol) -> None:
    """What ``[adaptive]`` asks of the other tables
    (:meth:`~crs_study.adaptive.spec.AdaptiveSpec.check_protocol`)."""
    if not isinstance(protocol.adaptive, AdaptiveSpec):
        _fail("adaptive", f"expected an adaptive spec, got {protocol.adaptive!r}")
    set_name = protocol.stimulus.set_name
    protocol.adaptive.check_protocol(
        protocol.design.ordering, protocol.design.repetitions, tuple(level_parameters(set_name)),
        LevelSpec.size_parameter(set_name), len(protocol.symbols), protocol.symbol_set.plural)


def table_keys(set_name: str = DEFAULT_SET) -> dict[str, tuple[str, ...]]:
    """The keys of each table (``""``: the top level) of a protocol showing the set
    ``set_name``, as the set spells them; a key outside them is refused at once."""
    column = set_column(set_name)

    def keys(cls: type) -> tuple[str, ...]:
        return tuple("set" if f.name == "set_name" else spell(f.name, column)
                     for f in fields(cls) if f.name != "set_name" or cls is StimulusSpec)

    return {
        "": ("study", "stimulus", "conditions", "design", "responses", "levels", "adaptive"),
        "study": ("id", "version", "title", "device", "consent_form", "consent_form_version",
                  "analysis_plan"),
        "stimulus": keys(StimulusSpec),
        "conditions": ("names", "prompts"),
        "design": keys(DesignSpec),
        "responses": keys(ResponseSpec),
        "levels": keys(LevelSpec),
        **ADAPTIVE_TABLE_KEYS,
    }


#: :func:`table_keys` of the default set.
TABLE_KEYS: dict[str, tuple[str, ...]] = table_keys()

_LAYOUTS: dict[str, Layout] = {}


def _layout(device: str) -> Layout:
    if device not in _LAYOUTS:
        _LAYOUTS[device] = load_layout(device)
    return _LAYOUTS[device]


def consent_form_path(protocol: Protocol) -> Path:
    """The protocol's consent form: beside the protocol file, else shipped with crs-study."""
    candidate = protocol.path.parent / protocol.consent_form
    return candidate if candidate.is_file() else shipped_file(protocol.consent_form)


def analysis_plan_path(protocol: Protocol) -> Path | None:
    """The analysis plan's path when it exists (beside the protocol or shipped), else None."""
    candidate = protocol.path.parent / protocol.analysis_plan
    if candidate.is_file():
        return candidate
    try:
        return shipped_file(protocol.analysis_plan)
    except ConfigError:
        return None

