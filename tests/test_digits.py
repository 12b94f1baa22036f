"""Digit strokes: the shipped file, strict loading, arc-length motion (stimuli/digits.py)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.errors import ProtocolError
from crs_study.protocol import load_protocol
from crs_study.stimuli.digits import (
    arc_lengths,
    frames_for_stroke,
    load_digits,
    mean_extent,
    point_at,
    resample_by_arc_length,
    sample_stroke,
)


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
    # for semi-axes a = w0/2, b = h0/2, the 0's own extents (it fills the unit box, which is
    # scaled by w / W, h / H). A 16-chord inscribed polygon is shorter by about
    # (pi^2/6) / 16^2 of a circle's perimeter (0.6 %), so allow 1 %.
    zero = load_digits()[0]
    w, h = 0.49 * 30, 0.81 * 30
    big_w, big_h = zero.mean_extent
    a, b = w / big_w / 2, h / big_h / 2
    ramanujan = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    length = zero.length_mm(w, h)
    assert length == pytest.approx(ramanujan, rel=0.01)
    assert length < ramanujan  # inscribed


def test_scaled_maps_the_unit_box_around_the_centre():
    one = load_digits()[1]
    big_w, big_h = one.mean_extent
    flag, top, _ = one.scaled(10.0, 20.0, (5.0, -3.0))[0]
    # The 1's top point is (0.5, 1.0) in the box: x = 5 + 0, y = -3 + 0.5 * 20 / H.
    assert top == pytest.approx([5.0, -3.0 + 0.5 * 20.0 / big_h])
    # its flag starts at (0.2, 0.75): x = 5 - 0.3 * 10 / W, y = -3 + 0.25 * 20 / H
    assert flag == pytest.approx([5.0 - 0.3 * 10.0 / big_w, -3.0 + 0.25 * 20.0 / big_h])


def test_shipped_mean_extents():
    # The shipped strokes' bounding boxes (unit box), by hand from crs_study/data/digits.toml:
    # widths 1, 0.3, 1, 0.93, 1, 0.933, 0.9, 1, 0.95, 0.9 (mean 0.8913); heights 1, 1, 1,
    # 0.992, 1, 0.999, 0.967, 1, 1, 1 (mean 0.9958).
    digits = load_digits()
    assert mean_extent(digits) == pytest.approx((0.8913, 0.9958), abs=1e-12)
    assert all(d.mean_extent == mean_extent(digits) for d in digits.values())
    assert digits[1].extent == pytest.approx((0.3, 1.0))


PAPER_SIZE = (0.49, 0.81)  # Wang, Meng & Chen 2025: "The average height and width of digits
#                            are only#                            0.81- and 0.49-pixel pitch."


@pytest.mark.parametrize("protocol_name", ["digit_identification.toml", "pilot.toml"])
def test_protocol_size_is_the_mean_bounding_box_of_the_shown_digits(protocol_name):
    """The protocol's digit_width_pitch x digit_height_pitch is what the ten digits measure
    on average: on their strokes exactly, on the drawn bump path (corners between frames
    cut by under one frame's step) to a few hundredths of a pitch."""
    from crs_study.paths import shipped_file
    from crs_study.protocol import load_protocol
    from crs_study.stimuli.stimulus import make_stimulus

    protocol = load_protocol(shipped_file(f"protocols/{protocol_name}"))
    spec = protocol.stimulus
    assert (spec.symbol_width_pitch, spec.symbol_height_pitch) == PAPER_SIZE
    layout = protocol.layout()
    pitch = layout.pitch_mm
    digits = load_digits(spec.strokes_file)
    boxes = []
    for d in protocol.symbols:
        points = np.concatenate(digits[d].scaled(spec.symbol_width_pitch * pitch,
                                                 spec.symbol_height_pitch * pitch))
        boxes.append(np.ptp(points, axis=0) / pitch)
    assert np.mean(boxes, axis=0) == pytest.approx(PAPER_SIZE, rel=1e-12)
    drawn = []
    for d in protocol.symbols:
        stim = make_stimulus(protocol, layout, d)
        drawn.append(np.ptp(stim.centres_mm[stim.drawn], axis=0) / pitch)
    step = spec.stroke_speed_mm_s / spec.frame_rate_hz / pitch  # 0.044 pitch a frame
    measured = np.mean(drawn, axis=0)
    assert np.all(measured <= np.array(PAPER_SIZE) + 1e-9)
    assert measured == pytest.approx(PAPER_SIZE, abs=step / 2)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.05, 5.0), st.floats(0.05, 5.0))
def test_any_size_is_the_mean_extent(width, height):
    digits = load_digits()
    boxes = [np.ptp(np.concatenate(d.scaled(width, height, (3.0, -2.0))), axis=0)
             for d in digits.values()]
    assert np.mean(boxes, axis=0) == pytest.approx([width, height], rel=1e-12)


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


#: A multi-line strokes array, as the shipped file writes it (line numbers on the right).
MULTILINE = (HEADER                                   # 1
             + "[digits.7]\n"                          # 2
             + "strokes = [[[0, 1], [1, 1], [0.3, 0]]]\n"  # 3
             + "\n"                                    # 4
             + "[digits.4]\n"                          # 5
             + "# two strokes\n"                       # 6
             + "strokes = [\n"                         # 7
             + "  [[0.7, 1], [0, 0.35], [1, 0.35]],\n"  # 8
             + "  [[0.7, 1],\n"                        # 9
             + "   [0.7, -0.2]],\n"                    # 10: strokes[1][1]
             + "]\n")


