"""Analysis plans: what is tested and how, declared before the data exist.

A plan is a TOML file under ``analysis/`` read strictly through :class:`crs_study._toml.Section`:
an unknown key, a wrong type or a value outside its range is a one-line
:class:`~crs_study.errors.PlanError` naming the file, the key path and the value received.
Every table and every key is optional except ``[plan].name``; the defaults are those of
``analysis/digit_identification.toml``, documented in ``analysis/README.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from crs_study._toml import Section, read_toml
from crs_study.analysis.glmm_core import MAX_QUADRATURE
from crs_study.analysis.structure import (
    REDUCTION_STEPS,
    SINGULAR_FIT_RULES,
    STRUCTURES,
    RandomSpec,
    written_terms,
)
from crs_study.errors import AnalysisError, PlanError
from crs_study.paths import shipped_file

TIMEOUT_POLICIES = ("exclude", "count_as_error")
#: The primary p: the LR statistic against chi2, its parametric bootstrap, or the bootstrap
#: below a number of participants (:mod:`crs_study.analysis.bootstrap`).
P_VALUE_RULES = ("auto", "chi2", "bootstrap")
GLMM_METHODS = ("laplace", "agq")
#: The symbol's random intercept and per-symbol comparisons have two names, the same thing:
#: ``symbol`` (any stimulus set) and ``digit``, as plans written for the digit set say (it
#: names the symbol column ``digit``; :mod:`crs_study.dataset.schema`). Either groups by the
#: symbol column of the data, whatever it is called.
SYMBOL_EFFECTS = ("symbol", "digit")
PER_SYMBOL_TESTS = ("per_symbol", "per_digit")
RANDOM_EFFECTS = ("participant", *SYMBOL_EFFECTS)
SECONDARY_TESTS = ("paired_t", "wilcoxon", "mcnemar", *PER_SYMBOL_TESTS)
#: The secondary tests a plan runs when it names none (all, each once).
DEFAULT_SECONDARY_TESTS = SECONDARY_TESTS[:4]
CORRECTIONS = ("holm", "bonferroni", "holm-sidak", "hommel", "fdr_bh", "none")
BIAS_CORRECTIONS = ("miller-madow", "none")
BOOTSTRAP_UNITS = ("participant", "trial")
PSYCHOMETRIC_FUNCTIONS = ("logistic", "weibull")
REPORT_FORMATS = ("markdown", "html")
CHARTS = ("accuracy", "confusion", "speed_accuracy", "caf", "psychometric", "tracks",
          "thresholds")
#: Columns a protocol may vary; the first present with more than one value is the level
#: (``digit_height`` in a digit dataset, ``symbol_height`` in any other; the last two for
#: data written by other tools).
KNOWN_LEVEL_COLUMNS = ("digit_height", "symbol_height", "stroke_speed", "digit_size",
                       "stimulus_level")


def known_level_columns(symbol_column: str | None) -> tuple[str, ...]:
    """The level columns to look for, in order, in trials naming the symbol ``symbol_column``
    (``digit``: the columns looked for before stimulus sets; ``symbol``: its own size column
    ``symbol_height`` instead of ``digit_height``); every known one when None."""
    if symbol_column is None:
        return KNOWN_LEVEL_COLUMNS
    size = f"{symbol_column}_height"
    return tuple(c for c in KNOWN_LEVEL_COLUMNS
                 if c == size or c not in ("digit_height", "symbol_height"))


@dataclass(frozen=True)
class Exclusions:
    """Which trials are left out before any analysis (counts are reported per reason)."""

    practice: bool = True
    device_faults: bool = True
    timeouts: str = "exclude"          # or "count_as_error"
    anticipation_s: float = 0.15       # response_time below this is an anticipation; 0 = off
    max_response_time_s: float = 0.0   # response_time above this is excluded; 0 = off
    rt_column: str = "response_time"


@dataclass(frozen=True)
class PrimaryTest:
    """The confirmatory test: ``correct ~ condition`` with the random part the plan states
    (:mod:`crs_study.analysis.structure`): by default the maximal model,
    ``(1 + condition | participant) [+ (1 + condition | symbol)]``, reduced by the stated
    rule when its fit is singular."""

    outcome: str = "correct"
    test: str = "glmm"
    method: str = "laplace"
    n_quadrature: int = 25
    random_effects: tuple[str, ...] = ("participant",)
    reference: str = ""                # the reference condition; "" = first of plan.conditions
    structure: str = "maximal"         # "maximal", "intercepts" or an lme4 random part
    singular_fit: str = "keep"         # or "reduce"
    reduction: tuple[str, ...] = REDUCTION_STEPS
    p_value: str = "auto"              # "chi2", "bootstrap" or "auto"
    bootstrap_below: int = 20          # auto: the bootstrap with fewer participants
    bootstrap_replicates: int = 1000
    bootstrap_stop_after: int = 20     # sequential: stop once this many reached the LR

    @property
    def random_spec(self) -> RandomSpec:
        """The random part as :func:`~crs_study.analysis.primary.fit_primary` takes it."""
        return RandomSpec(self.random_effects, self.structure, self.singular_fit,
                          self.reduction)

    def model_options(self) -> dict:
        """The keyword arguments of :func:`~crs_study.analysis.primary.primary_test` and
        ``fit_primary`` that describe the random part."""
        return {"structure": self.structure, "singular_fit": self.singular_fit,
                "reduction": self.reduction}

    def test_options(self) -> dict:
        """The keyword arguments of :func:`~crs_study.analysis.primary.primary_test` that
        describe the test: the random part and the rule for the primary p."""
        return {**self.model_options(), "p_value": self.p_value,
                "bootstrap_below": self.bootstrap_below,
                "bootstrap_replicates": self.bootstrap_replicates,
                "bootstrap_stop_after": self.bootstrap_stop_after}


@dataclass(frozen=True)
class SecondaryTests:
    tests: tuple[str, ...] = DEFAULT_SECONDARY_TESTS
    correction: str = "holm"


@dataclass(frozen=True)
class ConfusionPlan:
    bias_correction: str = "miller-madow"
    bootstrap: int = 2000
    bootstrap_unit: str = "participant"


@dataclass(frozen=True)
class SpeedAccuracyPlan:
    caf_bins: int = 5


@dataclass(frozen=True)
class PsychometricPlan:
    level_column: str = "auto"         # "auto" looks for KNOWN_LEVEL_COLUMNS
    function: str = "logistic"
    lapse_max: float = 0.1
    threshold: float = 0.5             # F(level) = threshold, between guess and 1 - lapse
    bootstrap: int = 200


@dataclass(frozen=True)
class ReportPlan:
    format: str = "markdown"
    charts: tuple[str, ...] = CHARTS


@dataclass(frozen=True)
class AnalysisPlan:
    """A parsed analysis plan (see ``analysis/README.md`` for every key)."""

    name: str
    description: str = ""
    alpha: float = 0.05
    conditions: tuple[str, ...] = ()   # order of conditions; empty = as found in the data
    chance: float = 0.0                # 0 = 1 / number of symbols in the data
    seed: int = 20260101
    primary: PrimaryTest = field(default_factory=PrimaryTest)
    exclusions: Exclusions = field(default_factory=Exclusions)
    secondary: SecondaryTests = field(default_factory=SecondaryTests)
    confusion: ConfusionPlan = field(default_factory=ConfusionPlan)
    speed_accuracy: SpeedAccuracyPlan = field(default_factory=SpeedAccuracyPlan)
    psychometric: PsychometricPlan = field(default_factory=PsychometricPlan)
    report: ReportPlan = field(default_factory=ReportPlan)
    source: str = ""

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str | Path = "<plan>") -> AnalysisPlan:
        """Build a plan from parsed TOML, rejecting unknown keys and out-of-range values."""
        root = Section(data, source, error=PlanError)
        head = root.table("plan")
        name = head.string("name")
        description = head.string("description", "")
        alpha = head.number("alpha", 0.05, minimum=0.0, exclusive_minimum=True, maximum=0.5)
        conditions = _strings(head, "conditions", (), unique=True)
        chance = head.number("chance", 0.0, minimum=0.0, maximum=1.0)
        if chance == 1.0:
            raise head.fail("chance", "expected a probability below 1, got 1.0")
        seed = head.integer("seed", 20260101, minimum=0)
        head.done()

        primary = _primary(root.table("primary", {}), conditions)
        exclusions = _exclusions(root.table("exclusions", {}))
        secondary = _secondary(root.table("secondary", {}))
        confusion = _confusion(root.table("confusion", {}))
        speed = root.table("speed_accuracy", {})
        speed_plan = SpeedAccuracyPlan(caf_bins=speed.integer("caf_bins", 5, minimum=2,
                                                             maximum=20))
        speed.done()
        psychometric = _psychometric(root.table("psychometric", {}))
        report = root.table("report", {})
        report_plan = ReportPlan(
            format=report.string("format", "markdown", choices=REPORT_FORMATS),
            charts=_strings(report, "charts", CHARTS, choices=CHARTS, unique=True),
        )
        report.done()
        root.done()
        return cls(name=name, description=description, alpha=alpha, conditions=conditions,
                   chance=chance, seed=seed, primary=primary, exclusions=exclusions,
                   secondary=secondary, confusion=confusion, speed_accuracy=speed_plan,
                   psychometric=psychometric, report=report_plan, source=str(source))

    def reference_condition(self, present: list[str]) -> str:
        """The reference condition: the plan's, else the first planned, else the first present."""
        if self.primary.reference:
            return self.primary.reference
        if self.conditions:
            return self.conditions[0]
        return present[0]


