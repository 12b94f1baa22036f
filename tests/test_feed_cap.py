"""The feed cap (crs_study.rendering.feed_cap): what the boards actually hold never collapses.

The bug (found by the live link's helper): the cap kept each beam at or below its longest
stable shape,
but the boards hold whole-us pulses, and the write policy resends a channel only when it moved
by more than the dead-band; decoded from the boards, 3 of 186 frames of a finger writing 9
made ``CompressedBeams.solve`` raise CollapseError. These tests render frames, send them to the
simulated device (its virtual LSC-24 boards decode the very bytes a serial port would carry),
read the pulses the boards' servos then hold back as setpoints (``displayed_setpoints`` once the
servos are in place) and solve the beam model on them: the source of truth is the beam model of
crs_study.display.beam (Eq. 3 with the arc-length constraint) on the boards' own decoding, not
the renderer's arithmetic.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.clock import VirtualClock
from crs_study.device import calibration, writes
from crs_study.device.base import open_device
from crs_study.device.calibration import PulseMap
from crs_study.display.beam import CompressedBeams
from crs_study.errors import CollapseError, RenderError
from crs_study.live.area import RecognitionArea
from crs_study.live.session import LiveSession
from crs_study.live.trace import digit_trace
from crs_study.protocol import load_protocol
from crs_study.rendering import feed_cap
from crs_study.rendering.feed_cap import FeedCap, WireSlack, mm_per_us
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import make_stimulus

#: Virtual seconds between frames: the wire carries any frame and the servos arrive (a full
#: 9 mm stroke takes 72 ms) well within it.
SETTLE_S = 0.2


def collapses(layout, renderer, frames, url="sim://", **options) -> list[int]:
    """Indices of the frames whose setpoints, as the simulated boards hold them, collapse a
    beam. ``frames``: (x, y, z) bump centres (layout frame) and heights, z <= 0 for flat."""
    solver = CompressedBeams.for_layout(layout)
    clock = VirtualClock()
    device = open_device(url, layout, clock, **options)
    device.open()
    bad = []
    try:
        for k, (x, y, diameter, z) in enumerate(frames):
            setpoints = (layout.neutral_setpoints() if z <= 0.0 else
                         renderer.render_bump((x, y), diameter, z).setpoints)
            device.send(setpoints)
            clock.advance(SETTLE_S)
            held = device.displayed_setpoints()  # the boards' pulses, decoded, servos arrived
            try:
                solver.solve(held, check_yield_curvature=False)
            except CollapseError:
                bad.append(k)
    finally:
        device.close()
    return bad


def digit_frames(layout, digit: int) -> list[tuple[float, float, float, float]]:
    """A finger writing ``digit`` (60 mm high, 30 mm/s, pressing 5 mm) as the live link shows
    it, one frame every other packet of the 72 packets/s."""
    area = RecognitionArea.for_layout(layout)
    frames = []
    for x, y, z in digit_trace(digit, height_mm=60.0, speed_mm_s=30.0,
                               press_mm=5.0).xyz[::2].tolist():
        placed = area.place(x, y, z)
        frames.append((0.0, 0.0, 90.0, 0.0) if placed is None
                      else (placed[0], placed[1], area.diameter_mm, placed[2]))
    return frames


def test_the_constants_are_the_devices():
    assert feed_cap.PULSE_QUANTUM_US == calibration.PULSE_QUANTUM_US
    assert feed_cap.WIRE_DEADBAND_US == writes.DEFAULT_DEADBAND_US


def test_pulses_are_whole_quanta(layout2d, rng):
    pulse_map = PulseMap.from_layout(layout2d)
    travel = np.array([a.calibration.travel_mm for a in layout2d.actuators])
    pulses = pulse_map.to_pulses(rng.uniform(0.0, 1.0, (50, layout2d.n_actuators)) * travel)
    assert np.all(pulses % calibration.PULSE_QUANTUM_US == 0)


@pytest.mark.parametrize("digit", [9, 8, 2])
def test_a_finger_writing_a_digit_never_collapses_a_beam_on_the_boards(layout2d, digit):
    frames = digit_frames(layout2d, digit)
    assert collapses(layout2d, Renderer(layout2d, "crs"), frames) == []
    # the same frames capped at the longest stable shape alone (no room for the wire) do
    # collapse once on the boards: the bug, and this test's power to see it
    assert collapses(layout2d, Renderer(layout2d, "crs", wire=None), frames) != []


def test_a_wider_dead_band_needs_and_gets_more_room(layout2d):
    frames = digit_frames(layout2d, 8)
    options = {"deadband_us": 3, "refresh_s": 0.0}  # never repaired by a full write
    assert collapses(layout2d, Renderer(layout2d, "crs", wire=WireSlack(3)), frames,
                     **options) == []
    assert collapses(layout2d, Renderer(layout2d, "crs"), frames, **options) != []


# Bumps near the cap: tall, narrow or wide, centred anywhere over the display and beyond its
# pixels (where a beam is crossed between pixels with every pixel flat), and flat frames
# between them (a beam going flat while the dead-band could hold a feed).
frame = st.tuples(st.floats(-60.0, 60.0), st.floats(-60.0, 60.0), st.floats(20.0, 160.0),
                  st.one_of(st.just(0.0), st.floats(0.05, 9.0), st.floats(6.0, 9.0)))


@settings(max_examples=40, deadline=None)
@given(frames=st.lists(frame, min_size=2, max_size=12), deadband=st.sampled_from([0, 1, 2]),
       refresh_s=st.sampled_from([0.0, 1.0]))
def test_random_frames_near_the_cap_never_collapse_on_the_boards(layout2d, frames, deadband,
                                                                 refresh_s):
    renderer = Renderer(layout2d, "crs", wire=WireSlack(deadband))
    assert collapses(layout2d, renderer, frames, deadband_us=deadband,
                     refresh_s=refresh_s) == []


@settings(max_examples=25, deadline=None)
@given(frames=st.lists(st.tuples(st.floats(-20.0, 20.0), st.just(0.0), st.floats(10.0, 120.0),
                                 st.one_of(st.just(0.0), st.floats(0.05, 9.0))),
                       min_size=2, max_size=10))
def test_random_frames_never_collapse_the_1d_beam(layout1d, frames):
    assert collapses(layout1d, Renderer(layout1d, "crs"), frames) == []


# -- the cap's numbers ---------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(fraction=st.lists(st.floats(0.0, 1.0), min_size=19, max_size=19),
       flat=st.lists(st.booleans(), min_size=19, max_size=19))
def test_longest_is_the_beam_models(layout2d, fraction, flat):
    """FeedCap's dense products give CompressedBeams.longest_feeds (rounding aside)."""
    heights = np.where(flat, 0.0, np.array(fraction) * 9.0)
    longest, room = FeedCap(layout2d, None).limits(heights)
    expected = np.maximum(CompressedBeams.for_layout(layout2d).longest_feeds(heights), 0.0)
    np.testing.assert_allclose(longest, expected, rtol=1e-12, atol=1e-12)
    assert room == longest  # without a wire the room is the longest shape itself


