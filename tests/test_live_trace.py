"""Finger traces, the sender and recordings read back (crs_study/live/trace.py, sender.py,
record.py)."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from crs_study.live import (
    FingerTrace,
    LiveError,
    decode_packet,
    digit_trace,
    hold_trace,
    read_trace,
    send_trace,
    stroke_trace,
    symbol_trace,
)
from crs_study.live.trace import DIGIT_ASPECT
from crs_study.stimuli.digits import load_digits
from crs_study.stimuli.sets import load_stimulus_set


def distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Shortest distance of each point to the polyline (segment by segment)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("pkj,kj->pk", points[:, None] - a, ab) / np.sum(ab * ab, axis=1),
                0.0, 1.0)
    nearest = a + t[..., None] * ab
    return np.min(np.linalg.norm(points[:, None] - nearest, axis=2), axis=1)


def test_digit_trace_follows_the_strokes_at_the_speed():
    trace = digit_trace(4, height_mm=60.0, speed_mm_s=30.0, press_mm=5.0, rate_hz=72.0)
    assert np.allclose(trace.times, np.arange(len(trace)) / 72.0)
    strokes = load_digits()[4].scaled(60.0 * DIGIT_ASPECT, 60.0)
    pressed = trace.xyz[:, 2] == 5.0
    lifted = trace.xyz[:, 2] == 0.0
    assert pressed.sum() > 100 and lifted.any() and np.all(pressed | lifted)
    near = np.min([distance_to_polyline(trace.xyz[pressed, :2], s) for s in strokes], axis=0)
    assert near.max() < 1e-9  # every pressed sample lies on a stroke
    steps = np.linalg.norm(np.diff(trace.xyz[:, :2], axis=0), axis=1)
    assert steps.max() <= 30.0 / 72.0 + 1e-9  # never faster than the finger speed
    assert np.median(steps[steps > 0]) == pytest.approx(30.0 / 72.0)


def test_a_letter_is_written_with_the_letter_sets_strokes():
    trace = symbol_trace("S", "letters", height_mm=60.0, speed_mm_s=30.0, press_mm=5.0)
    assert trace.name == "letter S, 60 mm at 30 mm/s"
    strokes = load_stimulus_set("letters").glyph("S").scaled(60.0 * DIGIT_ASPECT, 60.0)
    pressed = trace.xyz[:, 2] == 5.0
    near = np.min([distance_to_polyline(trace.xyz[pressed, :2], s) for s in strokes], axis=0)
    assert pressed.sum() > 100 and near.max() < 1e-9
    # the digit set through the same path is digit_trace, sample for sample
    assert np.array_equal(symbol_trace("4").xyz, digit_trace(4).xyz)


def test_stroke_and_hold_and_jitter():
    stroke = stroke_trace((-50.0, 0.0), (50.0, 0.0), speed_mm_s=40.0, rate_hz=50.0)
    assert tuple(stroke.xyz[0]) == (-50.0, 0.0, 5.0) and tuple(stroke.xyz[-1]) == (50.0, 0.0, 5.0)
    assert stroke.duration_s == pytest.approx(100.0 / 40.0)
    held = hold_trace((3.0, 4.0), duration_s=10.0, rate_hz=100.0).jittered(0.5, seed=3)
    assert len(held) == 1001
    assert np.std(held.xyz[:, 0]) == pytest.approx(0.5, rel=0.1)  # 1001 draws: SE ~2 %
    assert np.mean(held.xyz[:, :2], axis=0) == pytest.approx((3.0, 4.0), abs=0.1)
    assert np.all(held.xyz[:, 2] == 5.0)


def test_resampled_interpolates_linearly_in_time():
    trace = FingerTrace([0.0, 1.0, 3.0], [[0, 0, 1], [10, 0, 1], [10, 20, 1]])
    out = trace.resampled(2.0)
    assert np.allclose(out.times, np.arange(7) / 2.0)
    assert np.allclose(out.xyz[:, 0], np.interp(out.times, [0, 1, 3], [0, 10, 10]))
    assert np.allclose(out.xyz[:, 1], np.interp(out.times, [0, 1, 3], [0, 0, 20]))


@pytest.mark.parametrize("make, message", [
    (lambda: FingerTrace([0.0, 0.0], [[0, 0, 1]] * 2), "strictly increasing"),
    (lambda: FingerTrace([0.0], [[0, float("nan"), 1]]), "finite"),
    (lambda: digit_trace(4, speed_mm_s=0.0), "finger speed"),
    (lambda: digit_trace(4, rate_hz=1e9), "rate"),
    (lambda: stroke_trace((0, 0), (0, 0)), "two different"),
    (lambda: hold_trace(duration_s=-1.0), "duration"),
    (lambda: hold_trace().jittered(-1.0), "jitter"),
    (lambda: symbol_trace("A", "letters"), r"letter: expected one of C, J, L to N, .* got 'A'"),
    (lambda: symbol_trace("C", "runes"), r"stimulus set: 'runes' is not a shipped stimulus set"),
    (lambda: symbol_trace("C", "letters", height_mm=0.0), "letter height"),
])
def test_bad_traces_are_one_line_errors(make, message):
    with pytest.raises(LiveError, match=message):
        make()


def test_sender_sends_the_trace_in_order_on_time():
    trace = stroke_trace((0.0, 0.0), (10.0, 0.0), speed_mm_s=100.0, rate_hz=200.0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(2.0)
        report = send_trace(trace, sock.getsockname(), stream=7, first_sequence=40)
        packets = [decode_packet(sock.recv(64)) for _ in range(len(trace))]
    assert report.packets == len(trace) == 21 and report.stream == 7
    assert [p.sequence for p in packets] == list(range(40, 61))
    assert {p.stream for p in packets} == {7}
    assert np.allclose([p.x_mm for p in packets], trace.xyz[:, 0], atol=1e-5)
    sent = np.array([p.sender_time for p in packets])
    assert sent[-1] - sent[0] == pytest.approx(trace.duration_s, abs=0.02)


def test_read_trace_replays_accepted_packets(tmp_path):
    path = tmp_path / "r.jsonl"
    lines = [{"format": "crs-study live recording", "version": 1},
             {"packet": {"t": 1.0, "status": "accepted", "x": 1, "y": 2, "z": 3}},
             {"packet": {"t": 1.01, "status": "stale", "x": 9, "y": 9, "z": 9}},
             {"packet": {"t": 1.02, "status": "accepted", "x": 4, "y": 5, "z": 6}},
             {"frame": {"index": 0}}]
    path.write_text("\n".join(json.dumps(x) for x in lines) + "\n{\"cut", encoding="utf-8")
    trace = read_trace(path)
    assert np.allclose(trace.times, [0.0, 0.02]) and np.allclose(trace.xyz, [[1, 2, 3],
                                                                            [4, 5, 6]])


@pytest.mark.parametrize("text, message", [
    ("", "header"), ('{"format": "other"}\n', "header"),
    ('{"format": "crs-study live recording", "version": 9}\n', "version 1"),
    ('{"format": "crs-study live recording", "version": 1}\nnot json\n{}\n', ":2: not a JSON"),
    ('{"format": "crs-study live recording", "version": 1}\n', "no accepted packet"),
])
def test_bad_recordings(tmp_path, text, message):
    path = tmp_path / "bad.jsonl"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(LiveError, match=message):
        read_trace(path)
    with pytest.raises(LiveError, match="no such recording"):
        read_trace(tmp_path / "missing.jsonl")


def test_live_send_writes_a_letter_from_the_command_line(capsys):
    from crs_study.cli import main

    trace = symbol_trace("C", "letters", rate_hz=500.0, speed_mm_s=200.0, height_mm=30.0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.settimeout(2.0)
        host, port = sock.getsockname()
        assert main(["live-send", "--to", f"{host}:{port}", "--symbol", "C", "--set",
                     "letters", "--rate", "500", "--speed-mm-s", "200", "--height-mm", "30",
                     "--json"]) == 0
        packets = [decode_packet(sock.recv(64)) for _ in range(len(trace))]
    report = json.loads(capsys.readouterr().out)
    assert report["trace"] == "letter C, 30 mm at 200 mm/s" and report["packets"] == len(trace)
    got = np.array([[p.x_mm, p.y_mm, p.z_mm] for p in packets])
    assert np.allclose(got, trace.xyz, atol=1e-5)
