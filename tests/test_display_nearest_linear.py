"""Tests for the nearest-pixel and linear-connection display models."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.display import get_model
from crs_study.display.base import MODELS
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import layout_from_dict, load_layout

LAYOUT2D = load_layout("crs2d")
LAYOUT1D = load_layout("crs1d")


def _setpoints(layout, heights):
    sp = np.zeros(layout.n_actuators)
    sp[: layout.n_pixels] = heights
    return sp


def test_both_models_are_registered():
    assert get_model("nearest", LAYOUT2D).name == "nearest"
    assert get_model("linear", LAYOUT2D).name == "linear"
    assert {"nearest", "linear"} <= set(MODELS)


def test_nearest_1d_is_a_staircase_with_steps_half_way():
    model = get_model("nearest", LAYOUT1D)
    sp = _setpoints(LAYOUT1D, [1.0, 2.0, 3.0, 4.0, 5.0])  # pixels at 0, 30, ..., 120 mm
    x = np.array([-15.0, 0.0, 14.9, 15.1, 44.0, 46.0, 120.0, 134.9, 135.1, 500.0])
    z = model.surface(sp, np.column_stack([x, np.full_like(x, 7.0)]))  # y is ignored in 1D
    np.testing.assert_array_equal(z, [1, 1, 1, 2, 2, 3, 5, 5, 0, 0])


@settings(max_examples=60, deadline=None)
@given(pixel=st.integers(0, 18), radius=st.floats(0.0, 14.99), angle=st.floats(0, 2 * np.pi),
       seed=st.integers(0, 2**16))
def test_nearest_2d_shows_a_pixels_height_within_its_inscribed_circle(pixel, radius, angle,
                                                                     seed):
    # A point within d/2 of a pixel is nearer to it than to any other pixel of the lattice.
    heights = np.random.default_rng(seed).uniform(0, 9, LAYOUT2D.n_pixels)
    point = LAYOUT2D.pixel_xy[pixel] + radius * np.array([math.cos(angle), math.sin(angle)])
    z = get_model("nearest", LAYOUT2D).surface(_setpoints(LAYOUT2D, heights), point[None])
    assert z[0] == heights[pixel]


def test_nearest_2d_is_base_beyond_the_cells():
    model = get_model("nearest", LAYOUT2D)
    sp = _setpoints(LAYOUT2D, np.full(LAYOUT2D.n_pixels, 3.0))
    # the hexagon's corner pixel (2, -2) sits at (30, -52) mm; its cell ends d/sqrt(3) away
    corner = LAYOUT2D.pixel_xy[2]
    outward = corner / np.linalg.norm(corner)
    inside = corner + outward * (30 / math.sqrt(3) - 0.1)
    outside = corner + outward * (30 / math.sqrt(3) + 0.1)
    np.testing.assert_array_equal(model.surface(sp, np.array([inside, outside])), [3.0, 0.0])


def test_linear_1d_is_numpy_interp_and_zero_outside():
    model = get_model("linear", LAYOUT1D)
    heights = [0.0, 2.0, 5.0, 1.0, 0.5]
    x = np.linspace(-20, 140, 97)
    z = model.surface(_setpoints(LAYOUT1D, heights), np.column_stack([x, np.zeros_like(x)]))
    expected = np.interp(x, [0, 30, 60, 90, 120], heights, left=0, right=0)
    np.testing.assert_allclose(z, expected, atol=1e-12)
    assert model.surface(_setpoints(LAYOUT1D, heights), np.array([[45.0, 0.0]]))[0] == 3.5


@settings(max_examples=40, deadline=None)
@given(a=st.floats(0, 5), b=st.floats(-0.05, 0.05), c=st.floats(-0.05, 0.05),
       seed=st.integers(0, 2**16))
def test_linear_2d_reproduces_affine_heights_inside_the_hull(a, b, c, seed):
    # Piecewise-linear interpolation is exact for affine data on every triangle.
    xy = LAYOUT2D.pixel_xy
    heights = a + b * xy[:, 0] + c * xy[:, 1]
    rng = np.random.default_rng(seed)
    # random points inside the hull: convex combinations of three random pixels
    idx = rng.integers(0, len(xy), size=(50, 3))
    w = rng.dirichlet(np.ones(3), size=50)
    points = np.einsum("nk,nkd->nd", w, xy[idx])
    z = get_model("linear", LAYOUT2D).surface(_setpoints(LAYOUT2D, heights), points)
    np.testing.assert_allclose(z, a + b * points[:, 0] + c * points[:, 1], atol=1e-9)


def test_linear_2d_at_pixels_centroids_and_outside():
    model = get_model("linear", LAYOUT2D)
    heights = np.arange(LAYOUT2D.n_pixels, dtype=float)
    sp = _setpoints(LAYOUT2D, heights)
    np.testing.assert_allclose(model.surface(sp, LAYOUT2D.pixel_xy), heights, atol=1e-12)
    # triangle of pixels 8, 9, 13 (axial (-1,0), (0,0), (-1,1)): centroid shows their mean
    centroid = LAYOUT2D.pixel_xy[[8, 9, 13]].mean(axis=0)
    assert model.surface(sp, centroid[None])[0] == pytest.approx((8 + 9 + 13) / 3)
    assert model.surface(sp, np.array([[200.0, 0.0]]))[0] == 0.0


def test_linear_on_collinear_2d_pixels_interpolates_along_the_line():
    data = {
        "name": "row", "geometry": {"lattice": "hex", "pitch_mm": 30.0,
                                    "pixels": [[0, 0], [1, 0], [2, 0]], "beams": [[0, 1, 2]]},
        "servos": {"travel_mm": 9.0, "boundary_travel_mm": 9.0, "speed_s_per_cm": 0.08},
        "beam": {"material": "steel", "youngs_modulus_gpa": 193.0, "width_mm": 1.0,
                 "thickness_mm": 0.15, "yield_strength_mpa": 965.0},
        "skin": {"foundation_stiffness_kpa": 1.0},
        "controllers": [{"name": "A"}],
        "channels": {"pixels": ["A:1", "A:2", "A:3"], "boundaries": [["A:4", "A:5"]]},
        "calibration": {"default": {"zero_us": 1000, "full_us": 2000}},
    }
    layout = layout_from_dict(data)
    z = get_model("linear", layout).surface(
        _setpoints(layout, [0.0, 4.0, 2.0]), np.array([[15.0, 0.0], [45.0, 0.0], [15.0, 5.0]]))
    np.testing.assert_allclose(z, [2.0, 3.0, 0.0])


@pytest.mark.parametrize("name", ["nearest", "linear"])
def test_peak_is_the_highest_pixel_and_the_mean_of_ties(name):
    model = get_model(name, LAYOUT2D)
    heights = np.zeros(LAYOUT2D.n_pixels)
    heights[5] = 4.0
    np.testing.assert_allclose(model.peak_xy(_setpoints(LAYOUT2D, heights)), LAYOUT2D.pixel_xy[5])
    heights[9] = 4.0
    np.testing.assert_allclose(model.peak_xy(_setpoints(LAYOUT2D, heights)),
                               LAYOUT2D.pixel_xy[[5, 9]].mean(axis=0))


@pytest.mark.parametrize("name", ["nearest", "linear"])
def test_wrong_setpoint_length_is_a_one_line_error(name):
    with pytest.raises(DisplayModelError, match=r"crs2d: expected 37 setpoints .* shape \(5,\)"):
        get_model(name, LAYOUT2D).surface(np.zeros(5), np.zeros((1, 2)))


@pytest.mark.parametrize("name", ["nearest", "linear"])
def test_pixel_heights_alone_are_accepted(name):
    heights = np.linspace(0, 9, LAYOUT2D.n_pixels)
    model = get_model(name, LAYOUT2D)
    np.testing.assert_allclose(model.surface(heights, LAYOUT2D.pixel_xy), heights, atol=1e-12)
