"""Stimuli: the bump's path over time, the render cache, device checks (stimuli/stimulus.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crs_study.paths import shipped_file
from crs_study.protocol import load_protocol
from crs_study.protocol.feasibility import collapse_delta
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.digits import arc_lengths
from crs_study.stimuli.stimulus import display_centre, inside_convex_hull, make_stimulus


@pytest.fixture(scope="module")
def protocol():
    return load_protocol(shipped_file("protocols/digit_identification.toml"))


def test_frames_are_sampled_at_the_frame_rate(protocol, layout2d):
    stim = make_stimulus(protocol, layout2d, 3)
    f = protocol.frame_rate_hz
    assert stim.frame_times == pytest.approx(np.arange(stim.n_frames) / f)
    assert stim.duration_s == pytest.approx(stim.n_frames / f)
    assert stim.diameter_mm == 90.0


def test_bump_moves_at_the_stroke_speed(protocol, layout2d):
    spec = protocol.stimulus
    stim = make_stimulus(protocol, layout2d, 0)
    moving = arc_lengths(stim.centres_mm)
    steps = np.diff(moving)
    step = spec.stroke_speed_mm_s / spec.frame_rate_hz
    # Holds do not move; each drawing step covers v/f along the arc, and the chord of a step
    # is at most v/f (equal on straight parts, a little shorter across a corner).
    assert steps.max() <= step + 1e-9
    assert np.sum(steps > 0.9 * step) > 0.8 * np.sum(steps > 0)
    hold = round(spec.start_hold_s * spec.frame_rate_hz)
    assert np.all(stim.centres_mm[:hold] == stim.centres_mm[0])
    assert np.all(stim.heights_mm == spec.bump_height_mm)  # one stroke: never lifted


def test_one_stroke_digit_duration_matches_its_length(protocol, layout2d):
    spec = protocol.stimulus
    pitch = layout2d.pitch_mm
    from crs_study.stimuli.digits import load_digits

    length = load_digits()[7].length_mm(spec.symbol_width_pitch * pitch,
                                        spec.symbol_height_pitch * pitch)
    stim = make_stimulus(protocol, layout2d, 7)
    f = spec.frame_rate_hz
    expected = (round(spec.start_hold_s * f) + math.ceil(length * f / spec.stroke_speed_mm_s)
                + 1 + round(spec.end_hold_s * f))
    assert stim.n_frames == expected


@pytest.mark.parametrize("digit", [4, 5])
def test_two_stroke_digits_lift_the_bump_between_strokes(protocol, layout2d, digit):
    stim = make_stimulus(protocol, layout2d, digit)
    lifted = stim.stroke_index == -1
    f = protocol.frame_rate_hz
    assert lifted.sum() == max(1, round(protocol.stimulus.stroke_pause_s * f))
    assert np.all(stim.heights_mm[lifted] == 0.0)
    assert np.all(stim.heights_mm[~lifted] == protocol.stimulus.bump_height_mm)
    assert set(stim.stroke_index.tolist()) == {-1, 0, 1}
    # The lifted frames wait at the second stroke's first point: the bump rises there.
    first_of_second = np.flatnonzero(stim.stroke_index == 1)[0]
    assert stim.centres_mm[lifted][-1] == pytest.approx(stim.centres_mm[first_of_second])
    assert stim.target(int(np.flatnonzero(lifted)[0])).height_mm == 0.0


def test_digit_box_is_centred_on_the_display(protocol, layout2d):
    assert display_centre(layout2d) == pytest.approx((0.0, 0.0), abs=1e-9)
    # The protocol's digit width and height are the digits' mean bounding box (protocols/
    # README.md), so a wide digit may pass the box; the set of digits sits centred.
    stimuli = [make_stimulus(protocol, layout2d, d) for d in protocol.symbols]
    everything = np.concatenate([s.centres_mm for s in stimuli])
    np.testing.assert_allclose(everything.max(axis=0), -everything.min(axis=0), atol=1e-9)
    size = np.array([protocol.stimulus.symbol_width_pitch,
                     protocol.stimulus.symbol_height_pitch]) * layout2d.pitch_mm
    extents = np.array([np.ptp(s.centres_mm[s.drawn], axis=0) for s in stimuli])
    assert extents.mean(axis=0) == pytest.approx(size, rel=0.02)


def test_stimulus_arrays_are_read_only_and_cached(protocol, layout2d):
    stim = make_stimulus(protocol, layout2d, 8)
    assert make_stimulus(protocol, layout2d, 8) is stim
    with pytest.raises(ValueError):
        stim.centres_mm[0, 0] = 1.0


def test_render_frames_equals_rendering_each_target_and_is_cached(protocol, layout2d):
    stim = make_stimulus(protocol, layout2d, 2)
    renderer = Renderer(layout2d, "crs")
    frames = render_frames(stim, renderer)
    assert frames.shape == (stim.n_frames, layout2d.n_actuators)
    k = stim.n_frames // 2
    assert frames[k] == pytest.approx(renderer.render(stim.target(k)).setpoints)
    # Pixel heights are Eq. 7 sampled at the pixels.
    assert frames[k, : layout2d.n_pixels] == pytest.approx(
        stim.target(k).height(layout2d.pixel_xy))
    assert render_frames(stim, Renderer(layout2d, "crs")) is frames
    assert not frames.flags.writeable
    pixel_only = render_frames(stim, Renderer(layout2d, "pixel-only"))
    assert np.all(pixel_only[:, layout2d.n_pixels:] == 0)
    assert frames[:, layout2d.n_pixels:].max() > 0  # the skeleton is fed


def test_inside_convex_hull_margin():
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    inside, margin = inside_convex_hull(np.array([[5.0, 5.0], [1.0, 9.0]]), square)
    assert inside.all() and margin == pytest.approx(1.0)
    inside, margin = inside_convex_hull(np.array([[5.0, 5.0], [12.0, 5.0]]), square)
    assert inside.tolist() == [True, False] and margin == pytest.approx(-2.0)


def test_collapse_delta_is_eq_4(layout2d):
    # Eq. 4: Delta = 16 pi^4 E I / (27 beta d^4); E = 193 GPa, I = 1 x 0.15^3 / 12 mm^4,
    # beta = 1 kPa = 1e-3 N/mm^2, d = 30 mm -> 3.87 (the device file says 3.9).
    expected = 16 * math.pi**4 * 193e3 * (1.0 * 0.15**3 / 12) / (27 * 1e-3 * 30.0**4)
    assert collapse_delta(layout2d) == pytest.approx(expected)
    assert collapse_delta(layout2d) == pytest.approx(3.87, abs=0.01)


def test_the_device_check_and_the_sessions_share_one_rendering(protocol, layout2d):
    # a stimulus rendered within travel under policy="error" needs no clip: the sessions'
    # policy="clip" is served the very same frames, never a second rendering
    from dataclasses import replace

    from crs_study.stimuli.stimulus import placement_centre, stimulus_for

    spec = replace(protocol.stimulus, bump_height_mm=4.321)  # rendered nowhere else
    stim = stimulus_for(spec, layout2d.pitch_mm, placement_centre(spec, layout2d), 3)
    checked = render_frames(stim, Renderer(layout2d, "crs", policy="error"))
    assert render_frames(stim, Renderer(layout2d, "crs")) is checked
    # the feed cap shapes the frames: not the same entry
    assert render_frames(stim, Renderer(layout2d, "crs", cap_feed=False)) is not checked


def test_clipped_frames_are_still_refused_under_the_error_policy(protocol, layout2d):
    from dataclasses import replace

    from crs_study.errors import RenderError
    from crs_study.stimuli.stimulus import placement_centre, stimulus_for

    spec = replace(protocol.stimulus, bump_height_mm=9.5)  # above the 9 mm pixel travel
    stim = stimulus_for(spec, layout2d.pitch_mm, placement_centre(spec, layout2d), 1)
    clipped = render_frames(stim, Renderer(layout2d, "pixel-only"))
    assert clipped[:, : layout2d.n_pixels].max() == pytest.approx(layout2d.travel_mm)
    with pytest.raises(RenderError, match=r"pixel-only: setpoint out of range"):
        render_frames(stim, Renderer(layout2d, "pixel-only", policy="error"))
    assert render_frames(stim, Renderer(layout2d, "pixel-only")) is clipped
