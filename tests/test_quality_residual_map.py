"""The per-pixel residual map (crs_study.quality.residual_map): a servo's offset at neutral and
its gain recovered from heights at the pixels, the servo named, its endpoints corrected."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.geometry.layout import load_layout
from crs_study.quality.residual_map import (
    pixel_heights,
    reference_offsets,
    residual_map,
)


def _shapes(layout, rng, n=40, height=5.0):
    """Commanded pixel strokes of n bump-like shapes."""
    return rng.uniform(0.0, height, (n, layout.n_pixels))


@given(pixel=st.integers(0, 18), gain=st.floats(0.8, 1.25), seed=st.integers(0, 1000))
def test_property_a_gain_fault_is_recovered_and_named_alone(pixel, gain, seed):
    layout = load_layout("crs2d")
    rng = np.random.default_rng(seed)
    commanded = _shapes(layout, rng)
    residuals = rng.normal(0.0, 0.01, commanded.shape)  # measured - model, clean pixels
    residuals[:, pixel] += (gain - 1.0) * commanded[:, pixel]
    result = residual_map(layout, commanded, residuals, [], height_mm=5.0,
                          offset_limit_mm=0.2, gain_limit=0.05)
    assert result.pixels[pixel].gain == pytest.approx(gain, abs=0.005)
    named = [p.pixel for p in result.flagged]
    assert named == ([pixel] if abs(gain - 1.0) > 0.06 else named)
    assert all(p == pixel for p in named)  # never a healthy servo


def test_an_offset_at_neutral_from_a_tilted_reference():
    """The reference's plane is fitted robustly (the DIC's z axis tilted and offset): a pixel
    sitting 0.4 mm above it is its offset."""
    layout = load_layout("crs2d")
    rng = np.random.default_rng(1)
    gx, gy = np.meshgrid(np.arange(-80.0, 80.0, 1.0), np.arange(-75.0, 75.0, 1.0))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    z = 300.0 + 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + rng.normal(0, 0.01, len(xy))
    bumped = np.hypot(*(xy - layout.pixel_xy[6]).T)
    z += np.where(bumped < 20.0, 0.4 * (1 - bumped / 20.0).clip(0) ** 0.5, 0.0)
    offsets = reference_offsets(xy, z, layout, radius_mm=2.0, noise_mm=0.01)
    assert offsets[6] == pytest.approx(0.4 * (1 - 1 / 20) ** 0.5, abs=0.05)
    assert np.all(np.abs(np.delete(offsets, 6)) < 0.03)
    result = residual_map(layout, np.zeros((0, 19)), np.zeros((0, 19)), [offsets],
                          height_mm=5.0, offset_limit_mm=0.2, gain_limit=0.05)
    assert [p.channel for p in result.flagged] == ["A:7"]
    assert "offset +0.3" in result.flagged[0].why


def test_corrected_endpoints_make_the_real_stroke_the_command():
    """real = a + g c: the new map sends c' = (c - a) / g, so real = c at every stroke."""
    layout = load_layout("crs1d")
    rng = np.random.default_rng(2)
    commanded = _shapes(layout, rng)
    residuals = np.zeros_like(commanded)
    residuals[:, 3] = 0.2 * commanded[:, 3]  # gain 1.2
    offsets = np.zeros(5)
    offsets[3] = 0.3
    result = residual_map(layout, commanded, residuals, [offsets], height_mm=5.0,
                          offset_limit_mm=0.2, gain_limit=0.05)
    (channel, (zero, full)), = result.corrected_endpoints(layout).items()
    assert channel == "A:4"
    cal = layout.pixel_actuators[3].calibration
    for c in (0.5, 3.0, 8.0):
        pulse = zero + (full - zero) * c / cal.travel_mm  # the corrected map
        sent = (pulse - cal.zero_us) * cal.travel_mm / (cal.full_us - cal.zero_us)  # old mm
        assert 0.3 + 1.2 * sent == pytest.approx(c, abs=0.01)  # the real stroke


def test_pixel_heights_stay_inside_the_pixels_hull():
    """Only points inside the hull count (the models end there); their median at each pixel."""
    layout = load_layout("crs1d")
    xy = np.column_stack([np.arange(-5.0, 126.0, 0.5), np.zeros(262)])
    heights = np.where(xy[:, 0] > 120.0, 100.0, 1.0)  # wild beyond the last pixel
    heights[np.abs(xy[:, 0] - 30.0) < 0.1] = 50.0  # one wild point at pixel 1
    (at_pixels,) = pixel_heights(xy, heights, layout=layout, radius_mm=1.5)
    assert at_pixels.tolist() == [1.0] * 5