def load_plan(path: str | Path) -> AnalysisPlan:
    """Read and validate an analysis plan file (``analysis/*.toml``)."""
    return AnalysisPlan.from_dict(read_toml(path, PlanError), Path(path).name)


def default_plan_path() -> Path:
    """The shipped plan that goes with the default protocol."""
    return shipped_file("analysis/digit_identification.toml")


def _strings(section: Section, key: str, default: tuple[str, ...], *,
             choices: tuple[str, ...] | None = None, unique: bool = False) -> tuple[str, ...]:
    if not section.has(key):
        section.raw(key, None)
        return default
    values = section.array(key)
    for value in values:
        if not isinstance(value, str) or not value:
            raise section.fail(key, f"expected an array of non-empty strings, got {values!r}")
        if choices is not None and value not in choices:
            raise section.fail(key, f"expected values among {list(choices)}, got {value!r}")
    if unique and len(set(values)) != len(values):
        raise section.fail(key, f"expected no repeated values, got {values!r}")
    return tuple(values)


def _primary(section: Section, conditions: tuple[str, ...]) -> PrimaryTest:
    outcome = section.string("outcome", "correct", choices=("correct",))
    test = section.string("test", "glmm", choices=("glmm",))
    method = section.string("method", "laplace", choices=GLMM_METHODS)
    n_quadrature = section.integer("n_quadrature", 25, minimum=1, maximum=MAX_QUADRATURE)
    structure = section.string("structure", "maximal")
    written = structure not in STRUCTURES
    effects_given = section.has("random_effects")
    effects = _strings(section, "random_effects", ("participant",), choices=RANDOM_EFFECTS,
                       unique=True)
    if written and not effects_given:
        try:
            effects = tuple(dict.fromkeys(g for g, *_ in written_terms(structure)))
        except AnalysisError as exc:
            raise section.fail("structure", str(exc)) from None
    if "participant" not in effects:
        raise section.fail("random_effects",
                           f"expected 'participant' among the random effects, got {list(effects)}")
    _one_name(section, "random_effects", effects, SYMBOL_EFFECTS)
    singular_fit = section.string("singular_fit", "keep", choices=SINGULAR_FIT_RULES)
    reduction = _strings(section, "reduction", REDUCTION_STEPS, choices=REDUCTION_STEPS,
                         unique=True)
    try:
        spec = RandomSpec(effects, structure, singular_fit, reduction)
    except AnalysisError as exc:
        raise section.fail("structure", str(exc)) from None
    single_intercept = len(effects) == 1 and (structure == "intercepts" or (
        written and written_terms(structure)[0][1:3] == (True, False)))
    if method == "agq" and not single_intercept:
        raise section.fail("method", "adaptive quadrature needs a single random intercept; "
                                     f"got 'agq' with random_effects {list(effects)} and "
                                     f"structure {structure!r}")
    reference = section.string("reference", "")
    if reference and conditions and reference not in conditions:
        raise section.fail("reference",
                           f"expected one of plan.conditions {list(conditions)}, got {reference!r}")
    p_value = section.string("p_value", "auto", choices=P_VALUE_RULES)
    below = section.integer("bootstrap_below", 20, minimum=0, maximum=100_000)
    replicates = section.integer("bootstrap_replicates", 1000, minimum=19, maximum=100_000)
    stop_after = section.integer("bootstrap_stop_after", 20, minimum=0, maximum=replicates)
    section.done()
    return PrimaryTest(outcome, test, method, n_quadrature, spec.effects, reference,
                       spec.structure, spec.singular_fit, spec.reduction, p_value, below,
                       replicates, stop_after)


