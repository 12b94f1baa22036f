"""Shared checks of the power tests."""

from __future__ import annotations

import numpy as np

from crs_study.analysis.report import analyze
from crs_study.power_analysis import design_from_protocol, model_from_pilot


def pilot_model_matching_analyze(protocol, pilot):
    """The generating model ``model_from_pilot`` makes of ``pilot`` for ``protocol``, checked
    to carry analyze's primary GLMM fixed effects (to 1e-9); returns it with the fit's
    variance components, for the caller's checks of the SDs."""
    model = model_from_pilot(design_from_protocol(protocol), pilot)
    fitted = analyze([pilot], write=False).results["primary"]["model"]
    coefficients = fitted["coefficients"]
    intercept = coefficients["Intercept"]["estimate"]
    crs = coefficients["condition[crs]"]["estimate"]
    np.testing.assert_allclose(model.base[0, 0], [intercept, intercept + crs], rtol=1e-9)
    return model, fitted["variance_components"]
