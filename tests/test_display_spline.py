"""The clamped-spline model (crs_study.display.spline): a beam without axial load."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from crs_study.display import get_model
from crs_study.display.network import NetworkModel
from crs_study.errors import DisplayModelError
from crs_study.layout import load_layout


def test_1d_is_the_clamped_spline_through_the_pixels():
    """scipy's clamped CubicSpline on knots (clamp, pixels, clamp) is the reference."""
    layout = load_layout("crs1d")
    heights = np.array([0.5, 2.0, 3.0, 1.0, 0.0])
    setpoints = np.concatenate([heights, [0.0, 0.0]])
    x = np.linspace(-60.0, 200.0, 521)
    z = get_model("spline", layout).surface(setpoints, np.column_stack([x, 5 + 0 * x]))
    knots = np.array([-30.0, 0, 30, 60, 90, 120, 150])
    expected = CubicSpline(knots, np.concatenate([[0], heights, [0]]), bc_type="clamped")(x)
    expected[(x < -30) | (x > 150)] = 0.0
    np.testing.assert_allclose(z, expected, atol=1e-12)


def test_spline_equals_the_beam_without_load_or_foundation():
    layout = load_layout("crs1d")
    setpoints = np.array([0.0, 1.0, 2.5, 0.5, 0.0, 0.0, 0.0])
    xy = np.column_stack([np.linspace(-30, 150, 361), np.zeros(361)])
    np.testing.assert_allclose(
        get_model("spline", layout).surface(setpoints, xy),
        get_model("beam", layout, foundation=False).surface(setpoints, xy), atol=1e-9)


def test_2d_network_passes_through_every_pixel():
    layout = load_layout("crs2d")
    rng = np.random.default_rng(3)
    setpoints = np.zeros(layout.n_actuators)
    setpoints[: layout.n_pixels] = rng.uniform(0, 3, layout.n_pixels)
    model = get_model("spline", layout)
    assert isinstance(model, NetworkModel) and model.fabric is not None
    np.testing.assert_allclose(model.surface(setpoints, layout.pixel_xy),
                               setpoints[: layout.n_pixels], atol=1e-9)


def test_yield_curvature():
    layout = load_layout("crs1d").with_pitch(4.0)
    setpoints = np.array([0.0, 9.0, 0.0, 9.0, 0.0, 0.0, 0.0])
    with pytest.raises(DisplayModelError, match=r"spline: beam 0 bends to curvature .* plastic"):
        get_model("spline", layout).surface(setpoints, np.zeros((1, 2)))


def test_2d_beams_are_scipy_clamped_splines_with_their_arc_length():
    """Every beam of the 2D network (precomputed knot-slope map, Hermite evaluation) against
    scipy's CubicSpline, and its length against 12-point Gauss-Legendre on scipy's spline."""
    from crs_study.display.spline import spline_arc_length

    layout = load_layout("crs2d")
    rng = np.random.default_rng(5)
    setpoints = np.zeros(layout.n_actuators)
    setpoints[: layout.n_pixels] = rng.uniform(0, 4, layout.n_pixels)
    model = get_model("spline", layout)
    profiles = model.beam_profiles(setpoints)
    for b, spline in enumerate(model.splines(setpoints)):
        s = np.linspace(0.0, model.spans[b], 401)
        np.testing.assert_allclose(profiles.profile(b)(s), spline(s), atol=1e-12)
        assert profiles.length_mm[b] == pytest.approx(spline_arc_length(spline), abs=1e-10)
