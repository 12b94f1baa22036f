"""A protocol's :class:`~crs_study.power_analysis.design.PowerDesign`, read from its own trial
plan and its analysis plan.

Apart from :mod:`~crs_study.power_analysis.design` because only the process that starts a
power analysis reads a protocol: a worker process receives the design made here, and
importing the protocol package (its wire checks import the device's) would add a fifth of a
second to every worker's start.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pandas as pd

from crs_study.analysis.plan import AnalysisPlan, default_plan_path, load_plan, order_conditions
from crs_study.paths import resolve_protocol
from crs_study.power_analysis.design import PowerDesign, PowerError
from crs_study.protocol import analysis_plan_path, load_protocol
from crs_study.protocol.plan import make_plan


def design_from_protocol(protocol: Any, plan: Any = None) -> PowerDesign:
    """The :class:`PowerDesign` of a protocol (a path, a shipped name or a loaded
    :class:`~crs_study.protocol.Protocol`) under an analysis plan (a path or a loaded
    :class:`~crs_study.analysis.plan.AnalysisPlan`; default: the one the protocol names, else
    the shipped default, as ``analyze`` chooses)."""
    if not hasattr(protocol, "design"):
        protocol = load_protocol(resolve_protocol(protocol))
    if protocol.adaptive is not None:
        # each trial's level depends on the responses before it: a study cannot be drawn
        # cell by cell from a model, and the plan's result is the threshold, not a cell's
        # accuracy
        raise PowerError(f"{protocol.path}: its levels are chosen adaptively ([adaptive], "
                         f"{protocol.adaptive.procedure}); power covers protocols with fixed "
                         "levels: rehearse this one with crs-study dry-run")
    if plan is None:
        plan = analysis_plan_path(protocol) or default_plan_path()
    if not isinstance(plan, AnalysisPlan):
        plan = load_plan(plan)
    conditions, reference, _ = order_conditions(
        pd.DataFrame({"condition": list(protocol.conditions)}), plan)
    repetitions = _test_trials_per_cell(protocol)
    primary = plan.primary
    shown = protocol.symbol_set
    return PowerDesign(
        conditions=tuple(conditions), reference=reference, symbols=tuple(protocol.symbols),
        levels=tuple(protocol.level_values), repetitions=repetitions,
        random_effects=tuple(primary.random_effects), method=primary.method,
        n_quadrature=int(primary.n_quadrature), alpha=float(plan.alpha),
        structure=primary.structure, singular_fit=primary.singular_fit,
        reduction=tuple(primary.reduction), p_value=primary.p_value,
        bootstrap_below=int(primary.bootstrap_below),
        protocol=f"{protocol.study_id} {protocol.version}", plan=plan.name,
        protocol_path=str(Path(protocol.path)), exclusions=plan.exclusions,
        symbol_column=shown.column, noun=shown.noun, symbol_keys=symbol_keys(protocol))


def symbol_keys(protocol: Any) -> tuple[int, ...]:
    """Each symbol's position in the protocol's stimulus set: the key of its random streams
    (the observer's noise, :mod:`crs_study.power_analysis.observer`). For the digit set the
    position is the digit (its symbols are 0 to 9 in order), as the streams were keyed when
    every protocol showed digits; for another set it does not depend on which of its symbols
    a protocol shows, or in which order."""
    alphabet = list(protocol.symbol_set.symbols)
    return tuple(alphabet.index(s) for s in protocol.symbols)


def _test_trials_per_cell(protocol: Any) -> int:
    """The test trials of each (condition, symbol, level) cell in the protocol's own plans
    (two counterbalance positions), checked to be one number for every cell."""
    counts = set()
    for counterbalance in (0, 1):
        plan = make_plan(protocol, "powerdesign", 1, counterbalance)
        cells = Counter((t.condition, t.symbol, t.level) for t in plan.trials
                        if t.trial_type == "test")
        expected = {(c, d, lv) for c in protocol.conditions for d in protocol.symbols
                    for lv in protocol.level_values}
        if set(cells) != expected:
            raise PowerError(f"{protocol.path}: the trial plan does not show every (condition, "
                             f"{protocol.symbol_set.noun}, level) cell; the power analysis "
                             "needs a complete design")
        counts |= set(cells.values())
    if len(counts) != 1:
        raise PowerError(f"{protocol.path}: the cells of the trial plan have different numbers "
                         f"of test trials ({sorted(counts)}); the power analysis needs a "
                         "balanced design")
    return counts.pop()
