"""Tests for crs_study.stimuli.targets: the Eq. 7 bump and arc lengths along straight segments."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from crs_study.errors import RenderError
from crs_study.stimuli.targets import Bump, arc_excess, arc_length

finite = st.floats(-200.0, 200.0, allow_nan=False)
bumps = st.builds(
    Bump,
    centre_mm=st.tuples(finite, finite),
    diameter_mm=st.floats(5.0, 400.0),
    height_mm=st.floats(0.0, 30.0),
)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        pytest.param({"diameter_mm": 0.0}, "diameter must be > 0 mm, got 0.0", id="zero-diameter"),
        pytest.param({"diameter_mm": float("nan")}, "diameter must be > 0 mm, got nan", id="nan"),
        pytest.param({"height_mm": -1.0}, "height must be >= 0 mm, got -1.0", id="negative"),
        pytest.param({"centre_mm": (0.0, float("inf"))}, "centre must be finite", id="inf-centre"),
    ],
)
def test_bad_bump_is_a_one_line_render_error(kwargs, message):
    args = {"centre_mm": (0.0, 0.0), "diameter_mm": 90.0, "height_mm": 5.0, **kwargs}
    with pytest.raises(RenderError, match=message):
        Bump(**args)


def test_height_follows_eq7_at_known_radii():
    # Eq. 7: z = z_f/2 [1 + cos(2 pi rho / l)] for rho <= l/2, else 0 (l = 90, z_f = 4).
    bump = Bump((10.0, -5.0), 90.0, 4.0)
    rho = np.array([0.0, 22.5, 45.0, 45.0001, 100.0])
    xy = np.column_stack([10.0 + rho, np.full_like(rho, -5.0)])
    np.testing.assert_allclose(bump.height(xy), [4.0, 2.0, 0.0, 0.0, 0.0], atol=1e-12)
    # rotational symmetry
    angle = np.linspace(0, 2 * np.pi, 7)
    ring = np.column_stack([10.0 + 30 * np.cos(angle), -5.0 + 30 * np.sin(angle)])
    np.testing.assert_allclose(bump.height(ring), 2.0 * (1 + math.cos(2 * math.pi * 30 / 90)))


@settings(max_examples=60, deadline=None)
@given(bump=bumps, point=st.tuples(finite, finite), angle=st.floats(0.0, 2 * np.pi))
def test_slope_along_matches_a_central_difference(bump, point, angle):
    unit = np.array([math.cos(angle), math.sin(angle)])
    p = np.array(point)
    h = 1e-5 * bump.diameter_mm
    numeric = (bump.height(p + h * unit) - bump.height(p - h * unit)) / (2 * h)
    # the slope is continuous (z is C1 at the rim); a central difference is O(h^2) accurate
    scale = bump.height_mm / bump.diameter_mm
    assert bump.slope_along(p, unit) == pytest.approx(numeric, abs=1e-5 * scale + 1e-12)


def test_curvature_max_is_the_second_difference_at_the_centre():
    bump = Bump((0.0, 0.0), 90.0, 5.0)
    h = 1e-3
    z = bump.height(np.array([[-h, 0.0], [0.0, 0.0], [h, 0.0]]))
    assert bump.curvature_max() == pytest.approx(-(z[0] - 2 * z[1] + z[2]) / h**2, rel=1e-6)
    assert bump.curvature_max() == pytest.approx(2 * np.pi**2 * 5.0 / 90.0**2)


def _quad_arc_length(bump, start, end):
    """Independent reference: scipy.integrate.quad of sqrt(1 + (dz/ds)^2), split at the rim."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    span = float(np.linalg.norm(end - start))
    unit = (end - start) / span
    rel = np.asarray(bump.centre_mm) - start
    along = rel @ unit
    off2 = max(rel @ rel - along**2, 0.0)
    r = bump.diameter_mm / 2
    breaks = []
    if off2 < r * r:
        half = math.sqrt(r * r - off2)
        breaks = [t for t in (along - half, along, along + half) if 0 < t < span]

    def integrand(s):
        return math.sqrt(1.0 + float(bump.slope_along(start + s * unit, unit)) ** 2)

    value, _ = quad(integrand, 0.0, span, points=breaks or None, limit=200,
                    epsabs=1e-12, epsrel=1e-12)
    return value


@settings(max_examples=40, deadline=None)
@given(bump=bumps, start=st.tuples(finite, finite), end=st.tuples(finite, finite))
def test_arc_length_matches_scipy_quad(bump, start, end):
    if math.dist(start, end) < 1e-3:
        assert arc_length(bump, start, start) == 0.0
        return
    reference = _quad_arc_length(bump, start, end)
    assert arc_length(bump, start, end) == pytest.approx(reference, rel=1e-10, abs=1e-9)


def test_arc_excess_small_slope_limit_through_the_centre():
    # Small slopes: excess ~ (1/2) integral s^2 = (1/2)(pi h / l)^2 (l / 2) = pi^2 h^2 / (4 l).
    bump = Bump((50.0, 0.0), 90.0, 0.05)
    excess = arc_length(bump, (0.0, 0.0), (100.0, 0.0)) - 100.0
    assert excess == pytest.approx(np.pi**2 * 0.05**2 / (4 * 90.0), rel=1e-4)


def test_arc_excess_is_vectorised_over_segments(rng):
    bump = Bump((3.0, -7.0), 90.0, 6.0)
    starts = rng.uniform(-80, 80, size=(25, 2))
    ends = rng.uniform(-80, 80, size=(25, 2))
    spans = np.linalg.norm(ends - starts, axis=1)
    units = (ends - starts) / spans[:, None]
    together = arc_excess(bump, starts, units, spans)
    one_by_one = [arc_length(bump, tuple(s), tuple(e)) - n
                  for s, e, n in zip(starts, ends, spans, strict=True)]
    np.testing.assert_allclose(together, one_by_one, rtol=1e-12, atol=1e-12)


def test_segment_missing_the_bump_is_flat():
    bump = Bump((0.0, 0.0), 90.0, 6.0)
    assert arc_length(bump, (-100.0, 46.0), (100.0, 46.0)) == pytest.approx(200.0, abs=1e-12)
    assert arc_length(bump, (50.0, 0.0), (120.0, 0.0)) == pytest.approx(70.0, abs=1e-12)


def test_moved_to_keeps_shape():
    bump = Bump((0.0, 0.0), 90.0, 6.0).moved_to((5, 6))
    assert bump == Bump((5.0, 6.0), 90.0, 6.0)
