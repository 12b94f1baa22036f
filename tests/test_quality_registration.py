"""Registration by pixel fiducials (crs_study.quality.registration): a least-squares rigid or
similarity map recovers a known misregistration; mirror images and too few fiducials are
refused; the residual is reported and checked."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.errors import MeasurementError
from crs_study.geometry.layout import load_layout
from crs_study.quality.dic_import import Fiducials
from crs_study.quality.registration import fit_registration


def _dic(layout, angle_deg, shift, scale=1.0, noise=0.0, seed=0):
    """Pixels in a DIC frame turned by ``angle_deg``, shifted and scaled (column vectors)."""
    a = math.radians(angle_deg)
    rotation = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    rng = np.random.default_rng(seed)
    xy = scale * (layout.pixel_xy @ rotation.T + np.asarray(shift))
    return Fiducials("f.csv", np.arange(layout.n_pixels), xy + rng.normal(0, noise, xy.shape))


@given(angle=st.floats(-179, 179), sx=st.floats(-500, 500), sy=st.floats(-500, 500),
       scale=st.floats(0.5, 2.0), device=st.sampled_from(["crs1d", "crs2d"]),
       mode=st.sampled_from(["rigid", "similarity"]))
def test_property_an_exact_misregistration_is_recovered(angle, sx, sy, scale, device, mode):
    layout = load_layout(device)
    used = scale if mode == "similarity" else 1.0
    fit = fit_registration(_dic(layout, angle, (sx, sy), used), layout, mode)
    assert fit.rms_mm < 1e-6 * max(1.0, abs(sx), abs(sy))
    assert fit.scale == pytest.approx(1.0 / used)
    assert math.remainder(fit.rotation_deg + angle, 360.0) == pytest.approx(0.0, abs=1e-6)
    back = fit.to_display(_dic(layout, angle, (sx, sy), used).xy)
    np.testing.assert_allclose(back, layout.pixel_xy, atol=1e-6 * max(1.0, abs(sx), abs(sy)))


def test_noise_on_the_fiducials_is_the_residual():
    layout = load_layout("crs2d")
    fit = fit_registration(_dic(layout, 12.0, (40.0, -25.0), noise=0.05, seed=3), layout)
    # 19 fiducials (38 coordinates), 3 parameters: the RMS distance estimates the marking
    # noise, sigma sqrt(2 (38 - 3) / 38)
    assert fit.rms_mm == pytest.approx(0.05 * math.sqrt(2 * 35 / 38), rel=0.35)
    assert fit.rotation_deg == pytest.approx(-12.0, abs=0.05)
    assert fit.worst_pixel in range(19) and fit.max_mm >= fit.rms_mm
    fit.check(0.5)
    with pytest.raises(MeasurementError, match=r"misses by 0.0\d+ mm RMS, beyond the "
                                               r"protocol's 0.01 mm; the worst is pixel"):
        fit.check(0.01)


def test_a_mirror_image_is_refused_but_a_line_is_not_one():
    layout = load_layout("crs2d")
    mirrored = _dic(layout, 0.0, (0.0, 0.0))
    flipped = Fiducials("f.csv", mirrored.pixels, mirrored.xy * np.array([1.0, -1.0]))
    with pytest.raises(MeasurementError, match="only as a mirror image"):
        fit_registration(flipped, layout)
    line = load_layout("crs1d")  # collinear: the mirror across the line fits as well
    fit = fit_registration(_dic(line, 150.0, (3.0, 4.0)), line)
    assert fit.rotation_deg == pytest.approx(-150.0) and fit.rms_mm < 1e-9


def test_a_wrong_pixel_is_named():
    layout = load_layout("crs2d")
    fiducials = _dic(layout, 5.0, (1.0, 2.0))
    swapped = fiducials.xy.copy()
    swapped[[4, 5]] = swapped[[5, 4]]
    fit = fit_registration(Fiducials("f.csv", fiducials.pixels, swapped), layout)
    assert fit.worst_pixel in (4, 5) and fit.max_mm > 10.0


def test_too_few_or_unknown_fiducials():
    layout = load_layout("crs2d")
    few = _dic(layout, 0.0, (0.0, 0.0))
    with pytest.raises(MeasurementError, match="2 fiducial\\(s\\); expected at least 3"):
        fit_registration(Fiducials("f.csv", few.pixels[:2], few.xy[:2]), layout)
    with pytest.raises(MeasurementError, match="pixel 40 is not on crs2d"):
        fit_registration(Fiducials("f.csv", np.array([0, 1, 40]), few.xy[:3]), layout)
    with pytest.raises(MeasurementError, match="at one point"):
        fit_registration(Fiducials("f.csv", np.array([0, 1, 2]), np.zeros((3, 2))), layout)
