"""The host's write policy (device/writes.py), and its three users putting the same bytes out.

Wire arithmetic from docs/device.md ("What the wire allows"): 10 bits a byte at 9600 baud
(1.0417 ms), a SERVO_MOVE for n servos is 3 n + 7 bytes; the 1D device's board carries 7
channels (28 bytes, 29.2 ms), the 2D device's 19 on A (64 bytes, 66.7 ms) and 18 on B (61).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import serial
from _pty_helpers import PtyBoard, RecordingPort, SteppedClock, step_serial_device
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.clock import VirtualClock
from crs_study.device import codec, decoder
from crs_study.device.base import BYTE_TIME_S, default_move_ms
from crs_study.device.calibration import PulseMap
from crs_study.device.schedule import simulate_port
from crs_study.device.serial_device import SerialDevice
from crs_study.device.serial_port import SerialOptions
from crs_study.device.simulated import SimOptions, SimulatedDevice
from crs_study.device.writes import ChannelSplit, PortWrites, WritePolicy
from crs_study.errors import DeviceError
from crs_study.geometry.layout import load_layout

W = BYTE_TIME_S
FULL7 = 28 * W  # the 1D device's board: every channel


def pulses(*values: int) -> np.ndarray:
    return np.array(values, dtype=np.int64)


def port(refresh_s: float = 0.0, deadband_us: int = 0, n: int = 3) -> PortWrites:
    return PortWrites(n, WritePolicy(deadband_us, refresh_s))


# -- the policy, by hand -----------------------------------------------------------------------


def test_first_write_is_full_then_changed_only_within_the_deadband():
    p = port(deadband_us=1)
    assert p.next_write_at() == math.inf  # nothing wanted: nothing to write
    assert p.want(0.0, pulses(1000, 1500, 2000), 40) is False
    first = p.take(0.0)
    assert first.full and first.local.tolist() == [0, 1, 2] and first.n_bytes == 16
    assert first.done == pytest.approx(16 * W)
    p.want(1.0, pulses(1001, 1502, 2000), 40)  # 1 us is inside the dead-band, 2 us is not
    second = p.take(1.0)
    assert second.local.tolist() == [1] and second.n_bytes == 10 and not second.full
    p.want(2.0, pulses(1001, 1502, 2000), 40)  # nothing changed: nothing is written
    nothing = p.take(2.0)
    assert nothing.n_bytes == 0 and nothing.done == 2.0 and p.next_write_at() == math.inf


def test_a_frame_wanted_while_the_wire_is_busy_waits_and_a_newer_one_replaces_it():
    p = port()
    p.want(0.0, pulses(1000, 1000, 1000), 0)
    p.take(0.0)  # 16 bytes: the wire is busy until 16.7 ms
    assert p.want(0.005, pulses(1100, 1000, 1000), 0) is False
    assert p.next_write_at() == pytest.approx(16 * W)
    assert p.predict(0.005) == (1, 10, pytest.approx(26 * W))  # what its write will be
    assert p.want(0.010, pulses(1100, 1200, 1000), 0) is True  # merged: replaces it
    assert p.predict(0.010) == (2, 13, pytest.approx(29 * W))
    write = p.take(p.next_write_at())
    assert write.start == pytest.approx(16 * W) and write.local.tolist() == [0, 1]
    assert write.pulses.tolist() == [1100, 1200, 1000]  # the newest frame, not the first
    assert p.next_write_at() == math.inf  # no refresh: nothing more


def test_the_refresh_rides_on_the_first_frame_due_after_the_interval():
    # refresh 0.5 s, the same frame every 0.2 s: 0 full, 0.2 and 0.4 carry nothing, 0.6 full
    # (the simulated device's test of the same case: tests/test_simulated_device.py)
    p = port(refresh_s=0.5)
    same = pulses(1000, 1500, 2000)
    sizes = []
    for t in (0.0, 0.2, 0.4, 0.6, 0.8):
        p.want(t, same, 0)
        sizes.append(p.take(t).n_bytes)
    assert sizes == [16, 0, 0, 16, 0]


def test_a_held_pose_is_not_rewritten_and_the_next_frame_after_the_interval_is_full():
    # one frame at 0 and nothing more: the wire stays quiet (the refresh rides on frames, never
    # goes alone); the next frame, 3 s later, carries every channel although nothing changed
    p = port(refresh_s=0.5)
    same = pulses(1000, 1500, 2000)
    p.want(0.0, same, 30)
    p.take(0.0)
    assert p.next_write_at() == math.inf and p.take(2.9) is None
    p.want(3.0, same, 30)
    write = p.take(3.0)
    assert write.full and write.n_bytes == 16 and write.start == 3.0


def test_a_write_due_at_the_instant_a_frame_comes_goes_first():
    # the tie rule of all three users: the wire frees at exactly 16 bytes; the waiting frame
    # goes then, and a frame wanted at that very time waits for it
    p = port()
    p.want(0.0, pulses(1000, 1000, 1000), 0)
    p.take(0.0)
    p.want(0.001, pulses(1100, 1000, 1000), 0)
    free = p.next_write_at()
    first = p.take(free)
    assert first.pulses.tolist() == [1100, 1000, 1000]
    assert p.want(free, pulses(1100, 1200, 1000), 0) is False  # not merged: the wire took one
    assert p.next_write_at() == first.done


def test_full_wanted_sends_every_channel_and_other_bytes_book_the_wire():
    p = port()
    p.want(0.0, pulses(1000, 1000, 1000), 0)
    p.take(0.0)
    assert p.written(0.0, 4) == pytest.approx(20 * W)  # a battery query behind the frame
    p.want(0.0, pulses(1000, 1000, 1000), 500, full=True)  # the neutral pose on close
    write = p.take(0.0)
    assert write.full and write.start == pytest.approx(20 * W) and write.move_ms == 500


def test_send_all_carries_every_channel_every_time():
    p = PortWrites(3, WritePolicy(0, 0.0, send_all=True))
    for t in (0.0, 1.0):
        p.want(t, pulses(1000, 1000, 1000), 0)
        assert p.take(t).n_bytes == 16


def test_a_controller_without_channels_is_never_written():
    p = PortWrites(0, WritePolicy(0, 0.5))
    for t in (0.0, 1.0):
        p.want(t, np.zeros(0, dtype=np.int64), 0)
        assert p.take(t).n_bytes == 0


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"deadband_us": -1}, r"dead-band: expected a whole number of us >= 0, got -1"),
    ({"deadband_us": True}, r"dead-band: .* got True"),
    ({"refresh_s": math.nan}, r"refresh interval: .* got nan"),
    ({"refresh_s": "1"}, r"refresh interval: .* got '1'"),
    ({"baud": 0}, r"baud rate: expected a whole number > 0, got 0")])
def test_bad_policies_are_one_line_errors(kwargs, message):
    with pytest.raises(DeviceError, match=message):
        WritePolicy(**kwargs)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), refresh=st.sampled_from([0.0, 0.05, 0.3]),
       deadband=st.integers(0, 3), gaps=st.lists(st.floats(0.0, 0.12), min_size=1,
                                                 max_size=30))
def test_the_predicted_write_is_the_write(seed, refresh, deadband, gaps):
    # what a device reports for a frame waiting for the wire (FrameReport) is what the policy
    # then writes for it, unless a newer frame replaces it first
    rng = np.random.default_rng(seed)
    p = port(refresh, deadband, n=5)
    t = 0.0
    prediction = None  # nothing waits before the first frame, so no write compares with it
    for gap in gaps:
        t += gap
        while p.next_write_at() <= t:
            write = p.take(p.next_write_at())
            assert (len(write.local), write.n_bytes, write.done) == prediction
        p.want(t, rng.integers(1000, 1010, 5), 0)
        prediction = p.predict(t)
    write = p.take(p.next_write_at())
    assert (len(write.local), write.n_bytes, write.done) == prediction


# -- the three users put the same bytes on the wire at the same times --------------------------


LAYOUTS = {name: load_layout(name) for name in ("crs2d", "crs1d")}


def _frames(layout, seed: int, n: int) -> np.ndarray:
    """A random frame sequence: some frames move a few channels, some every channel, some by
    about the dead-band (0.005 to 0.03 mm is 0.6 to 3 us), some nothing."""
    rng = np.random.default_rng(seed)
    travel = PulseMap.from_layout(layout).travel_mm
    frames = [rng.uniform(0, travel)]
    for _ in range(n - 1):
        frame = frames[-1].copy()
        kind = rng.integers(4)
        if kind == 0:
            pick = rng.choice(layout.n_actuators, rng.integers(1, 6), replace=False)
            frame[pick] = rng.uniform(0, travel[pick])
        elif kind == 1:
            frame = rng.uniform(0, travel)
        elif kind == 2:
            pick = rng.choice(layout.n_actuators, rng.integers(1, 8), replace=False)
            frame[pick] = np.clip(frame[pick] + rng.uniform(-0.03, 0.03, len(pick)), 0,
                                  travel[pick])
        frames.append(frame)
    return np.array(frames)


def _board_writes(device) -> list[list[tuple[float, bytes]]]:
    """(start, bytes) of every frame each simulated board received (start: its arrival less
    its bytes' wire time)."""
    out = []
    for board in device.boards:
        writes = []
        for received in board.received:
            data = received.message.encode()
            writes.append((received.t - len(data) * device.byte_s, data))
        out.append(writes)
    return out


def _estimated_writes(layout, frames, times, options) -> list[list[tuple[float, bytes]]]:
    split = ChannelSplit(layout)
    policy = WritePolicy(options["deadband_us"], options["refresh_s"])
    pulses_all = PulseMap.from_layout(layout).to_pulses(frames)
    out = []
    for c, members in enumerate(split.members):
        run = simulate_port(pulses_all[:, members], times, policy,
                            move_ms=default_move_ms(layout))
        out.append([(w.start, split.write_bytes(c, w)) for w in run.writes if w.n_bytes])
    return out


def _serial_writes(layout, frames, times, options, until):
    """The serial device's writer threads, writing real ptys, stepped through the event times
    on a :class:`SteppedClock` (lead_s = 0: no early writes against wake-up jitter, which a
    stepped clock does not have). Returns its writes per port and the end time."""
    boards = [PtyBoard() for _ in layout.controllers]
    clock = SteppedClock()
    ports = []
    try:
        ports = [RecordingPort(serial.Serial(b.path, 9600, timeout=0.05, write_timeout=0.5,
                                             exclusive=True), clock) for b in boards]
        device = SerialDevice(layout, ports, clock, SerialOptions(lead_s=0.0, **options))
        clock.device = device
        with device:
            end = step_serial_device(device, clock, times, frames, until)
        assert device.faults == []
        written = [p.writes for p in ports]
        for board, writes in zip(boards, written, strict=True):  # and the ptys carried them
            assert board.wait_for_bytes(sum(len(d) for _, d in writes))
            assert bytes(board.raw) == b"".join(d for _, d in writes)
        return written, end
    finally:
        for board in boards:
            board.close()


def _simulated_writes(layout, frames, times, options, until):
    clock = VirtualClock()
    device = SimulatedDevice(layout, clock, SimOptions(**options), record=True)
    with device:
        for t, frame in zip(times, frames, strict=True):
            clock.sleep_until(t)
            device.send(frame)
        clock.sleep_until(until)
        device.displayed_setpoints()  # the writes due by then
    return _board_writes(device)


gaps = st.one_of(st.floats(0.0, 0.012),  # faster than the wire: frames merge
                 st.floats(0.012, 0.15),  # about a frame's wire time
                 st.floats(0.15, 2.5))  # pauses: the frame after one may be a refresh


@settings(max_examples=30, deadline=None)
@given(name=st.sampled_from(sorted(LAYOUTS)), seed=st.integers(0, 2**32 - 1),
       gaps=st.lists(gaps, min_size=1, max_size=16), deadband=st.integers(0, 3),
       refresh=st.sampled_from([0.0]) | st.floats(0.15, 1.2))
def test_serial_simulated_and_estimate_write_the_same_bytes_at_the_same_times(
        name, seed, gaps, deadband, refresh):
    """One frame sequence (random setpoints, timings, dead-band and refresh interval), three
    writers: SerialDevice's writer threads on real ptys, SimulatedDevice's boards, and the
    estimate (``simulate_port``). Every write matches in bytes and start time; the serial and
    simulated devices also agree on the battery query before and the neutral pose after,
    which the estimate leaves out."""
    layout = LAYOUTS[name]
    frames = _frames(layout, seed, len(gaps))
    times = 0.05 + np.cumsum(gaps)
    options = {"deadband_us": deadband, "refresh_s": refresh}
    serial_writes, end = _serial_writes(layout, frames, times, options, times[-1])
    simulated = _simulated_writes(layout, frames, times, options, end)
    estimated = _estimated_writes(layout, frames, times, options)
    query = codec.get_battery_voltage()
    for real, sim, est in zip(serial_writes, simulated, estimated, strict=True):
        assert [d for _, d in sim] == [d for _, d in real]
        assert [t for t, _ in sim] == pytest.approx([t for t, _ in real], abs=1e-9)
        assert real[0] == (0.0, query)  # asked on open
        neutral = decoder.decode_frame(real[-1][1])
        assert neutral.time_ms == 500 and real[-1][0] == pytest.approx(end)  # and on close
        assert est == real[1:-1]


def test_a_frame_handed_over_the_instant_a_wire_frees_waits_for_the_one_waiting():
    # the tie rule, exactly, in all three: frame 0 at 0.05 s is every channel (A: 64 bytes,
    # until 0.05 + 64 byte times); frame 1 at 0.06 s waits for it; frame 2 comes at the very
    # instant A's wire frees. Frame 1 goes then, frame 2 after it (not merged into it).
    layout = LAYOUTS["crs2d"]
    frames = np.array([np.full(layout.n_actuators, v) for v in (1.0, 2.0, 3.0)])
    times = np.array([0.05, 0.06, 0.05 + 64 * BYTE_TIME_S])
    options = {"deadband_us": 0, "refresh_s": 0.0}
    serial_writes, end = _serial_writes(layout, frames, times, options, times[-1])
    simulated = _simulated_writes(layout, frames, times, options, end)
    estimated = _estimated_writes(layout, frames, times, options)
    a_real, a_sim, a_est = serial_writes[0], simulated[0], estimated[0]
    assert [d for _, d in a_sim] == [d for _, d in a_real] and a_est == a_real[1:-1]
    moves = [decoder.decode_frame(d) for _, d in a_est]
    assert [m.positions[0][1] for m in moves] == [1111, 1222, 1333]  # 1, 2, 3 mm on 9 mm
    assert [t for t, _ in a_est] == [0.05, times[2], times[2] + 64 * BYTE_TIME_S]
