"""The compressed beam at small d/l: regression tests for the quality helper's anomalies.

Reported: on the 1D patch ``beam`` worse than ``spline`` for d/l <= 0.2, D_S flat at ~0.02;
on the hexagonal patch D_P/(d/l) = 0.30 at d/l = 0.1 against 0.10 at 0.3. At the current
models neither flat D_S nor the 0.30 is reproduced (first two tests); what remains is
explained and pinned:

* 1D, D_P at d/l = 0.2-0.25: the renderer feeds the target's whole arc length, and a beam
  through pixel samples is short of it by the interpolation error (a few 1e-3 of the excess
  length), so N rises to ~0.35 N_cr on a 13-pixel patch and the bows between pixels shift the
  peak by up to 0.75 mm at l = 150 mm. The independent FE reference agrees to 0.01 mm, so this
  is the physics of the feed rule, not the solver. D_P stays below 0.02 d/l throughout, and
  falls again at d/l = 0.1.
* hex, D_P ~ 0.096 d/l at every d/l: the fabric is a membrane (maximum principle), so the
  displayed peak lies on a beam line; for a bump centred inside a lattice triangle it can at
  best sit at the nearest point of the triangle's sides. The mean distance from a uniform
  point of an equilateral triangle to its nearest side is r/3 (the incentre splits it into
  three triangles of height r, each nearest to its base), r = d/(2 sqrt 3) the inradius, so
  D_P -> d / (6 sqrt 3 l) = 0.0962 d/l as l/d grows: a floor proportional to d/l, not an
  error that grows as d/l shrinks.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from crs_study.display import get_model
from crs_study.quality import distortion, periodic_layout
from crs_study.rendering.render import Renderer
from crs_study.stimuli.targets import Bump

D_OVER_L = (0.1, 0.15, 0.2, 0.25, 0.3, 1 / 3)
#: mean distance to the nearest side of the lattice triangle, in units of d (module docstring)
RIDGE_FLOOR = 1.0 / (6.0 * math.sqrt(3.0))


@pytest.fixture(scope="module")
def one_d():
    return {(m, x): distortion(m, "1d", x, symmetric=True)
            for m in ("beam", "spline") for x in D_OVER_L}


def test_1d_beam_shape_improves_as_d_over_l_shrinks_and_beats_the_spline(one_d):
    beam = [one_d["beam", x].D_S for x in D_OVER_L]
    spline = [one_d["spline", x].D_S for x in D_OVER_L]
    assert all(b < a for a, b in zip(beam[1:], beam[:-1], strict=True))  # rising with d/l
    assert all(b <= s * 1.001 for b, s in zip(beam, spline, strict=True))
    assert beam[0] < 0.003  # d/l = 0.1: not flat at ~0.02


def test_1d_beam_peak_error_stays_small_and_vanishes_at_small_d_over_l(one_d):
    for x in D_OVER_L:
        assert one_d["beam", x].D_P <= 0.02 * x
    assert one_d["beam", 0.1].D_P < 0.2 * one_d["beam", 0.2].D_P
    assert one_d["beam", 0.1].D_P < 0.01 * 0.25 * 0.1  # 1 % of pixel-only (0.25 d/l)


def test_1d_peak_shift_at_d_over_l_0_2_is_the_feed_rule_not_the_solver():
    """Bump 10 mm from a pixel, d/l = 0.2: the beam's peak shifts beyond the target like the
    FE reference's; the cause is the spline's length deficit, which loads the beam."""
    d, l = 30.0, 150.0
    layout = periodic_layout("1d", d, 0.5 * l + 0.5 * d)
    setpoints = Renderer(layout, "crs", policy="error").render(Bump((10.0, 0.0), l, 5.0)
                                                               ).setpoints
    x = np.linspace(-40.0, 60.0, 2001)
    xy = np.column_stack([x, np.zeros_like(x)])
    peaks = {m: x[np.argmax(get_model(m, layout).surface(setpoints, xy))]
             for m in ("beam", "reference", "spline")}
    assert peaks["beam"] == pytest.approx(peaks["reference"], abs=0.02)
    assert peaks["beam"] - 10.0 > 0.5  # overshoot, from the load
    assert abs(peaks["spline"] - 10.0) < 0.3
    beam = get_model("beam", layout).beam_profiles(setpoints)
    spline = get_model("spline", layout).beam_profiles(setpoints)
    deficit = beam.commanded_length_mm[0] - spline.length_mm[0]
    assert 1e-3 < deficit < 0.03  # mm: the interpolation error of the arc length
    assert 0.25 < beam.axial_load_n[0] / beam.critical_load_n[0] < 0.5


def test_mean_distance_to_the_nearest_side_of_an_equilateral_triangle():
    """The constant of the ridge floor, by Monte Carlo (independent of the argument)."""
    rng = np.random.default_rng(0)
    u, v = rng.random((2, 400_000))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, math.sqrt(3) / 2]])  # side d = 1
    p = corners[0] + u[:, None] * (corners[1] - corners[0]) + v[:, None] * (corners[2]
                                                                             - corners[0])
    to_base = p[:, 1]
    to_left = (math.sqrt(3) * p[:, 0] - p[:, 1]) / 2
    to_right = (math.sqrt(3) * (1 - p[:, 0]) - p[:, 1]) / 2
    mean = np.minimum(np.minimum(to_base, to_left), to_right).mean()
    assert mean == pytest.approx(RIDGE_FLOOR, rel=3e-3)


@pytest.mark.parametrize("d_over_l", [0.1, 0.15, 0.3])
def test_hex_beam_peak_error_is_the_ridge_floor_at_every_d_over_l(d_over_l):
    """D_P/(d/l) of the compressed beam on the hexagonal patch: ~0.096 at 0.1 as at 0.3."""
    result = distortion("beam", "hex", d_over_l, symmetric=True)
    assert result.D_P / d_over_l == pytest.approx(RIDGE_FLOOR, rel=0.04)