def _exclusions(section: Section) -> Exclusions:
    practice = section.boolean("practice", True)
    faults = section.boolean("device_faults", True)
    timeouts = section.string("timeouts", "exclude", choices=TIMEOUT_POLICIES)
    anticipation = section.number("anticipation_s", 0.15, minimum=0.0, maximum=10.0)
    slow = section.number("max_response_time_s", 0.0, minimum=0.0)
    if slow and slow <= anticipation:
        raise section.fail("max_response_time_s",
                           f"expected a limit above anticipation_s ({anticipation:g}), "
                           f"got {slow!r}")
    rt_column = section.string("rt_column", "response_time",
                               choices=("response_time", "response_time_from_offset"))
    section.done()
    return Exclusions(practice, faults, timeouts, anticipation, slow, rt_column)


def _one_name(section: Section, key: str, values: tuple[str, ...], names: tuple[str, ...]
              ) -> None:
    """Refuse two names of one thing (``symbol`` and ``digit``) in ``values``."""
    both = [v for v in values if v in names]
    if len(both) > 1:
        raise section.fail(key, f"{both[0]!r} and {both[1]!r} name the same thing (the symbol "
                           f"shown); expected one of them, got {list(values)}")


def _secondary(section: Section) -> SecondaryTests:
    tests = _strings(section, "tests", DEFAULT_SECONDARY_TESTS, choices=SECONDARY_TESTS,
                     unique=True)
    _one_name(section, "tests", tests, PER_SYMBOL_TESTS)
    correction = section.string("correction", "holm", choices=CORRECTIONS)
    section.done()
    return SecondaryTests(tests, correction)


