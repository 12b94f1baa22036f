"""Tests for crs_study.render: conditions, the split rule, the clamp policy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.errors import RenderError
from crs_study.render import (
    CONDITIONS,
    BeamGeometry,
    Renderer,
    Rendering,
    register_condition,
    render,
    split_feed,
)
from crs_study.targets import Bump, arc_length

coordinate = st.floats(-90.0, 90.0, allow_nan=False)
device_bumps = st.builds(
    Bump,
    centre_mm=st.tuples(coordinate, coordinate),
    diameter_mm=st.floats(30.0, 200.0),
    height_mm=st.floats(0.0, 9.0),
)


@settings(max_examples=200, deadline=None)
@given(total=st.floats(0.0, 18.0), travel=st.floats(0.5, 9.0))
def test_split_parts_sum_to_the_whole_and_fit_each_end(total, travel):
    start, end = split_feed(np.array([total]), travel)
    assert start[0] + end[0] == pytest.approx(total, abs=1e-12)
    assert start[0] >= 0 and end[0] >= 0
    assert start[0] <= travel + 1e-12
    if total <= 2 * travel:
        assert end[0] <= travel + 1e-12
    if total <= 2 * travel and 0.5 * total <= travel:
        assert start[0] == pytest.approx(end[0])  # the even split


def test_split_of_a_feed_beyond_one_end_puts_the_rest_on_the_other():
    start, end = split_feed(np.array([4.0, 14.0, 20.0]), 9.0)
    np.testing.assert_allclose(start, [2.0, 7.0, 9.0])
    np.testing.assert_allclose(end, [2.0, 7.0, 11.0])  # 11 > 9: the clamp policy reports it


@settings(max_examples=60, deadline=None)
@given(bump=device_bumps)
def test_crs_feeds_make_each_beam_as_long_as_the_target_arc(layout2d, bump):
    result = Renderer(layout2d, "crs").render(bump)
    if result.clamped:
        return  # checked in the clamp tests
    sp = result.setpoints
    for beam in layout2d.beams:
        fed = sp[beam.start_servo] + sp[beam.end_servo]
        target = arc_length(bump, beam.start, beam.end) - beam.straight_length
        assert fed == pytest.approx(target, abs=1e-9)
        assert sp[beam.start_servo] == pytest.approx(sp[beam.end_servo])  # even split
    pixels = Renderer(layout2d, "pixel-only").render(bump).setpoints
    np.testing.assert_array_equal(sp[: layout2d.n_pixels], pixels[: layout2d.n_pixels])


@settings(max_examples=40, deadline=None)
@given(bump=device_bumps)
def test_pixel_only_samples_the_target_and_keeps_boundaries_neutral(layout2d, bump):
    result = Renderer(layout2d, "pixel-only").render(bump)
    np.testing.assert_allclose(result.setpoints[: layout2d.n_pixels],
                               bump.height(layout2d.pixel_xy), atol=0)
    np.testing.assert_array_equal(result.setpoints[layout2d.n_pixels:], 0.0)
    assert result.clamped == ()


def test_centred_bump_feeds_symmetric_beams_equally(layout2d):
    # The 2D device is 6-fold symmetric about pixel 9 (axial [0, 0]): the three beams through
    # it get one feed, the six offset beams another.
    geometry = BeamGeometry(layout2d)
    feeds = geometry.feeds(Bump((0.0, 0.0), 90.0, 6.0))
    through = [b.index for b in layout2d.beams if 9 in b.pixels]
    offset = [b.index for b in layout2d.beams if 9 not in b.pixels]
    assert len(through) == 3 and len(offset) == 6
    np.testing.assert_allclose(feeds[through], feeds[through][0], rtol=1e-12)
    np.testing.assert_allclose(feeds[offset], feeds[offset][0], rtol=1e-12)
    assert feeds[through][0] > feeds[offset][0] > 0
    np.testing.assert_allclose(geometry.arc_lengths(Bump((0.0, 0.0), 90.0, 6.0)),
                               geometry.straight + feeds)


def test_crs_1d_device(layout1d):
    bump = Bump((45.0, 0.0), 90.0, 5.0)  # half-way between pixels 1 and 2
    sp = render(layout1d, bump, "crs").setpoints
    np.testing.assert_allclose(sp[:5], [0.0, 3.75, 3.75, 0.0, 0.0], atol=1e-12)
    beam = layout1d.beams[0]
    assert sp[5] + sp[6] == pytest.approx(
        arc_length(bump, beam.start, beam.end) - beam.straight_length, rel=1e-12)


def test_flat_target_renders_the_neutral_pose(layout2d):
    result = render(layout2d, Bump((0.0, 0.0), 90.0, 0.0), "crs")
    np.testing.assert_array_equal(result.setpoints, layout2d.neutral_setpoints())
    assert result.clamped == ()


def test_pixel_beyond_travel_is_clipped_and_reported(layout2d):
    bump = Bump((0.0, 0.0), 90.0, 12.0)  # pixel 9 asked for 12 mm, travel 9 mm
    result = Renderer(layout2d, "pixel-only").render(bump)
    assert result.setpoints[9] == 9.0
    assert result.setpoints.max() <= 9.0
    assert result.clamped == ("pixel 9: 12.000 mm clipped to 9.000 mm (range 0..9 mm)",)
    with pytest.raises(RenderError, match=r"pixel-only: setpoint out of range: pixel 9: 12.000"):
        Renderer(layout2d, "pixel-only", policy="error").render(bump)


def test_feed_beyond_boundary_travel_is_clipped_and_reported(layout1d):
    # A tall narrow bump: arc excess ~ 39 mm along the beam, more than 2 x 9 mm of travel.
    bump = Bump((60.0, 0.0), 30.0, 30.0)
    result = Renderer(layout1d, "crs").render(bump)
    messages = " | ".join(result.clamped)
    assert "beam 0 end:" in messages and "(range 0..9 mm)" in messages
    assert np.all(result.setpoints <= 9.0)
    with pytest.raises(RenderError, match=r"crs: setpoint out of range: pixel 2: 30.000 mm"):
        Renderer(layout1d, "crs", policy="error").render(bump)


def test_unknown_condition_and_policy_are_one_line_errors(layout2d):
    with pytest.raises(RenderError, match=r"unknown condition 'crss'; known: .*crs.*pixel-only"):
        Renderer(layout2d, "crss")
    with pytest.raises(RenderError, match=r"unknown clamp policy 'ignore'; known: clip, error"):
        Renderer(layout2d, "crs", policy="ignore")


def test_registered_condition_is_used_and_limited(layout2d):
    def everything_up(layout, target, geometry=None):
        return np.full(layout.n_actuators, 10.0)

    register_condition("test-everything-up", everything_up)
    try:
        result = Renderer(layout2d, "test-everything-up").render(Bump((0.0, 0.0), 90.0, 1.0))
        assert isinstance(result, Rendering)
        assert len(result.clamped) == layout2d.n_actuators
        np.testing.assert_array_equal(result.setpoints, 9.0)
    finally:
        CONDITIONS.pop("test-everything-up")


def test_renderer_reuse_matches_one_off_render(layout2d, rng):
    renderer = Renderer(layout2d, "crs")
    for centre in rng.uniform(-60, 60, size=(10, 2)):
        bump = Bump(tuple(centre), 90.0, 5.0)
        np.testing.assert_array_equal(renderer.render(bump).setpoints,
                                      render(layout2d, bump, "crs").setpoints)
