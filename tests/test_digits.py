"""Digit strokes: the shipped file, strict loading, arc-length motion (crs_study/digits.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.digits import (
    arc_lengths,
    frames_for_stroke,
    load_digits,
    point_at,
    resample_by_arc_length,
    sample_stroke,
)
from crs_study.errors import ProtocolError


def test_shipped_digits_cover_0_to_9_in_the_unit_box():
    digits = load_digits()
    assert sorted(digits) == list(range(10))
    for digit in digits.values():
        for stroke in digit.strokes:
            assert stroke.shape[1] == 2 and len(stroke) >= 2
            assert stroke.min() >= 0.0 and stroke.max() <= 1.0
            assert not stroke.flags.writeable


def test_two_stroke_digits_are_4_and_5():
    digits = load_digits()
    assert {d for d, v in digits.items() if len(v.strokes) == 2} == {4, 5}


def test_zero_is_an_ellipse_of_the_right_perimeter():
    # Ramanujan's approximation of an ellipse's perimeter, pi (3(a+b) - sqrt((3a+b)(a+3b))),
    # for semi-axes a = w/2, b = h/2. A 16-chord inscribed polygon is shorter by about
    # (pi^2/6) / 16^2 of a circle's perimeter (0.6 %), so allow 1 %.
    w, h = 0.49 * 30, 0.81 * 30
    a, b = w / 2, h / 2
    ramanujan = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    length = load_digits()[0].length_mm(w, h)
    assert length == pytest.approx(ramanujan, rel=0.01)
    assert length < ramanujan  # inscribed


def test_scaled_maps_the_unit_box_around_the_centre():
    one = load_digits()[1]
    top = one.scaled(10.0, 20.0, (5.0, -3.0))[0]
    # The 1's top point is (0.5, 1.0) in the box: x = 5 + 0, y = -3 + 0.5 * 20.
    assert top[1] == pytest.approx([5.0, 7.0])


def test_arc_lengths_and_point_at_on_a_right_angle():
    path = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    assert arc_lengths(path) == pytest.approx([0.0, 3.0, 7.0])
    assert point_at(path, np.array([0.0, 1.5, 5.0, 99.0])) == pytest.approx(
        np.array([[0.0, 0.0], [1.5, 0.0], [3.0, 2.0], [3.0, 4.0]]))


def test_sample_stroke_moves_at_constant_speed_and_ends_on_the_last_point():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])  # 15 mm
    points = sample_stroke(path, speed_mm_s=20.0, frame_rate_hz=15.0)
    assert len(points) == frames_for_stroke(15.0, 20.0, 15.0) == math.ceil(15 * 15 / 20) + 1
    s = arc_lengths(points)
    steps = np.diff(s)
    # The corner cuts the chord of one step; along the arc every step is v/f except the last.
    along = np.concatenate([[0.0], np.minimum(np.arange(1, len(points)) * 20 / 15, 15.0)])
    assert point_at(path, along) == pytest.approx(points)
    assert steps[-1] <= 20 / 15 + 1e-12
    assert points[-1] == pytest.approx([10.0, 5.0])


def test_frames_for_an_exact_multiple_is_not_rounded_up():
    assert frames_for_stroke(3.0, 1.0, 1.0) == 4


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.floats(0, 1)), min_size=2, max_size=12),
       st.floats(1.0, 100.0), st.floats(5.0, 60.0))
def test_sampling_is_monotone_in_arc_length(points, speed, rate):
    path = np.array(points) * 30.0
    total = arc_lengths(path)[-1]
    if total < 1e-6:
        return
    samples = sample_stroke(path, speed, rate)
    expected = np.minimum(np.arange(len(samples)) * speed / rate, total)
    assert point_at(path, expected) == pytest.approx(samples, abs=1e-9)
    assert expected[-1] == pytest.approx(total)
    assert expected[-2] < total
    even = resample_by_arc_length(path, 7)
    assert even[0] == pytest.approx(path[0]) and even[-1] == pytest.approx(path[-1])


HEADER = "format = 1\n"


@pytest.mark.parametrize("body, match", [
    pytest.param("format = 2\n[digits.0]\nstrokes = [[[0, 0], [1, 1]]]\n",
                 r"format: expected 1, got 2", id="format"),
    pytest.param(HEADER + "[digits.x]\nstrokes = [[[0, 0], [1, 1]]]\n",
                 r"digits.x: expected a digit 0 to 9", id="key"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1.5, 1]]]\n",
                 r"digits.3.strokes\[0\]\[1\]: expected x and y in the unit box.*1.5", id="box"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0]]]\n",
                 r"digits.3.strokes\[0\]: expected a list of at least 2", id="short"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0.5, 0.5], [0.5, 0.5]]]\n",
                 r"digits.3.strokes\[0\]: a stroke must have a length > 0", id="zero-length"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1, \"a\"]]]\n",
                 r"digits.3.strokes\[0\]\[1\]: expected \[x, y\] numbers", id="type"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1, 1]]]\ncolour = 1\n",
                 r"digits.3: unknown key 'colour'", id="unknown"),
    pytest.param(HEADER + "[digits.3]\nstrokes = []\n",
                 r"digits.3.strokes: expected at least one stroke", id="no-stroke"),
    pytest.param(HEADER + "[digits]\n", r"digits: expected at least one digit", id="empty"),
    pytest.param(HEADER + "[digits.3\n", r"not valid TOML", id="syntax"),
])
def test_strict_loading(tmp_path, body, match):
    path = tmp_path / "strokes.toml"
    path.write_text(body)
    with pytest.raises(ProtocolError, match=match):
        load_digits(path)


def test_missing_file(tmp_path):
    with pytest.raises(ProtocolError, match=r"no such strokes file"):
        load_digits(tmp_path / "nope.toml")


def test_own_file_is_read_and_reloaded_when_changed(tmp_path):
    path = tmp_path / "strokes.toml"
    path.write_text(HEADER + "[digits.7]\nstrokes = [[[0, 1], [1, 1], [0.3, 0]]]\n")
    assert list(load_digits(path)) == [7]
    import os
    import time

    path.write_text(HEADER + "[digits.1]\nstrokes = [[[0.5, 1], [0.5, 0]]]\n")
    os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))
    assert list(load_digits(path)) == [1]
