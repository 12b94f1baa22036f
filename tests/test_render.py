"""Tests for crs_study.rendering.render: conditions, the split rule, the clamp policy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.errors import CollapseError, RenderError
from crs_study.rendering.render import (
    CONDITIONS,
    BeamGeometry,
    Condition,
    Renderer,
    Rendering,
    register_condition,
    render,
    split_feed,
)
from crs_study.stimuli.targets import Bump, arc_length

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
    result = Renderer(layout2d, "crs", cap_feed=False).render(bump)  # the paper's rule
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


@pytest.mark.parametrize("condition", ["pixel-only", "crs"])
def test_a_1d_device_shows_the_profile_in_x_alone(layout1d, condition):
    """The 1D counterpart of Eq. 7 is rho = |x - x_f|: y_f must not lower the pixels or the
    feeds (a bump at y_f = 20 mm used to render as a slice 20 mm off its centre)."""
    on_line = render(layout1d, Bump((45.0, 0.0), 90.0, 5.0), condition)
    off_line = render(layout1d, Bump((45.0, 20.0), 90.0, 5.0), condition)
    np.testing.assert_array_equal(off_line.setpoints, on_line.setpoints)
    # raised cosine at the pixels, 30 mm apart: z_f/2 (1 + cos(2 pi dx / l))
    dx = layout1d.pixel_xy[:, 0] - 45.0
    expected = np.where(np.abs(dx) <= 45.0, 2.5 * (1 + np.cos(2 * np.pi * dx / 90.0)), 0.0)
    np.testing.assert_allclose(on_line.setpoints[: layout1d.n_pixels], expected, atol=1e-12)


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

    register_condition(Condition("test-everything-up", everything_up, drives_beams=True,
                                 display_model="beam"))
    try:
        renderer = Renderer(layout2d, "test-everything-up", cap_feed=False)  # clipping only
        result = renderer.render(Bump((0.0, 0.0), 90.0, 1.0))
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


# --- the feed cap: the commanded display never asks a beam to collapse -------------------------
def test_flat_beam_crossed_between_pixels_is_capped_not_collapsed(layout2d):
    """Bump centre beyond the pixel hull: a beam's line crosses the bump between its pixels
    while all its pixels stay at base. The paper's rule feeds it ~10 um; the beam can take
    only the steel's shortening (~margin N_cr S / EA, a few um) and the beam model raises
    CollapseError on the uncapped frame. Capped, it solves, and the cap is reported."""
    from crs_study.display.beam import CompressedBeams

    bump = Bump((-85.0, 0.0), 90.0, 2.0)  # crosses beam 0 between its clamp and pixel 3
    solver = CompressedBeams.for_layout(layout2d)
    raw = Renderer(layout2d, "crs", cap_feed=False).render(bump)
    with pytest.raises(CollapseError, match="beam 0: commanded length"):
        solver.solve(raw.setpoints)
    # wire=None: the cap itself, for setpoints that reach the beams exactly (the room the
    # boards' pulses need is tests/test_feed_cap.py's)
    capped = Renderer(layout2d, "crs", wire=None).render(bump)
    assert any(m.startswith("beam 0: feed ") and "capped to" in m for m in capped.clamped)
    beam = layout2d.beams[0]
    assert np.all(capped.setpoints[list(beam.pixels)] == 0.0)
    assert raw.setpoints[beam.start_servo] + raw.setpoints[beam.end_servo] > 8e-3
    ea = layout2d.beam_section.youngs_modulus_mpa * layout2d.beam_section.area_mm2
    fed = capped.setpoints[beam.start_servo] + capped.setpoints[beam.end_servo]
    flat_limit = 0.98 * solver.critical_load_n[0] * beam.straight_length / ea
    assert fed == pytest.approx(flat_limit, rel=1e-3)  # the straight beam's elastic shortening
    profiles = solver.solve(capped.setpoints)
    assert profiles.axial_load_n[0] == pytest.approx(0.98 * solver.critical_load_n[0], rel=1e-3)
    with pytest.raises(RenderError, match=r"crs: beam 0: feed .* capped to .* collapse"):
        Renderer(layout2d, "crs", policy="error").render(bump)


@settings(max_examples=40, deadline=None)
@given(bump=device_bumps)
def test_capped_crs_frames_always_solve_and_uncapped_beams_keep_the_rule(layout2d, bump):
    from crs_study.display.beam import CompressedBeams

    solver = CompressedBeams.for_layout(layout2d)
    paper = Renderer(layout2d, "crs", cap_feed=False).render(bump).setpoints
    result = Renderer(layout2d, "crs", wire=None).render(bump)  # setpoints reach the beams
    sp = result.setpoints
    try:
        solver.solve(sp, check_yield_curvature=False)
    except CollapseError as exc:  # pragma: no cover - the property under test
        raise AssertionError(f"capped frame collapses: {exc}") from None
    capped = {int(m.split()[1].rstrip(":")) for m in result.clamped if m.startswith("beam ")}
    longest = solver.longest_feeds(sp[: layout2d.n_pixels])
    for b, beam in enumerate(layout2d.beams):
        fed = sp[beam.start_servo] + sp[beam.end_servo]
        if b in capped:
            assert fed == pytest.approx(longest[b], abs=1e-12)
            assert fed < paper[beam.start_servo] + paper[beam.end_servo]
        else:
            np.testing.assert_allclose(sp[[beam.start_servo, beam.end_servo]],
                                       paper[[beam.start_servo, beam.end_servo]])


def test_pixel_only_never_builds_the_beam_solver(layout2d):
    renderer = Renderer(layout2d, "pixel-only")
    renderer.render(Bump((0.0, 0.0), 90.0, 5.0))
    assert renderer._beams is None
