"""Shared checks of the power tests."""

from __future__ import annotations

import dataclasses

import numpy as np

from crs_study.analysis.plan import load_plan
from crs_study.analysis.report import analyze
from crs_study.power_analysis import design_from_protocol, model_from_pilot
from crs_study.protocol import load_protocol
from crs_study.protocol.model import analysis_plan_path


def pilot_model_matching_analyze(protocol, pilot):
    """The generating model ``model_from_pilot`` makes of ``pilot`` for ``protocol``, checked
    to carry analyze's primary GLMM fixed effects (to 1e-9); returns it with the fit's
    variance components, for the caller's checks of the SDs. analyze runs the protocol's plan
    with the chi2 p: the fit is the same, and the parametric bootstrap of the p (below 20
    participants) would refit the model hundreds of times for a p not compared."""
    model = model_from_pilot(design_from_protocol(protocol), pilot)
    fitted = analyze([pilot], chi2_plan(protocol), write=False).results["primary"]["model"]
    coefficients = fitted["coefficients"]
    intercept = coefficients["Intercept"]["estimate"]
    crs = coefficients["condition[crs]"]["estimate"]
    np.testing.assert_allclose(model.base[0, 0], [intercept, intercept + crs], rtol=1e-9)
    return model, fitted["variance_components"]


def chi2_plan(protocol):
    """The analysis plan of ``protocol`` with the chi2 LR p (``p_value = "chi2"``)."""
    plan = load_plan(analysis_plan_path(load_protocol(protocol)))
    return dataclasses.replace(plan, primary=dataclasses.replace(plan.primary, p_value="chi2"))
