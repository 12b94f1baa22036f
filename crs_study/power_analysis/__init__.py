"""Power analysis by simulation: how many participants a protocol needs.

``power(protocol, ...) -> PowerResult`` (:mod:`crs_study.power_analysis.api`) applies the analysis
plan's primary test, exactly as ``analyze`` runs it, to many simulated studies of the
protocol's design, drawn from a pilot's GLMM fit or from the simulated observer's predicted
accuracies (or real dry-runs, ``fidelity="full"``), mapped over a local process pool or a
Dask cluster; the result has the curve with its Monte Carlo intervals, ``to_frame()``,
``to_json()``, ``plot(ax=None)`` and the one-line ``headline()``.

The stages, in the order they build on each other:

* :mod:`~crs_study.power_analysis.design`: the protocol's design and the plan's test; ranges;
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

from crs_study.power_analysis.api import power
from crs_study.power_analysis.design import PowerDesign, PowerError, design_from_protocol
from crs_study.power_analysis.model import GenerativeModel, model_from_parameters, model_from_pilot
from crs_study.power_analysis.observer import model_from_observer
from crs_study.power_analysis.result import PowerResult

__all__ = ["GenerativeModel", "PowerDesign", "PowerError", "PowerResult", "design_from_protocol",
           "model_from_observer", "model_from_parameters", "model_from_pilot", "power"]