def _confusion(section: Section) -> ConfusionPlan:
    plan = ConfusionPlan(
        bias_correction=section.string("bias_correction", "miller-madow",
                                       choices=BIAS_CORRECTIONS),
        bootstrap=section.integer("bootstrap", 2000, minimum=0, maximum=100_000),
        bootstrap_unit=section.string("bootstrap_unit", "participant", choices=BOOTSTRAP_UNITS),
    )
    section.done()
    return plan


def _psychometric(section: Section) -> PsychometricPlan:
    plan = PsychometricPlan(
        level_column=section.string("level_column", "auto"),
        function=section.string("function", "logistic", choices=PSYCHOMETRIC_FUNCTIONS),
        lapse_max=section.number("lapse_max", 0.1, minimum=0.0, maximum=0.5),
        threshold=section.number("threshold", 0.5, minimum=0.0, exclusive_minimum=True,
                                 maximum=0.99),
        bootstrap=section.integer("bootstrap", 200, minimum=0, maximum=10_000),
    )
    section.done()
    return plan


def order_conditions(trials: pd.DataFrame, plan: AnalysisPlan) -> tuple[list[str], str,
                                                                         list[str]]:
    """Conditions present (plan order first), the reference, and notes on mismatches."""
    present = list(pd.unique(trials["condition"]))
    notes = []
    ordered = [c for c in plan.conditions if c in present]
    extra = sorted(c for c in present if c not in plan.conditions)
    missing = [c for c in plan.conditions if c not in present]
    if missing:
        notes.append(f"missing condition(s) {missing}: the plan names them but no analysed "
                     f"trial has them; compared only {ordered + extra}")
    if extra and plan.conditions:
        notes.append(f"condition(s) {extra} are not in the plan; analysed after the planned ones")
    ordered += extra
    if not ordered:
        raise AnalysisError("no trial is left to analyse after the exclusions "
                            "(see the exclusion counts)")
    reference = plan.reference_condition(ordered)
    if reference not in ordered:
        notes.append(f"reference condition {reference!r} has no trials; used {ordered[0]!r} "
                     "as the reference instead")
        reference = ordered[0]
    ordered.remove(reference)
    return [reference, *ordered], reference, notes
