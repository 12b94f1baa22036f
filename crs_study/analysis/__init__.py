"""Analysis of stored datasets: load, accuracy, the GLMM, secondary tests, confusions,
speed against accuracy, psychometric functions, charts and the report.

The public entry points are :func:`analyze` (every analysis of the plan, as an
:class:`Analysis` of result objects; the report written on request), :func:`load_dataset`
(the trials an analysis sees, as :class:`StudyData`), :func:`load_datasets` (the loader's
checked table of every trial), :func:`load_plan`, :func:`fit_primary` (the primary
likelihood-ratio tests alone, for power simulations) and :func:`compare_results` (a
reanalysis against an earlier ``results.json``); they are imported lazily so that
``import crs_study.analysis.glmm`` does not pull in matplotlib.
"""

from __future__ import annotations

from crs_study._lazy import lazy_exports

_EXPORTS = {
    "analyze": "crs_study.analysis.report",
    "analyze_dataset": "crs_study.analysis.report",
    "Analysis": "crs_study.analysis.report",
    "ReportFiles": "crs_study.analysis.report",
    "load_dataset": "crs_study.analysis.study_data",
    "StudyData": "crs_study.analysis.study_data",
    "load_datasets": "crs_study.analysis.load",
    "LoadedData": "crs_study.analysis.load",
    "load_plan": "crs_study.analysis.plan",
    "AnalysisPlan": "crs_study.analysis.plan",
    "fit_primary": "crs_study.analysis.primary",
    "PrimaryFits": "crs_study.analysis.primary",
    "compare_results": "crs_study.analysis.reproduce",
    "ResultsComparison": "crs_study.analysis.reproduce",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
