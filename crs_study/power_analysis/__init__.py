"""Power analysis by simulation: how many participants a protocol needs.

``power(protocol, ...) -> PowerResult`` (:mod:`crs_study.power_analysis.api`) applies the analysis
plan's primary test, exactly as ``analyze`` runs it, to many simulated studies of the
protocol's design, drawn from a pilot's GLMM fit or from the simulated observer's predicted
accuracies (or real dry-runs, ``fidelity="full"``), mapped over a local process pool or a
Dask cluster; the result has the curve with its Monte Carlo intervals, ``to_frame()``,
``to_json()``, ``plot(ax=None)`` and the one-line ``headline()``.

The stages, in the order they build on each other:

* :mod:`~crs_study.power_analysis.design`: the protocol's design and the plan's test; ranges;
  :mod:`~crs_study.power_analysis.protocol_design`: that design read from a protocol;
* :mod:`~crs_study.power_analysis.model`: the generating model (pilot, parameters);
  :mod:`~crs_study.power_analysis.observer`: the observer's predicted accuracies (mode 2);
* :mod:`~crs_study.power_analysis.simulate`: studies with common random numbers;
* :mod:`crs_study.analysis.glmm_batch` (with :mod:`crs_study.analysis.glmm_newton`): the
  primary GLMM fitted to many studies at once, at ``fit_glmm``'s maximum;
* :mod:`~crs_study.power_analysis.study`: the unit of work;
  :mod:`~crs_study.power_analysis.fidelity`: mode 3;
* :mod:`~crs_study.power_analysis.backends`: this process, a process pool, or Dask;
* :mod:`~crs_study.power_analysis.result`: :class:`PowerResult`.
"""

from __future__ import annotations

from crs_study._lazy import lazy_exports

#: The entry points, each loaded from its module on first use: a worker process that runs a
#: power task unpickles it from :mod:`~crs_study.power_analysis.study`, and importing that
#: must not import the whole analysis with its reports and charts (a second of every
#: worker's start, in the timed power point).
_EXPORTS = {
    "power": "crs_study.power_analysis.api",
    "PowerDesign": "crs_study.power_analysis.design",
    "PowerError": "crs_study.power_analysis.design",
    "design_from_protocol": "crs_study.power_analysis.protocol_design",
    "GenerativeModel": "crs_study.power_analysis.model",
    "model_from_parameters": "crs_study.power_analysis.model",
    "model_from_pilot": "crs_study.power_analysis.model",
    "model_from_observer": "crs_study.power_analysis.observer",
    "PowerResult": "crs_study.power_analysis.result",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
