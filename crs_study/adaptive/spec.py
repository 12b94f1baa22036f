"""The ``[adaptive]`` table of a protocol: which level adapts, and by which procedure.

One stimulus parameter (``digit_height_pitch`` or ``stroke_speed_mm_s``) follows a procedure
in every block: each block (one condition, the skeleton mounted by hand) runs its own track
of ``trials`` test trials. The procedure works on a *difficulty axis* ``u``: ``u = level``
(``scale = "linear"``) or ``u = log10(level)`` (``"log"``), negated for the stroke speed, so
that a smaller ``u`` is always harder (a smaller digit, a faster stroke). Both procedures
show levels of one grid: ``levels`` levels evenly spaced on the scale from ``min`` to ``max``
(:meth:`AdaptiveSpec.grid`), so every level a session can show is known in advance and
``validate`` checks each on the device.

- ``staircase`` (:class:`StaircaseSpec`): PsychoPy's ``StairHandler`` rules (1-up/1-down
  until the first reversal, then n-down/1-up; step ``steps[k]`` after k reversals), steps
  counted in grid levels (so a PsychoPy ``"log"`` step of 0.1 is one level of a grid spaced
  0.1 log units apart), or weighted 1-up/1-down steps for a target rate (Kaernbach 1991: the
  easier step is ``target / (1 - target)`` times the harder one, which must come out whole).
- ``quest-plus`` (:class:`QuestPlusSpec`): the ``questplus`` package's QUEST+ (Watson
  2017) over the grid, with a Weibull function of ``u`` whose guess rate is one over the
  number of digits.

Every error is a one-line :class:`~crs_study.errors.ProtocolError` carrying the key at fault
(the loader adds the file and the line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal, get_args

from crs_study._toml import integer_problem, number_problem, string_problem
from crs_study.errors import ProtocolError
from crs_study.stimuli.stimulus import NUMBER_RANGES

Procedure = Literal["staircase", "quest-plus"]
Scale = Literal["linear", "log"]
Rule = Literal["1-up-2-down", "1-up-3-down", "weighted"]
PROCEDURES: tuple[str, ...] = get_args(Procedure)
SCALES: tuple[str, ...] = get_args(Scale)
RULES: tuple[str, ...] = get_args(Rule)

#: Parameters that may adapt, as a protocol file spells them (the size by its stimulus set:
#: ``digit_height_pitch`` for digits, ``symbol_height_pitch`` for other sets): key -> +1 when
#: a larger value is easier (a bigger symbol), -1 when a smaller one is (a slower stroke).
EASIER: dict[str, int] = {"digit_height_pitch": 1, "symbol_height_pitch": 1,
                          "stroke_speed_mm_s": -1}
#: The rate a fixed rule converges to (Levitt 1971, Table I): p^n = 1/2.
RULE_TARGETS: dict[str, float] = {"1-up-2-down": 0.5 ** 0.5, "1-up-3-down": 0.5 ** (1 / 3)}
RULE_DOWN: dict[str, int] = {"1-up-2-down": 2, "1-up-3-down": 3, "weighted": 1}
#: Most levels of the grid (each is checked on the device by validate, about 0.4 s each).
MAX_ADAPTIVE_LEVELS = 40
#: Levels are rounded to this many decimals: what the trial file stores (``format_value``
#: writes 6), so a level read back from the file is the level shown.
LEVEL_DECIMALS = 6
MAX_TRIALS = 1000
#: The range of ``width_to_height`` (symbol width over height; ``[levels]`` shares it).
WIDTH_TO_HEIGHT_RANGE = (0.05, 20.0)


def _fail(key_path: str, problem: str | None) -> None:
    if problem is not None:
        raise ProtocolError(problem, key_path=key_path)


def _numbers(key_path: str, values: object, *, minimum: float, maximum: float,
             exclusive_minimum: bool = False) -> tuple[float, ...]:
    if not isinstance(values, list | tuple) or not values:
        _fail(key_path, f"expected a non-empty array of numbers, got {values!r}")
    for i, v in enumerate(values):
        _fail(f"{key_path}[{i}]", number_problem(v, minimum=minimum, maximum=maximum,
                                                 exclusive_minimum=exclusive_minimum))
    return tuple(float(v) for v in values)


def round_level(level: float) -> float:
    """``level`` as the trial file stores it (:data:`LEVEL_DECIMALS` decimals)."""
    return round(float(level), LEVEL_DECIMALS)


@dataclass(frozen=True)
class StaircaseSpec:
    """``[adaptive.staircase]``: rule, start level, steps (in grid levels) and stops."""

    rule: Rule
    start: float
    steps: tuple[int, ...]
    stop_reversals: int = 0  # 0: stop after the block's trials only
    estimate_reversals: int = 6

    def __post_init__(self) -> None:
        _fail("adaptive.staircase.rule", string_problem(self.rule, choices=RULES))
        _fail("adaptive.staircase.start", number_problem(self.start, minimum=0.0,
                                                         exclusive_minimum=True))
        steps = self.steps
        if not isinstance(steps, list | tuple) or not steps:
            _fail("adaptive.staircase.steps", f"expected a non-empty array of whole numbers "
                  f"of grid levels, got {steps!r}")
        for i, step in enumerate(steps):
            _fail(f"adaptive.staircase.steps[{i}]", integer_problem(
                step, minimum=1, maximum=MAX_ADAPTIVE_LEVELS))
        _fail("adaptive.staircase.stop_reversals", integer_problem(
            self.stop_reversals, minimum=0, maximum=MAX_TRIALS))
        _fail("adaptive.staircase.estimate_reversals", integer_problem(
            self.estimate_reversals, minimum=1, maximum=MAX_TRIALS))
        if self.stop_reversals and self.estimate_reversals > self.stop_reversals:
            _fail("adaptive.staircase.estimate_reversals", "expected at most stop_reversals "
                  f"({self.stop_reversals}) reversals to average, got "
                  f"{self.estimate_reversals!r}")
        object.__setattr__(self, "start", float(self.start))
        object.__setattr__(self, "steps", tuple(steps))

    @property
    def n_down(self) -> int:
        return RULE_DOWN[self.rule]


def _keys(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))


@dataclass(frozen=True)
class QuestPlusSpec:
    """``[adaptive.quest_plus]``: the parameter grid of QUEST+ (Watson 2017).

    ``thresholds`` threshold values evenly spaced on the scale from ``min`` to ``max``;
    ``slopes`` (Weibull beta on the difficulty axis, per log10 unit on a log scale) and
    ``lapse_rates``. The stimulus grid is the ``[adaptive]`` one."""

    thresholds: int
    slopes: tuple[float, ...]
    lapse_rates: tuple[float, ...]

    def __post_init__(self) -> None:
        _fail("adaptive.quest_plus.thresholds", integer_problem(self.thresholds, minimum=2,
                                                                maximum=200))
        slopes = _numbers("adaptive.quest_plus.slopes", self.slopes, minimum=0.0,
                          maximum=1000.0, exclusive_minimum=True)
        lapses = _numbers("adaptive.quest_plus.lapse_rates", self.lapse_rates, minimum=0.0,
                          maximum=0.5)
        for key, values in (("slopes", slopes), ("lapse_rates", lapses)):
            if len(set(values)) != len(values):
                _fail(f"adaptive.quest_plus.{key}", f"a value appears twice in {list(values)}")
        object.__setattr__(self, "slopes", slopes)
        object.__setattr__(self, "lapse_rates", lapses)


@dataclass(frozen=True)
class AdaptiveSpec:
    """The ``[adaptive]`` table (see the module docstring and protocols/README.md).

    ``minimum``/``maximum`` bound the level (keys ``min``, ``max``); ``target_rate`` is the
    identification rate whose level every threshold names (a fixed staircase rule implies
    it); ``practice_level`` the level of practice trials (None: the easiest level);
    ``width_to_height`` the digit's shape when its height adapts."""

    parameter: str
    procedure: Procedure
    trials: int
    minimum: float
    maximum: float
    scale: Scale
    levels: int
    target_rate: float | None = None
    practice_level: float | None = None
    width_to_height: float | None = None
    staircase: StaircaseSpec | None = None
    quest_plus: QuestPlusSpec | None = None

    def __post_init__(self) -> None:
        _fail("adaptive.parameter", string_problem(self.parameter, choices=tuple(EASIER)))
        _fail("adaptive.procedure", string_problem(self.procedure, choices=PROCEDURES))
        _fail("adaptive.trials", integer_problem(self.trials, minimum=2, maximum=MAX_TRIALS))
        _fail("adaptive.scale", string_problem(self.scale, choices=SCALES))
        _fail("adaptive.levels", integer_problem(self.levels, minimum=3,
                                                 maximum=MAX_ADAPTIVE_LEVELS))
        low, high = NUMBER_RANGES[self.range_key][:2]
        for key, value in (("min", self.minimum), ("max", self.maximum)):
            _fail(f"adaptive.{key}", number_problem(value, minimum=low, maximum=high))
        if not float(self.minimum) < float(self.maximum):
            _fail("adaptive.max", f"expected a level above min = {self.minimum!r}, got "
                  f"{self.maximum!r}")
        object.__setattr__(self, "minimum", float(self.minimum))
        object.__setattr__(self, "maximum", float(self.maximum))
        if self.procedure == "staircase":
            if not isinstance(self.staircase, StaircaseSpec):
                _fail("adaptive.staircase", "missing: procedure = \"staircase\" needs an "
                      "[adaptive.staircase] table")
            if self.quest_plus is not None:
                _fail("adaptive.quest_plus", "only used with procedure = \"quest-plus\"")
        else:
            if not isinstance(self.quest_plus, QuestPlusSpec):
                _fail("adaptive.quest_plus", "missing: procedure = \"quest-plus\" needs an "
                      "[adaptive.quest_plus] table")
            if self.staircase is not None:
                _fail("adaptive.staircase", "only used with procedure = \"staircase\"")
        self._check_target()
        if self.practice_level is not None:
            _fail("adaptive.practice_level", self._level_problem(self.practice_level))
            object.__setattr__(self, "practice_level", float(self.practice_level))
        if self.width_to_height is not None:  # a number now: the stimulus is sized by it next
            _fail("adaptive.width_to_height", number_problem(
                self.width_to_height, minimum=WIDTH_TO_HEIGHT_RANGE[0],
                maximum=WIDTH_TO_HEIGHT_RANGE[1]))
            object.__setattr__(self, "width_to_height", float(self.width_to_height))
        self.grid()  # distinct levels
        if self.staircase is not None:
            self._check_staircase()

    def _check_staircase(self) -> None:
        stair = self.staircase
        _fail("adaptive.staircase.start", self._level_problem(stair.start))
        grid = self.grid()
        if round_level(stair.start) not in grid:
            nearest = sorted(grid, key=lambda v: abs(v - stair.start))[:2]
            _fail("adaptive.staircase.start", f"expected a level of the grid ({self.levels} "
                  f"levels from {self.minimum:g} to {self.maximum:g} on a {self.scale} "
                  f"scale; nearest {sorted(nearest)}), got {stair.start!r}")
        for i, step in enumerate(stair.steps):
            if step >= self.levels:
                _fail(f"adaptive.staircase.steps[{i}]", f"a step of {step} levels cannot "
                      f"move within a grid of {self.levels} levels; expected 1 to "
                      f"{self.levels - 1}")
            easier = step * self.easier_ratio
            if abs(easier - round(easier)) > 1e-6:
                _fail("adaptive.target_rate", f"weighted steps: the easier step is "
                      f"{self.rate:g} / (1 - {self.rate:g}) = {self.easier_ratio:.4g} times "
                      f"the harder one, {easier:.4g} levels for steps[{i}] = {step}; expected "
                      "a whole number (e.g. target 0.75 with any step, 0.8 with any step)")

    def check_protocol(self, ordering: str, repetitions: int, parameters: tuple[str, ...],
                       size_parameter: str, n_symbols: int, plural: str) -> None:
        """What ``[adaptive]`` asks of the protocol's other tables: blocked conditions, one
        block (one track) each, a parameter its stimulus set spells, a target above chance,
        the symbols' shape when their height adapts (the width stays in range)."""
        if ordering != "blocked":
            _fail("design.ordering", "an adaptive procedure runs one track per block (the "
                  f"skeleton is mounted by hand): expected \"blocked\", got {ordering!r}")
        if repetitions != 1:
            _fail("design.repetitions", "with [adaptive], each condition's block is one track "
                  f"of adaptive.trials trials: expected 1, got {repetitions!r}")
        _fail("adaptive.parameter", string_problem(self.parameter, choices=parameters))
        chance = 1.0 / n_symbols
        if self.rate <= chance:
            key = "adaptive.target_rate" if self.target_rate is not None else \
                "adaptive.staircase.rule"
            _fail(key, f"the target rate {self.rate:.4g} is at or below chance (1 / "
                  f"{n_symbols} {plural} = {chance:.4g}); expected a rate above it")
        ratio = self.width_to_height
        if self.parameter == size_parameter:
            _fail("adaptive.width_to_height", number_problem(
                ratio, minimum=WIDTH_TO_HEIGHT_RANGE[0], maximum=WIDTH_TO_HEIGHT_RANGE[1]))
            low, high = NUMBER_RANGES["symbol_width_pitch"][:2]
            for key, level in (("min", self.minimum), ("max", self.maximum)):
                if not low <= level * ratio <= high:
                    _fail(f"adaptive.{key}", f"the width {level * ratio:g} pitch "
                          f"(width_to_height {ratio:g} x {level:g}) is outside {low:g}-{high:g}")
        elif ratio is not None:
            _fail("adaptive.width_to_height", f"only used with parameter = "
                  f"\"{size_parameter}\", got parameter = {self.parameter!r}")

    def _level_problem(self, value: object) -> str | None:
        return number_problem(value, minimum=self.minimum, maximum=self.maximum)

    def _check_target(self) -> None:
        fixed = self.staircase is not None and self.staircase.rule in RULE_TARGETS
        if fixed:
            if self.target_rate is not None:
                _fail("adaptive.target_rate", f"set by rule = {self.staircase.rule!r} "
                      f"({RULE_TARGETS[self.staircase.rule]:.4f}); remove it, or use rule = "
                      f"\"weighted\", got {self.target_rate!r}")
            return
        if self.target_rate is None:
            _fail("adaptive.target_rate", "missing: the identification rate the threshold "
                  "names (e.g. 0.75)")
        _fail("adaptive.target_rate", number_problem(self.target_rate, minimum=0.0,
                                                     maximum=1.0, exclusive_minimum=True))
        if self.target_rate >= 1.0:
            _fail("adaptive.target_rate", f"expected a rate below 1, got {self.target_rate!r}")
        object.__setattr__(self, "target_rate", float(self.target_rate))
        if self.quest_plus is not None and self.target_rate >= 1.0 - max(
                self.quest_plus.lapse_rates):
            _fail("adaptive.target_rate", f"expected a rate below 1 - the largest lapse rate "
                  f"({1.0 - max(self.quest_plus.lapse_rates):g}), got {self.target_rate!r}")

    @property
    def range_key(self) -> str:
        """The stimulus field whose range bounds the levels (the size's general name)."""
        return "symbol_height_pitch" if self.parameter.endswith("_height_pitch") \
            else self.parameter

    # --- the difficulty axis ---
    @property
    def easier(self) -> int:
        return EASIER[self.parameter]

    @property
    def rate(self) -> float:
        """The target identification rate (implied by a fixed staircase rule)."""
        if self.staircase is not None and self.staircase.rule in RULE_TARGETS:
            return RULE_TARGETS[self.staircase.rule]
        return float(self.target_rate)

    def to_axis(self, level: float) -> float:
        """``u`` of ``level``: larger is easier (see the module docstring)."""
        value = math.log10(level) if self.scale == "log" else float(level)
        return self.easier * value

    def from_axis(self, u: float) -> float:
        value = self.easier * u
        return 10.0 ** value if self.scale == "log" else value

    @property
    def axis_bounds(self) -> tuple[float, float]:
        """``(hardest, easiest)`` on the difficulty axis."""
        ends = sorted((self.to_axis(self.minimum), self.to_axis(self.maximum)))
        return ends[0], ends[1]

    @property
    def easiest_level(self) -> float:
        return self.maximum if self.easier > 0 else self.minimum

    @property
    def practice(self) -> float:
        """The level of practice trials."""
        return self.practice_level if self.practice_level is not None else self.easiest_level

    @property
    def easier_ratio(self) -> float:
        """Easier step over harder step: 1, or ``rate / (1 - rate)`` for weighted steps."""
        if self.staircase is None or self.staircase.rule != "weighted":
            return 1.0
        return self.rate / (1.0 - self.rate)

    def grid_axis(self) -> tuple[float, ...]:
        """The grid on the difficulty axis, hardest first."""
        low, high = self.axis_bounds
        n = self.levels
        return tuple(low + (high - low) * i / (n - 1) for i in range(n))

    def grid(self) -> tuple[float, ...]:
        """The grid's levels (as stored: 6 decimals), hardest first (smallest digit or
        fastest stroke)."""
        levels = tuple(round_level(self.from_axis(u)) for u in self.grid_axis())
        if len(set(levels)) != len(levels):
            _fail("adaptive.levels", f"{self.levels} levels from {self.minimum:g} to "
                  f"{self.maximum:g} are closer than the 6 decimals the trial file keeps; "
                  "expected fewer levels")
        return levels

    def shown_levels(self) -> tuple[float, ...]:
        """Every level a session can show, ascending: the grid and the practice level."""
        return tuple(sorted(set(self.grid()) | {round_level(self.practice)}))


