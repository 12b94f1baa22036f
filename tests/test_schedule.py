"""Frame scheduling: bytes per frame, the rates the wire allows, latency with merging.

Wire arithmetic from hardware.md ("What the wire allows"): 3 n + 7 bytes a SERVO_MOVE, 10 bits
a byte at 9600 baud; 19 servos = 64 bytes = 66.7 ms, 18 servos = 61 bytes = 63.5 ms.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.device import codec
from crs_study.device.base import BYTE_TIME_S
from crs_study.device.calibration import PulseMap
from crs_study.device.schedule import (
    ChannelSplit,
    channel_balance,
    max_frame_rate_hz,
    wire_plan,
)
from crs_study.errors import DeviceError

MS = 1e-3


def _alternating(layout, n_frames: int) -> np.ndarray:
    """Every channel changes every frame, never back to an earlier value: 0.2 mm a frame."""
    assert n_frames <= 45
    return np.repeat(0.2 * np.arange(1, n_frames + 1)[:, None], layout.n_actuators, axis=1)


def test_full_frames_on_the_2d_device_match_the_published_table(layout2d):
    plan = wire_plan(layout2d, _alternating(layout2d, 10), 10.0, deadband_us=0)
    assert plan.full_bytes == (64, 61)  # 19 on A, 18 on B (hardware.md table)
    assert plan.changed_bytes.tolist() == [[64, 61]] * 10
    assert plan.full_frame_rate_hz == pytest.approx(1 / (64 * 10 / 9600))  # 15.0 frames/s
    # 10 frames/s leaves the wire idle between frames: each frame's latency is 64 bytes
    assert plan.latency_changed_s == pytest.approx(np.full(10, 64 * 10 / 9600))
    assert plan.median_latency_s == pytest.approx(66.67 * MS, abs=0.01 * MS)
    assert plan.merged_changed == 0 and plan.within_full_bound


def test_one_changing_channel_costs_ten_bytes(layout1d):
    frames = np.zeros((6, layout1d.n_actuators))
    frames[:, 0] = np.arange(1, 7)  # pixel 0 moves by 1 mm (111 us) a frame
    plan = wire_plan(layout1d, frames, 15.0)
    assert plan.changed_bytes[:, 0].tolist() == [10] * 6  # 3 x 1 + 7
    assert plan.latency_changed_s == pytest.approx(np.full(6, 10 * BYTE_TIME_S))
    assert plan.latency_full_s == pytest.approx(np.full(6, 28 * BYTE_TIME_S))  # 7 channels
    assert plan.changed_only_rate_hz == pytest.approx(96.0)  # 9600 / 100 bits
    assert max_frame_rate_hz(layout1d, frames) == pytest.approx(96.0)


def test_frames_faster_than_the_wire_merge_and_latency_stays_bounded(layout1d):
    # 7 channels, 28 bytes = 29.17 ms a frame, frames every 20 ms. By hand (module docstring):
    # frame 0 goes at 0; frame 1 waits for 29.17 and ends 58.33; frame 2 waits until 58.33 and
    # ends 87.5; frame 3 is superseded by frame 4 before the wire frees; both end at 116.67.
    w = 28 * BYTE_TIME_S
    plan = wire_plan(layout1d, _alternating(layout1d, 5), 50.0, deadband_us=0)
    expected = [w, 2 * w - 0.02, 3 * w - 0.04, 4 * w - 0.06, 4 * w - 0.08]
    assert plan.latency_changed_s == pytest.approx(expected)
    assert plan.merged_changed == 1
    assert not plan.within_full_bound


def _reference_latency_send_all(times: np.ndarray, write_s: float) -> np.ndarray:
    """Independent formulation: write i starts at max(end of write i-1, first arrival after
    write i-1 started) and carries every frame that arrived since; all writes take write_s."""
    latency = np.zeros(len(times))
    start = -math.inf
    end = -math.inf
    k = 0
    while k < len(times):
        start = max(end, times[k])
        end = start + write_s
        covered = np.flatnonzero((times <= start) & (np.arange(len(times)) >= k))
        latency[covered] = end - times[covered]
        k = covered[-1] + 1
    return latency


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(1.0, 200.0), n=st.integers(1, 40))
def test_send_everything_latency_matches_an_independent_model(layout2d, rate, n):
    plan = wire_plan(layout2d, _alternating(layout2d, n), rate)
    times = np.arange(n) / rate
    # the frame's latency is its worse controller's: A writes 64 bytes, B 61
    a = _reference_latency_send_all(times, 64 * BYTE_TIME_S)
    b = _reference_latency_send_all(times, 61 * BYTE_TIME_S)
    assert plan.latency_full_s == pytest.approx(np.maximum(a, b))
    # latency never grows: at most one write waited for plus one's own
    assert plan.max_latency_s <= 2 * 64 * BYTE_TIME_S + 1e-9
    assert plan.max_latency_full_s <= 2 * 64 * BYTE_TIME_S + 1e-9


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rate=st.floats(2.0, 100.0), deadband=st.integers(0, 3))
def test_changed_only_never_needs_more_bytes_than_everything(layout2d, seed, rate, deadband):
    rng = np.random.default_rng(seed)
    frames = rng.uniform(0, 9, (20, layout2d.n_actuators))
    frames[:, rng.random(layout2d.n_actuators) < 0.5] = 3.0  # half the channels hold still
    plan = wire_plan(layout2d, frames, rate, deadband_us=deadband)
    assert np.all(plan.changed_bytes <= np.array(plan.full_bytes))
    assert plan.max_latency_s <= 2 * 64 * BYTE_TIME_S + 1e-9


def test_deadband_skips_small_changes_only(layout1d):
    split = ChannelSplit(layout1d)
    pulses = np.array([1000, 1001, 1002, 1500, 1000, 1000, 1000])
    last = np.array([1000, 1000, 1000, 1000, 1003, 1000, 1000])
    assert split.changed(0, pulses, last, deadband_us=0).tolist() == [1, 2, 3, 4]
    assert split.changed(0, pulses, last, deadband_us=1).tolist() == [2, 3, 4]
    assert split.changed(0, pulses, last, deadband_us=2).tolist() == [3, 4]
    assert split.changed(0, pulses, None).tolist() == list(range(7))
    frame = split.frame(0, pulses, np.array([3, 4]), 67)
    assert codec.decode_frame(frame) == codec.ServoMove(((4, 1500), (5, 1000)), 67)
    assert split.frame(0, pulses, np.array([], dtype=int), 67) == b""


def test_moving_bump_sends_fewer_bytes_than_everything(layout2d):
    from crs_study.render import Renderer
    from crs_study.targets import Bump

    renderer = Renderer(layout2d, "crs")
    path = np.column_stack([np.linspace(-15, 15, 30), np.linspace(-10, 10, 30)])
    frames = np.array([renderer.render(Bump(tuple(c), 90.0, 5.0)).setpoints for c in path])
    plan = wire_plan(layout2d, frames, 15.0)
    assert plan.median_latency_s < plan.median_latency_full_s
    assert plan.changed_only_rate_hz > plan.full_frame_rate_hz


def test_balance_of_the_shipped_file_and_of_a_lopsided_one(layout2d):
    balance = channel_balance(layout2d)
    assert balance.counts == {"A": 19, "B": 18} and balance.balanced
    assert "balanced" in balance.describe()
    # move five of B's channels to A: 24 / 13, the busiest full frame 79 bytes instead of 64
    acts = list(layout2d.actuators)
    moved = [i for i, a in enumerate(acts) if a.controller == "B"][:5]
    for channel, i in zip(range(20, 25), moved, strict=True):
        acts[i] = replace(acts[i], controller="A", channel=channel)
    lopsided = channel_balance(replace(layout2d, actuators=tuple(acts)))
    assert lopsided.counts == {"A": 24, "B": 13}
    assert lopsided.full_frame_bytes == 79 and lopsided.excess == pytest.approx(79 / 64 - 1)
    assert not lopsided.balanced and "unbalanced: A's full frame is 23% longer" in \
        lopsided.describe()


def test_setpoints_outside_limits_and_bad_rates_are_errors(layout2d):
    frames = np.zeros((3, layout2d.n_actuators))
    frames[1, 5] = 10.0
    with pytest.raises(DeviceError, match=r"A:6 pixel 5: setpoint 10\.0 mm in frame 1"):
        wire_plan(layout2d, frames, 15.0)
    with pytest.raises(DeviceError, match=r"frame rate: expected a number > 0.*-1"):
        wire_plan(layout2d, np.zeros((3, layout2d.n_actuators)), -1)


def test_initial_pose_decides_the_first_frame(layout1d):
    frames = np.full((2, layout1d.n_actuators), 2.0)
    assert wire_plan(layout1d, frames, 10).changed_bytes[:, 0].tolist() == [28, 0]
    assert wire_plan(layout1d, frames, 10, initial_setpoints=frames[0]
                     ).changed_bytes[:, 0].tolist() == [0, 0]
    assert max_frame_rate_hz(layout1d, frames) == math.inf
    assert PulseMap.from_layout(layout1d).to_pulses(frames[0])[0] == 1222
