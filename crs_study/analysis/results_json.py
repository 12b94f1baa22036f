"""``results.json``, written from the result objects of an :class:`~.report.Analysis`.

The analysis keeps its results as objects (accuracy, primary, secondary, confusions, ...);
this module lays them out as the file's sections, in the file's key order (documented in
:mod:`crs_study.analysis.report`), each section its object's ``to_dict()``. Nothing is read
back out of the file's dict: the report is written from the same objects
(:mod:`crs_study.analysis.report_text`), and :func:`content` is called afresh by each
``to_dict()``, so the file always says what the objects hold.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pandas as pd

from crs_study import __version__
from crs_study.analysis.plan_lock import LockCheck
from crs_study.analysis.sources import summarise_sources
from crs_study.paths import recorded_path

if TYPE_CHECKING:  # the Analysis's own module imports this one
    from crs_study.analysis.report import Analysis

#: Why an adaptive study's accuracy GLMM is not its primary result (``results.json``'s
#: ``comparisons[].secondary_because``).
ADAPTIVE_SECONDARY = ("an adaptive procedure steers accuracy towards its target rate: the "
                      "threshold comparison is the primary result")


def adaptive_answer(analysis: Analysis) -> bool:
    """True when thresholds answer the study (an adaptive study with a comparison)."""
    thresholds = analysis.thresholds
    return thresholds is not None and not thresholds.skipped and bool(thresholds.comparisons)


def comparisons(analysis: Analysis) -> list[dict]:
    """Every comparison, the primary GLMM comparison(s) first, then the secondary tests; in
    an adaptive study the GLMM's are marked secondary, saying why."""
    rows = analysis.primary.to_dict()["comparisons"] + analysis.secondary.to_dict()["comparisons"]
    if adaptive_answer(analysis):
        for row in rows:
            if row["primary"]:
                row["primary"] = False
                row["secondary_because"] = ADAPTIVE_SECONDARY
    return rows


def content(analysis: Analysis) -> dict:
    """``results.json``'s sections in the file's order (numbers as the objects hold them:
    :func:`~crs_study.analysis.jsonable.to_jsonable` makes them plain JSON), without
    ``charts``, which only a written analysis has."""
    data, accuracy = analysis.data, analysis.accuracy
    tables, primary = accuracy.to_dict(), analysis.primary.to_dict()
    secondary = analysis.secondary.to_dict()
    # named as the trials name the symbol: accuracy_by_digit and per_digit for digit data
    by_symbol = f"accuracy_by_{accuracy.by_symbol.columns[0]}"
    per_symbol = f"per_{analysis.secondary.symbol_column}"
    results = {
        "alpha": analysis.plan.alpha, "chance": accuracy.chance,
        "reference": analysis.reference, "n_participants": analysis.n_participants,
        "n_trials_total": int(len(data.all_trials)), "n_trials_analysed": int(len(data.trials)),
        "exclusions": data.exclusion_counts,
        "conditions": tables["conditions"],
        "accuracy_by_participant": tables["accuracy_by_participant"],
        by_symbol: tables[by_symbol],
        "comparisons": comparisons(analysis),
        "primary": {"omnibus": primary["omnibus"], "model": primary["model"]},
        per_symbol: secondary[per_symbol],
        "information_transfer": analysis.confusions.to_dict(),
        "speed_accuracy": analysis.speed_accuracy.to_dict(),
        "psychometric": analysis.psychometric.to_dict(),
    }
    thresholds = analysis.thresholds
    if thresholds is not None and not thresholds.skipped:  # (fixed-level studies: no key)
        results["thresholds"] = thresholds.to_dict()
    results["warnings"] = list(analysis.warnings)
    results["headline"] = analysis.headline
    results["sources"] = sources(analysis)
    plan_file = data.plan_path
    results["plan"] = {"name": analysis.plan.name,
                       "path": None if plan_file is None else recorded_path(plan_file),
                       "sha256": analysis.plan_sha256,
                       "lock": (analysis.plan_lock or LockCheck("not locked")).to_dict()}
    results["datasets"] = [{"path": str(d.resolve()), "name": name} for d, name in
                           zip(data.datasets, pd.unique(data.all_trials["dataset"]),
                               strict=False)]
    results["sessions"] = sessions(data.sessions)
    results["software"] = {"name": "crs-study", "version": __version__}
    results["generated_at"] = analysis.generated_at
    return results


def sources(analysis: Analysis) -> dict:
    """Who answered and on what: the kind (``simulated``, ``human`` or ``mixed``), sessions
    counted by kind, responder and device, and the notes on them."""
    data = analysis.data
    kinds = sorted(set(data.sources["kind"]))
    return {"kind": kinds[0] if len(kinds) == 1 else "mixed",
            "sessions": summarise_sources(data.sources), "notes": list(data.source_notes)}


def sessions(table: pd.DataFrame) -> list[dict]:
    """One record per session: where it is, its status, responder, device, seed, checksum."""
    columns = ["dataset", "participant", "session", "n_rows", "Status", "Responder",
               "DeviceURL", "Seed", "SoftwareVersion", "TrialsSha256"]
    table = table.reindex(columns=columns)
    return table.astype(object).where(table.notna(), None).to_dict("records")