@settings(max_examples=60, deadline=None)
@given(fraction=st.lists(st.floats(0.0, 1.0), min_size=19, max_size=19),
       flat=st.lists(st.booleans(), min_size=19, max_size=19),
       moves=st.lists(st.floats(-1.0, 1.0), min_size=19, max_size=19))
def test_the_room_holds_for_any_heights_within_their_hold(layout2d, fraction, flat, moves):
    """Rule 1: with the pixels anywhere within their hold of h (and the feed on the boards
    up to both ends' hold above the room), the beam is still within its longest shape."""
    cap = FeedCap(layout2d, WireSlack())
    heights = np.where(flat, 0.0, np.array(fraction) * 9.0)
    _, room = cap.limits(heights)
    held = np.clip(heights + np.array(moves) * cap.height_hold, 0.0, 9.0)
    longest_held = CompressedBeams.for_layout(layout2d).longest_feeds(held)
    for b, feed in enumerate(room):
        if feed > 0.0:
            assert feed + cap.feed_hold[b] <= longest_held[b] + 1e-12


def test_rule_2_sets_feeds_within_the_hold_to_rest_and_says_nothing(layout2d):
    cap = FeedCap(layout2d, WireSlack())
    hold = mm_per_us(layout2d)[layout2d.n_pixels] * WireSlack().hold_us
    heights = np.full(layout2d.n_pixels, 4.0)
    starts = [hold] * len(layout2d.beams)
    ends = [hold * 1.01] * len(layout2d.beams)
    capped_starts, capped_ends, messages = cap.apply(heights, starts, ends)
    assert capped_starts == [0.0] * len(starts)  # at the hold: could be held over a rest
    assert capped_ends == ends  # clear of it: kept
    assert messages == []


def test_wire_slack_checks_its_numbers():
    with pytest.raises(RenderError, match=r"dead-band: expected a whole number of us >= 0, "
                                          r"got -1"):
        WireSlack(-1)
    with pytest.raises(RenderError, match=r"dead-band: .* got 1.5"):
        WireSlack(1.5)
    with pytest.raises(RenderError, match=r"pulse quantum: expected us > 0, got 0"):
        WireSlack(1, 0)
    assert WireSlack(2).hold_us == 2.5


def test_the_frame_cache_keeps_renderings_for_another_wire_apart(layout2d):
    stimulus = make_stimulus(load_protocol("pilot"), layout2d, 4, None)
    exact = render_frames(stimulus, Renderer(layout2d, "crs", wire=None))
    roomy = render_frames(stimulus, Renderer(layout2d, "crs"))
    assert not np.array_equal(exact, roomy)  # the cap's room and rule 2 change some feeds
    assert np.array_equal(roomy, render_frames(stimulus, Renderer(layout2d, "crs")))


def test_a_live_session_leaves_room_for_its_devices_dead_band(layout2d):
    for deadband in (0, 1, 3):
        device = open_device(f"sim://?deadband_us={deadband}", layout2d, VirtualClock())
        assert LiveSession(device).renderer.wire == WireSlack(deadband)
