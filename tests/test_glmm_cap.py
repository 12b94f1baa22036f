"""The cap on the random effects' loadings (THETA_CAP) as Newton's method meets it.

A three-participant pilot of three digits (random answers) has a likelihood that rises
far out in the participants' slope SD: its profile points put loadings at the cap. By the
definition of a profile (the maximum over the *other* parameters) a profile point holds its
parameter at the value asked, even beyond the cap, while every free loading stays within it.
Newton's step once clipped the held value to the cap too, and the profile of that SD came
out flat there, its upper end null. Its other end: a profile interval's end is sought no
farther than ``PROFILE_SPAN`` from the estimate (separated data stay flat far out, every
point a slow fit).
"""

from __future__ import annotations

import numpy as np
import pytest
from _session_helpers import tiny_protocol
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis.glmm_fit import PROFILE_SPAN, _profile_end
from crs_study.analysis.glmm_newton import THETA_CAP
from crs_study.analysis.glmm_optimise import maximise
from crs_study.analysis.primary import fit_primary
from crs_study.analysis.study_data import load_dataset
from crs_study.session import dry_run


@pytest.fixture(scope="module")
def capped_fit(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cap")
    dry_run(tiny_protocol(folder), 3, folder / "ds", responder="random")
    data = load_dataset(folder / "ds", include_simulated=True)
    trials = data.trials.loc[data.trials["correct"].notna()]
    fits = fit_primary(trials, ["pixel-only", "crs"], "pixel-only", ("participant", "digit"))
    return fits.full


def test_a_profile_point_holds_its_value_beyond_the_cap(capped_fit):
    problem, theta = capped_fit._model.problem, capped_fit._model.theta
    n_fixed = problem.n_fixed
    for index in range(n_fixed, len(theta)):
        for held in (0.5 * THETA_CAP, 1.3 * THETA_CAP, 2.4 * THETA_CAP):
            start = theta.copy()
            start[index] = held
            opt = maximise(problem, start, {index: held}, profile=True)
            assert opt.theta[index] == pytest.approx(held, rel=1e-12), (index, held)
            assert np.all(np.abs(np.delete(opt.theta[n_fixed:], index - n_fixed))
                          <= THETA_CAP * (1 + 1e-9))
    problem.objective(theta)


@settings(max_examples=60, deadline=None)
@given(estimate=st.floats(-5.0, 5.0), step=st.floats(0.01, 3.0), sign=st.sampled_from([-1, 1]),
       root=st.floats(0.05, 2.0 * PROFILE_SPAN))
def test_a_profile_end_is_sought_within_its_span(estimate, step, sign, root):
    """A profile end is the root of the signed-root drop when it lies within
    ``PROFILE_SPAN`` of the estimate (Brent's method to its tolerance), open (infinite)
    otherwise, and no point farther out is ever asked for."""
    asked = []

    def drop(value: float) -> float:
        asked.append(value)
        return abs(value - estimate) - root

    end = _profile_end(drop, estimate, sign * step)
    assert all(abs(v - estimate) <= PROFILE_SPAN * (1 + 1e-12) for v in asked)
    if root < PROFILE_SPAN:
        assert end == pytest.approx(estimate + sign * root, abs=1e-4)
    else:
        assert end == sign * np.inf
