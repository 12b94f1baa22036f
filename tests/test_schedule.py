"""Frame scheduling: bytes per frame, the rates the wire allows, latency with merging.

Wire arithmetic from docs/device.md ("What the wire allows"): 3 n + 7 bytes a SERVO_MOVE, 10 bits
a byte at 9600 baud; 19 servos = 64 bytes = 66.7 ms, 18 servos = 61 bytes = 63.5 ms.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from crs_study.device import codec, decoder
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
    assert plan.full_bytes == (64, 61)  # 19 on A, 18 on B (docs/device.md table)
    assert plan.changed_bytes.tolist() == [[64, 61]] * 10
    assert plan.full_frame_rate_hz == pytest.approx(1 / (64 * 10 / 9600))  # 15.0 frames/s
    # 10 frames/s leaves the wire idle between frames: each frame's latency is 64 bytes
    assert plan.latency_changed_s == pytest.approx(np.full(10, 64 * 10 / 9600))
    assert plan.median_latency_s == pytest.approx(66.67 * MS, abs=0.01 * MS)
    assert plan.merged_changed == 0 and plan.within_full_bound


def test_one_changing_channel_costs_ten_bytes(layout1d):
    frames = np.zeros((6, layout1d.n_actuators))
    frames[:, 0] = np.arange(1, 7)  # pixel 0 moves by 1 mm (111 us) a frame
    plan = wire_plan(layout1d, frames, 15.0, refresh_s=0)
    assert plan.changed_bytes[:, 0].tolist() == [10] * 6  # 3 x 1 + 7
    assert plan.latency_changed_s == pytest.approx(np.full(6, 10 * BYTE_TIME_S))
    assert plan.latency_full_s == pytest.approx(np.full(6, 28 * BYTE_TIME_S))  # 7 channels
    assert plan.changed_only_rate_hz == pytest.approx(96.0)  # 9600 / 100 bits
    assert max_frame_rate_hz(layout1d, frames, refresh_s=0) == pytest.approx(96.0)
    # with the full refresh on (default 1 s), frame 0 carries every channel (28 bytes), and
    # once a second some frame must: no rate above the full-frame bound 9600 / 280 bits fits
    plan = wire_plan(layout1d, frames, 15.0)
    assert plan.latency_changed_s == pytest.approx([28 * BYTE_TIME_S] + [10 * BYTE_TIME_S] * 5)
    assert plan.changed_bytes[:, 0].tolist() == [10] * 6  # what changed, refresh aside
    assert plan.refreshes == 1 and plan.rate_bound_hz == pytest.approx(9600 / 280)
    assert max_frame_rate_hz(layout1d, frames) == pytest.approx(9600 / 280)


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
    """Independent formulation: on an idle wire, write i starts at the first arrival at or after
    write i-1 ended; on a busy one, when write i-1 ends. It carries every frame that arrived
    since; a frame arriving at the very instant the wire frees is not one of them (the write
    due then goes first: the write policy's tie rule). All writes take write_s."""
    latency = np.zeros(len(times))
    end = -math.inf
    k = 0
    while k < len(times):
        later = np.arange(len(times)) >= k
        if times[k] >= end:  # idle wire: frame k starts its own write
            start = times[k]
            covered = np.flatnonzero((times <= start) & later)
        else:  # frame k waited: the write starts as the wire frees, before any frame due then
            start = end
            covered = np.flatnonzero((times < start) & later)
        end = start + write_s
        latency[covered] = end - times[covered]
        k = covered[-1] + 1
    return latency


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(1.0, 200.0), n=st.integers(1, 40))
@example(rate=30.0, n=3)  # the tie: frame 2 comes at 2/30 s, as A's 64-byte write frees
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
    assert decoder.decode_frame(frame) == codec.ServoMove(((4, 1500), (5, 1000)), 67)
    assert split.frame(0, pulses, np.array([], dtype=int), 67) == b""


def test_moving_bump_sends_fewer_bytes_than_everything(layout2d):
    from crs_study.rendering.render import Renderer
    from crs_study.stimuli.targets import Bump

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
    # what would even it: 19 / 18 again, five channels rewired from A to B
    assert lopsided.moves == (("A", "B", 5),)
    assert "rewire channels (5 from A to B) and record them in the device file" in \
        lopsided.describe()
    assert balance.moves == ()


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
    assert max_frame_rate_hz(layout1d, frames, refresh_s=0) == math.inf
    assert max_frame_rate_hz(layout1d, frames) == pytest.approx(9600 / 280)  # the refresh
    assert PulseMap.from_layout(layout1d).to_pulses(frames[0])[0] == 1222


# -- the full refresh ---------------------------------------------------------------------------


def _one_channel_per_controller(layout, n_frames: int) -> np.ndarray:
    """Only the first actuator of each controller moves, 1 mm a frame up and down."""
    frames = np.zeros((n_frames, layout.n_actuators))
    for name in {a.controller for a in layout.actuators}:
        first = next(a.index for a in layout.actuators if a.controller == name)
        frames[:, first] = 1.0 + (np.arange(n_frames) % 2)
    return frames


