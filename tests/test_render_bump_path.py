"""The fast path of a bump (crs_study.rendering.bump_path and the dense feed cap) renders what
the general path does, and what the renderer rendered before the fast path existed, within
``TOLERANCE_MM``: the sums run in another order (rounding, measured at most 4e-14 mm over these
draws), seven orders of magnitude below a pulse quantum (1 us = 0.009 mm on a 9 mm / 1000 us
servo), and the clip and cap messages are the same.

The oracle ``renderer_before`` is the renderer's limit and feed cap as they were at commit
90d7b34 (before the fast path and the wire's slack), over the unchanged condition functions
(``render_crs``, ``render_pixel_only``: Bump.height and stimuli.targets.arc_excess).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.device.calibration import PulseMap
from crs_study.display.beam import CompressedBeams
from crs_study.errors import RenderError
from crs_study.protocol import load_protocol
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.render import (
    CONDITIONS,
    BeamGeometry,
    Condition,
    Renderer,
    split_feed,
)
from crs_study.stimuli.stimulus import make_stimulus
from crs_study.stimuli.targets import Bump

#: What the fast path may differ by from the general one (mm; module docstring).
TOLERANCE_MM = 1e-10

coordinate = st.floats(-120.0, 120.0, allow_nan=False)
bumps = st.builds(
    Bump,
    centre_mm=st.tuples(coordinate, coordinate),
    diameter_mm=st.floats(5.0, 250.0),
    # past the 9 mm travel too (clipping), and 0 (flat)
    height_mm=st.one_of(st.just(0.0), st.floats(0.0, 12.0), st.floats(0.0, 1e-3)),
)
conditions = st.sampled_from(["crs", "pixel-only"])
devices = st.sampled_from(["crs2d", "crs1d"])


def renderer_before(layout, condition: str, bump: Bump) -> tuple[np.ndarray, tuple[str, ...]]:
    """Renderer(layout, condition).render(bump) at commit 90d7b34 (module docstring)."""
    if layout.lattice == "line" and bump.centre_mm[1] != float(layout.pixel_xy[0, 1]):
        bump = bump.moved_to((bump.centre_mm[0], float(layout.pixel_xy[0, 1])))
    geometry = BeamGeometry(layout)
    raw = CONDITIONS[condition].render(layout, bump, geometry)
    upper = np.array([a.calibration.travel_mm for a in layout.actuators])
    clipped = np.clip(raw, 0.0, upper)
    bad = np.flatnonzero(np.abs(clipped - raw) > 1e-12)
    messages = [f"{layout.actuators[i].name}: {raw[i]:.3f} mm clipped to {clipped[i]:.3f} mm "
                f"(range 0..{upper[i]:g} mm)" for i in bad]
    if layout.beams:
        total = clipped[geometry.start_servo] + clipped[geometry.end_servo]
        if total.any():
            heights = clipped[: layout.n_pixels]
            longest = np.maximum(CompressedBeams.for_layout(layout).longest_feeds(heights), 0.0)
            over = np.flatnonzero(total > longest)
            if over.size:
                clipped = clipped.copy()
                start, end = split_feed(np.minimum(total, longest), layout.boundary_travel_mm)
                clipped[geometry.start_servo[over]] = start[over]
                clipped[geometry.end_servo[over]] = end[over]
                messages += [
                    f"beam {b}: feed {total[b]:.4f} mm capped to {longest[b]:.4f} mm (the "
                    f"longest stable shape through its pixel heights; more would collapse the "
                    f"beam)" for b in over]
    if not messages:
        return raw, ()
    return clipped, tuple(messages)


def general_path(renderer: Renderer, bump: Bump):
    """The renderer's general path (condition function, then limit) for the same bump."""
    if renderer._line_y is not None:
        bump = bump.moved_to((bump.centre_mm[0], renderer._line_y))
    return renderer.limit(CONDITIONS[renderer.condition].render(renderer.layout, bump,
                                                         renderer._geometry))


@pytest.fixture(scope="module")
def layouts(layout2d, layout1d):
    return {"crs2d": layout2d, "crs1d": layout1d}


@settings(max_examples=400, deadline=None)
@given(bump=bumps, condition=conditions, device=devices)
def test_without_the_wire_the_fast_path_renders_what_the_renderer_did_before(
        layouts, bump, condition, device):
    layout = layouts[device]
    expected, expected_messages = renderer_before(layout, condition, bump)
    result = Renderer(layout, condition, wire=None).render(bump)
    np.testing.assert_allclose(result.setpoints, expected, rtol=0, atol=TOLERANCE_MM)
    assert result.clamped == expected_messages


@settings(max_examples=400, deadline=None)
@given(bump=bumps, condition=conditions, device=devices,
       deadband=st.sampled_from([None, 0, 1, 3]))
def test_the_fast_path_renders_what_the_general_path_does(layouts, bump, condition, device,
                                                          deadband):
    layout = layouts[device]
    wire = None if deadband is None else WireSlack(deadband)
    renderer = Renderer(layout, condition, wire=wire)
    fast = renderer.render(bump)
    general = general_path(renderer, bump)
    np.testing.assert_allclose(fast.setpoints, general.setpoints, rtol=0, atol=TOLERANCE_MM)
    assert fast.clamped == general.clamped
    again = renderer.render_bump(bump.centre_mm, bump.diameter_mm, bump.height_mm)
    assert again.setpoints.tobytes() == fast.setpoints.tobytes()


def test_render_bump_checks_its_numbers_as_a_bump_does(layout2d):
    renderer = Renderer(layout2d, "crs")
    with pytest.raises(RenderError, match=r"bump diameter must be > 0 mm, got 0.0"):
        renderer.render_bump((0.0, 0.0), 0.0, 1.0)
    with pytest.raises(RenderError, match=r"bump height must be >= 0 mm, got -1.0"):
        renderer.render_bump((0.0, 0.0), 90.0, -1.0)
    with pytest.raises(RenderError, match=r"bump centre must be finite"):
        renderer.render_bump((float("nan"), 0.0), 90.0, 1.0)


def test_a_bump_subclass_or_a_registered_condition_takes_the_general_path(layout2d):
    calls = []

    def traced(layout, target, geometry=None):
        calls.append(target)
        return CONDITIONS["crs"].render(layout, target, geometry)

    CONDITIONS["test-traced"] = Condition("test-traced", traced, drives_beams=True,
                                          display_model="beam")
    try:
        Renderer(layout2d, "test-traced").render(Bump((0.0, 0.0), 90.0, 5.0))
    finally:
        CONDITIONS.pop("test-traced")
    assert len(calls) == 1


def test_the_shipped_protocols_frames_put_the_same_pulses_on_the_wire(layout2d):
    """Every frame of the default protocol: the fast path's setpoints round to the very pulses
    the general path's do (the wire cannot tell the paths apart)."""
    protocol = load_protocol("digit_identification")
    pulse_map = PulseMap.from_layout(layout2d)
    for condition in ("crs", "pixel-only"):
        renderer = Renderer(layout2d, condition)
        for symbol in protocol.symbols:
            stimulus = make_stimulus(protocol, layout2d, symbol, None)
            for k in range(stimulus.n_frames):
                target = stimulus.target(k)
                fast = renderer.render(target).setpoints
                general = general_path(renderer, target).setpoints
                np.testing.assert_array_equal(pulse_map.to_pulses(fast),
                                              pulse_map.to_pulses(general))
