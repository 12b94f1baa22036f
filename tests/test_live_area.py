"""The recognition area and the bump under a finger (crs_study/live/area.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from crs_study.geometry.layout import load_layout
from crs_study.live import LiveError, RecognitionArea


def test_pixels_inside_and_the_area_is_their_hull(layout2d):
    area = RecognitionArea.for_layout(layout2d)
    centre = np.mean(layout2d.pixel_xy, axis=0)
    for x, y in layout2d.pixel_xy - centre:
        assert area.contains(x, y)
    assert not area.contains(61.0, 0.0)  # crs2d: the hull's corners are 60 mm out along x
    assert area.contains(59.0, 0.0)


LAYOUT = load_layout("crs2d")
AREA = RecognitionArea.for_layout(LAYOUT)
HULL = Delaunay(LAYOUT.pixel_xy)  # an independent point-in-hull test


# no deadline: an example takes microseconds, but a loaded 2-core machine stalled one for
# 298 ms (hypothesis' default deadline is 200 ms), failing a test that times nothing
@settings(deadline=None)
@given(st.floats(-100, 100), st.floats(-100, 100))
def test_contains_agrees_with_scipy_delaunay(x, y):
    area, hull = AREA, HULL
    inside = hull.find_simplex(np.array([area.to_layout(x, y)])) >= 0
    margin = np.max(area.edges[:, :2] @ np.array(area.to_layout(x, y)) + area.edges[:, 2])
    if abs(margin) > 1e-6:  # off the boundary, where rounding may decide either way
        assert area.contains(x, y) == bool(inside[0])


def test_margin_grows_the_area(layout2d):
    assert not RecognitionArea.for_layout(layout2d).contains(65.0, 0.0)
    assert RecognitionArea.for_layout(layout2d, margin_mm=10.0).contains(65.0, 0.0)


def test_line_display_uses_x_only(layout1d):
    area = RecognitionArea.for_layout(layout1d)
    assert area.centre_mm == (60.0, 0.0)
    assert area.contains(-60.0, 500.0) and area.contains(60.0, -3.0)
    assert not area.contains(60.5, 0.0)
    assert area.describe() == "x_f in [-60, 60] mm"


def test_bump_height_is_the_press_depth_within_the_travel(layout2d):
    area = RecognitionArea.for_layout(layout2d)
    bump = area.bump(10.0, -5.0, 4.0)
    assert bump.centre_mm == pytest.approx((10.0, -5.0)) and bump.height_mm == 4.0
    assert bump.diameter_mm == 90
    assert area.bump(0.0, 0.0, 50.0).height_mm == layout2d.travel_mm
    assert area.bump(0.0, 0.0, -2.0).height_mm == 0.0
    assert area.bump(200.0, 0.0, 4.0) is None
    assert RecognitionArea.for_layout(layout2d, max_height_mm=3).bump(0, 0, 5).height_mm == 3


@pytest.mark.parametrize("kwargs, message", [
    ({"margin_mm": -1.0}, "area margin"), ({"diameter_mm": 0.0}, "bump diameter"),
    ({"max_height_mm": 20.0}, "largest bump height"), ({"margin_mm": float("nan")}, "margin"),
])
def test_bad_area_options(layout2d, kwargs, message):
    with pytest.raises(LiveError, match=message):
        RecognitionArea.for_layout(layout2d, **kwargs)