def test_a_refresh_goes_out_every_interval_at_full_length(layout1d):
    # by hand: frames every 1/15 s; refresh_s = 0.95. Frame 0 is full (the last refresh is
    # long past), then the first write at or after 0.95 s, frame 15 (1.0 s), then frame 30
    # (2.0 s). Full: 7 channels, 28 bytes; otherwise one channel, 10 bytes.
    frames = _one_channel_per_controller(layout1d, 40)
    plan = wire_plan(layout1d, frames, 15.0, refresh_s=0.95)
    full = {0, 15, 30}
    expected = [(28 if k in full else 10) * BYTE_TIME_S for k in range(40)]
    assert plan.latency_changed_s == pytest.approx(expected)
    assert plan.refreshes == 3 and plan.merged_changed == 0
    # a refresh 0.52 s before frame 0: frame 0 is changed-only, the next full write is the
    # first at or after 0.43 s, frame 7 (0.467 s), then frame 22 (1.467 s)
    plan = wire_plan(layout1d, frames, 15.0, refresh_s=0.95, last_refresh_s=-0.52)
    full = {7, 22, 37}
    expected = [(28 if k in full else 10) * BYTE_TIME_S for k in range(40)]
    assert plan.latency_changed_s == pytest.approx(expected)
    assert wire_plan(layout1d, frames, 15.0, refresh_s=0).refreshes == 0


def test_a_refresh_longer_than_the_period_delays_the_next_frame(layout2d):
    # 20 frames/s (50 ms), one channel a controller changing: 10 bytes, 10.4 ms. The refresh at
    # frame 0 takes 64 bytes (66.7 ms) on A: frame 1 (50 ms) waits for it and ends at
    # 66.7 + 10.4 ms, a latency of 27.1 ms; frame 2 finds the wire free again.
    frames = _one_channel_per_controller(layout2d, 6)
    plan = wire_plan(layout2d, frames, 20.0)
    w = BYTE_TIME_S
    assert plan.latency_changed_s == pytest.approx([64 * w, 64 * w + 10 * w - 0.05]
                                                   + [10 * w] * 4)
    assert plan.changed_only_rate_hz == pytest.approx(96.0)  # 10-byte frames, refresh aside
    assert plan.rate_bound_hz == pytest.approx(15.0) and not plan.within_changed_bound
    no_refresh = wire_plan(layout2d, frames, 20.0, refresh_s=0, last_refresh_s=0)
    assert no_refresh.rate_bound_hz == pytest.approx(96.0) and no_refresh.within_changed_bound
    assert no_refresh.summary()["refreshes"] == 0 and plan.summary()["refreshes"] == 1


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"refresh_s": -1.0}, r"refresh interval: expected a number of seconds >= 0 .* got -1\.0"),
    ({"refresh_s": math.nan}, r"refresh interval: .* got nan"),
    ({"last_refresh_s": 0.5}, r"last refresh: expected a time <= 0 s .* got 0\.5")])
def test_bad_refresh_arguments_are_errors(layout1d, kwargs, message):
    with pytest.raises(DeviceError, match=message):
        wire_plan(layout1d, np.zeros((2, layout1d.n_actuators)), 10.0, **kwargs)


@pytest.mark.parametrize(("rate", "refresh_s"), [(14.3, 0.37), (23.7, 0.37), (41.9, 0.61),
                                                 (23.7, 0.0)])
def test_the_model_matches_a_simulated_run(layout2d, rate, refresh_s):
    """The plan's per-frame latency, refreshes included, against the boards of a
    SimulatedDevice fed the same frames on a virtual clock: the latency of frame k is the end
    of the first write on each board that started at or after frame k was handed over.

    The device gets the resting channels' pose (a full frame) 0.2 s before frame 0, which the
    plan is told (``initial_setpoints``, ``last_refresh_s=-0.2``). The rates are not whole
    numbers of byte times a frame, so no frame arrives at the very instant a wire frees (which
    of the two goes first is then a matter of float rounding, in the model as on the clock).
    """
    from crs_study.clock import VirtualClock
    from crs_study.device.base import open_device

    rng = np.random.default_rng(3)
    n = 90
    frames = np.full((n, layout2d.n_actuators), 3.0)
    moving = rng.random(layout2d.n_actuators) < 0.5  # about half the channels change
    for name in ("A", "B"):  # and at least one on each controller, so every frame is written
        moving[next(a.index for a in layout2d.actuators if a.controller == name)] = True
    frames[:, moving] = rng.uniform(0.5, 8.5, (n, int(moving.sum())))
    rest = np.full(layout2d.n_actuators, 3.0)
    plan = wire_plan(layout2d, frames, rate, initial_setpoints=rest, refresh_s=refresh_s,
                     last_refresh_s=-0.2)

    device = open_device(f"sim://?refresh_s={refresh_s}", layout2d, VirtualClock(),
                         record=True)
    device.open()
    start = device.clock.now() + 0.3
    device.clock.sleep_until(start - 0.2)
    device.send(rest)
    for k, setpoints in enumerate(frames):
        device.clock.sleep_until(start + k / rate)
        device.send(setpoints)
    device.displayed_setpoints(start + n / rate + 1.0)  # everything waiting is delivered
    latency = np.zeros(n)
    full_writes = 0
    for board, members in zip(device.boards, ChannelSplit(layout2d).members, strict=True):
        moves = [r for r in board.received if isinstance(r.message, codec.ServoMove)]
        ends = np.array([r.t for r in moves])
        starts = ends - np.array([3 * len(r.message.positions) + 7 for r in moves]) * BYTE_TIME_S
        ours = starts >= start - 1e-9  # the stimulus's writes, not the pose before it
        full_writes = max(full_writes, sum(len(r.message.positions) == len(members)
                                           for r, mine in zip(moves, ours, strict=True) if mine))
        for k in range(n):
            first = np.flatnonzero(starts >= start + k / rate - 1e-9)[0]
            latency[k] = max(latency[k], ends[first] - (start + k / rate))
    device.close()
    assert latency == pytest.approx(plan.latency_changed_s, abs=1e-9)
    assert full_writes == plan.refreshes
    if refresh_s:
        # the refresh is what the model added: without it, the figures differ
        assert plan.refreshes >= 2
        assert not np.allclose(wire_plan(layout2d, frames, rate, initial_setpoints=rest,
                                         refresh_s=0).latency_changed_s, latency)