@pytest.mark.parametrize("body, line, match", [
    pytest.param("format = 2\n[digits.0]\nstrokes = [[[0, 0], [1, 1]]]\n", 1,
                 r"format: expected 1, got 2", id="format"),
    pytest.param(HEADER + "[digits.x]\nstrokes = [[[0, 0], [1, 1]]]\n", 2,
                 r"digits.x: expected a digit 0 to 9", id="key"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1.5, 1]]]\n", 3,
                 r"digits.3.strokes\[0\]\[1\]: expected x and y in the unit box.*1.5", id="box"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0]]]\n", 3,
                 r"digits.3.strokes\[0\]: expected a list of at least 2", id="short"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0.5, 0.5], [0.5, 0.5]]]\n", 3,
                 r"digits.3.strokes\[0\]: a stroke must have a length > 0", id="zero-length"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1, \"a\"]]]\n", 3,
                 r"digits.3.strokes\[0\]\[1\]: expected \[x, y\] numbers", id="type"),
    pytest.param(HEADER + "[digits.3]\nstrokes = [[[0, 0], [1, 1]]]\ncolour = 1\n", 4,
                 r"digits.3: unknown key 'colour'", id="unknown"),
    pytest.param(HEADER + "[digits.3]\nstrokes = []\n", 3,
                 r"digits.3.strokes: expected at least one stroke", id="no-stroke"),
    pytest.param(HEADER + "[digits.3]\n", 2,
                 r"digits.3: missing required key 'strokes'", id="no-strokes-key"),
    pytest.param(HEADER + "[digits]\n", 2, r"digits: expected at least one digit", id="empty"),
    pytest.param(HEADER + "[digits.1]\nstrokes = [[[0.5, 1], [0.5, 0]]]\n", 2,
                 r"digits: expected digits whose mean bounding-box width is > 0", id="flat"),
    pytest.param(HEADER + "[digits.3\n", 2, r"not valid TOML: .*line 2", id="syntax"),
    pytest.param(MULTILINE, 10, r"digits.4.strokes\[1\]\[1\]: expected x and y in the unit "
                 r"box \[0, 1\], got \[0.7, -0.2\]", id="multi-line"),
    pytest.param(MULTILINE.replace("[0, 0.35], ", "[0, 0.35], 3, "), 8,
                 r"digits.4.strokes\[0\]\[2\]: expected \[x, y\] numbers, got 3", id="row"),
])
def test_strict_loading_names_the_file_and_the_line(tmp_path, body, line, match):
    path = tmp_path / "strokes.toml"
    path.write_text(body)
    with pytest.raises(ProtocolError) as caught:
        load_digits(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:{line}: "), message
    assert re.search(match, message), message
    assert "\n" not in message


def test_a_protocol_names_its_strokes_file_and_both_lines(tmp_path):
    """An error in a protocol's own strokes file names the protocol's line of
    stimulus.strokes_file, then the strokes file and its line."""
    from test_protocol import SHIPPED

    strokes = tmp_path / "my_digits.toml"
    strokes.write_text(MULTILINE)
    text = SHIPPED.read_text().replace(
        '# strokes_file = "my_digits.toml"', 'strokes_file = "my_digits.toml"')
    text = text.replace("digits = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]", "digits = [4, 7]")
    text = text.replace('keys = ["0", "1", "2", "3", "4", "5", "6", "7", "8", "9"]',
                        'keys = ["4", "7"]')
    protocol = tmp_path / "p.toml"
    protocol.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.startswith("strokes_file"))
    with pytest.raises(ProtocolError) as caught:
        load_protocol(protocol)
    assert str(caught.value).startswith(
        f"{protocol}:{line}: stimulus.strokes_file: {strokes}:10: digits.4.strokes[1][1]: ")
    # a digit the protocol shows but the file does not define
    strokes.write_text(MULTILINE.replace("   [0.7, -0.2]],", "   [0.7, 0]],"))
    protocol.write_text(text.replace("digits = [4, 7]", "digits = [4, 7, 8]")
                        .replace('keys = ["4", "7"]', 'keys = ["4", "7", "8"]'))
    with pytest.raises(ProtocolError, match=rf"p.toml:{line}: stimulus.strokes_file: "
                       r".*my_digits.toml defines no strokes for digit 8 of stimulus.digits"):
        load_protocol(protocol)


def test_missing_file(tmp_path):
    with pytest.raises(ProtocolError, match=r"no such strokes file"):
        load_digits(tmp_path / "nope.toml")


def test_own_file_is_read_and_reloaded_when_changed(tmp_path):
    path = tmp_path / "strokes.toml"
    path.write_text(HEADER + "[digits.7]\nstrokes = [[[0, 1], [1, 1], [0.3, 0]]]\n")
    assert list(load_digits(path)) == [7]
    import os
    import time

    path.write_text(HEADER + "[digits.1]\nstrokes = [[[0.3, 0.8], [0.5, 1], [0.5, 0]]]\n")
    os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))
    assert list(load_digits(path)) == [1]