def spec_from_table(table: dict) -> AdaptiveSpec:
    """The :class:`AdaptiveSpec` of an ``[adaptive]`` table as a session's recorded protocol
    text holds it (checked when the session ran; the analysis replays its tracks with it).
    Raises :class:`ProtocolError`, ``KeyError`` or ``TypeError`` for a table that is not one.
    """
    stair, quest = table.get("staircase"), table.get("quest_plus")
    return AdaptiveSpec(
        table["parameter"], table["procedure"], table["trials"], table["min"], table["max"],
        table["scale"], table["levels"], target_rate=table.get("target_rate"),
        practice_level=table.get("practice_level"),
        width_to_height=table.get("width_to_height"),
        staircase=None if stair is None else StaircaseSpec(**stair),
        quest_plus=None if quest is None else QuestPlusSpec(**quest))


#: The keys of a protocol's ``[adaptive]`` table and its sub-tables (the protocol model's
#: ``table_keys``).
ADAPTIVE_TABLE_KEYS: dict[str, tuple[str, ...]] = {
    "adaptive": ("parameter", "procedure", "trials", "min", "max", "scale", "levels",
                 "target_rate", "practice_level", "width_to_height", "staircase", "quest_plus"),
    "adaptive.staircase": _keys(StaircaseSpec),
    "adaptive.quest_plus": _keys(QuestPlusSpec),
}
