"""The virtual LSC-24 board: servo motion, decoding the byte stream, replies and faults.

Sources written beside the numbers:
- docs/device.md, "The published 2D device": speed 0.08 s/cm, so a full 9 mm stroke takes 72 ms.
- docs/device.md, "Published test vectors": ``55 55 08 03 01 E8 03 01 D0 07`` = servo 1 to 2000 us
  in 1000 ms; ``55 55 04 0F 4C 1D`` = battery 7500 mV.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.device import codec, decoder
from crs_study.device.virtual_controller import (
    BROWNOUT_BATTERY_MV,
    ServoBank,
    ServoSpec,
    VirtualController,
    speed_us_per_s,
)

SPEED_S_PER_MM = 0.008  # 0.08 s/cm (docs/device.md)
US_PER_MM = 1000.0 / 9.0  # crs2d default calibration: 1000 us over 9 mm


def board(**kw) -> VirtualController:
    spec = ServoSpec(rest_us=1000.0, max_speed_us_s=speed_us_per_s(1000, 2000, 9.0,
                                                                    SPEED_S_PER_MM))
    return VirtualController("A", 24, 1, [spec] * 24, **kw)


def test_full_stroke_speed_is_72_ms():
    # docs/device.md: "speed 0.08 s/cm, so a full stroke takes about 72 ms" (9 mm)
    assert speed_us_per_s(1000, 2000, 9.0, SPEED_S_PER_MM) == pytest.approx(1000 / 0.072)


@pytest.mark.parametrize(
    ("stroke_mm", "move_s"),
    [pytest.param(9.0, 0.0, id="full-stroke-as-fast-as-possible"),
     pytest.param(9.0, 0.2, id="full-stroke-slow-move-time"),
     pytest.param(2.0, 0.01, id="short-stroke-speed-limited"),
     pytest.param(2.0, 0.05, id="short-stroke-move-time-limited"),
     pytest.param(0.5, 0.0, id="tiny")],
)
def test_move_finishes_at_max_of_move_time_and_speed_limit(stroke_mm, move_s):
    vc = board()
    target = 1000 + round(stroke_mm * US_PER_MM)
    stroke_mm = (target - 1000) / US_PER_MM  # whole-us target
    t0 = 1.0
    vc.receive(codec.servo_move({5: target}, round(move_s * 1000)), t0)
    finish = t0 + max(move_s, stroke_mm * SPEED_S_PER_MM)
    i = 5 - 1
    assert vc.positions_us(finish)[i] == pytest.approx(target)
    slope = (target - 1000) / (finish - t0)
    assert vc.positions_us(finish - 1e-3)[i] == pytest.approx(target - slope * 1e-3)
    assert slope <= 1000 / 0.072 + 1e-6  # never faster than the speed limit
    # linear in between: a quarter of the way at a quarter of the time
    quarter = t0 + 0.25 * (finish - t0)
    assert vc.positions_us(quarter)[i] == pytest.approx(1000 + 0.25 * (target - 1000))
    assert vc.positions_us(finish + 5.0)[i] == pytest.approx(target)


def test_published_servo_move_vector_moves_servo_1():
    vc = board()
    frame = bytes.fromhex("55 55 08 03 01 E8 03 01 D0 07")  # servo 1 -> 2000 us in 1000 ms
    assert vc.receive(frame, 0.0) == b""
    assert vc.positions_us(0.5)[0] == pytest.approx(1500.0)  # half-way through 1000 ms
    assert vc.positions_us(1.0)[0] == pytest.approx(2000.0)
    assert vc.positions_us(1.0)[1:] == pytest.approx(np.full(23, 1000.0))  # others at rest
    assert vc.good_frames == 1 and vc.bad_frames == 0


def test_battery_reply_is_the_published_frame():
    vc = board(battery_mv=7500)
    reply = vc.receive(codec.get_battery_voltage(), 0.0)
    assert reply == bytes.fromhex("55 55 04 0F 4C 1D")  # docs/device.md: 7500 mV


def test_new_command_starts_from_where_the_servo_is():
    vc = board()
    vc.receive(codec.servo_move({1: 2000}, 1000), 0.0)
    vc.receive(codec.servo_move({1: 1000}, 1000), 0.5)  # at 1500 us, turn back
    assert vc.positions_us(0.5)[0] == pytest.approx(1500.0)
    assert vc.positions_us(1.0)[0] == pytest.approx(1250.0)
    assert vc.positions_us(1.5)[0] == pytest.approx(1000.0)


def test_garbage_between_frames_is_counted_and_frames_still_act():
    vc = board(record=True)
    stream = (b"\x00\x13" + codec.servo_move({2: 1800}, 0) + b"\xff\x01\x02"
              + codec.servo_move({3: 1200}, 0) + b"\xaa")
    vc.receive(stream, 0.0)
    vc.end_of_stream()
    pos = vc.positions_us(1.0)
    assert pos[1] == pytest.approx(1800.0) and pos[2] == pytest.approx(1200.0)
    assert vc.good_frames == 2
    assert vc.bad_frames == 3 == vc.beeps


def test_truncated_frame_at_end_of_stream_is_a_bad_frame():
    vc = board()
    vc.receive(codec.servo_move({2: 1800, 3: 1900}, 0)[:-2], 0.0)
    assert vc.bad_frames == 0  # may still complete
    vc.end_of_stream()
    assert vc.bad_frames == 1
    assert vc.positions_us(1.0)[1] == pytest.approx(1000.0)


def frames_strategy():
    move = st.dictionaries(st.integers(1, 24), st.integers(500, 2500), min_size=1, max_size=24)
    noise = st.binary(max_size=6).map(lambda b: bytes(x for x in b if x != 0x55))
    return st.lists(st.tuples(noise, move), min_size=1, max_size=15)


@settings(max_examples=60, deadline=None)
@given(frames_strategy(), st.integers(1, 9))
def test_any_stream_cut_anywhere_gives_last_command_per_channel(items, chunk):
    # random frames with random noise (no 0x55, so no false header) between them, fed in
    # chunks of any size: every frame acts, every noise run is one bad frame.
    stream = b"".join(n + codec.servo_move(m, 0) for n, m in items)
    vc = board()
    for k in range(0, len(stream), chunk):
        vc.receive(stream[k:k + chunk], 0.0)
    expected = np.full(24, 1000.0)
    for _, move in items:
        for servo, pulse in move.items():
            expected[servo - 1] = pulse
    assert vc.positions_us(10.0) == pytest.approx(expected)
    assert vc.good_frames == len(items)
    assert vc.bad_frames == sum(1 for n, _ in items if n)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 0.2), st.integers(500, 2500), st.integers(0, 300)),
                min_size=1, max_size=12))
def test_servo_never_exceeds_its_speed_limit_and_never_jumps(commands):
    vmax = 1000 / 0.072
    bank = ServoBank(np.array([1500.0]), np.array([vmax]))
    t = 0.0
    times = []
    for gap, target, move_ms in commands:
        t += gap
        bank.command(np.array([0]), np.array([float(target)]), move_ms / 1000.0, t)
        times.append(t)
    # sample densely after the last command: speed bounded, lands on the last target
    grid = np.linspace(t, t + 0.5, 400)
    pos = np.array([bank.position(s)[0] for s in grid])
    assert np.all(np.abs(np.diff(pos)) <= vmax * np.diff(grid) * (1 + 1e-9) + 1e-9)
    assert pos[-1] == pytest.approx(commands[-1][1])


def test_stalled_servo_stays_where_it_was_at_the_stall():
    vc = board()
    vc.stall(4, at=0.5)
    vc.receive(codec.servo_move({4: 2000, 5: 2000}, 1000), 0.0)
    assert vc.positions_us(0.4)[3] == pytest.approx(1400.0)
    vc.receive(codec.servo_move({4: 1000, 5: 1000}, 0), 0.6)
    assert vc.positions_us(2.0)[3] == pytest.approx(1500.0)  # frozen at the stall
    assert vc.positions_us(2.0)[4] == pytest.approx(1000.0)  # the neighbour obeys
    assert vc.stalled == {4: 0.5}


def test_stall_of_unknown_channel_is_refused():
    with pytest.raises(ValueError, match="no channel 25"):
        board().stall(25, at=0.0)


def test_brownout_servos_sink_to_rest_ignore_moves_and_battery_reads_low():
    vc = board()
    vc.receive(codec.servo_move({1: 2000}, 0), 0.0)
    vc.brownout(at=1.0)
    assert vc.positions_us(0.9)[0] == pytest.approx(2000.0)
    assert vc.battery_mv(0.9) > BROWNOUT_BATTERY_MV
    # limp: sinks to rest (1000 us) at the speed limit, 72 ms for the full stroke
    assert vc.positions_us(1.036)[0] == pytest.approx(1500.0)
    assert vc.positions_us(1.1)[0] == pytest.approx(1000.0)
    vc.receive(codec.servo_move({1: 2000}, 0), 1.2)
    assert vc.positions_us(2.0)[0] == pytest.approx(1000.0)
    assert vc.ignored_frames == 1
    assert vc.receive(codec.get_battery_voltage(), 2.0) == codec.battery_voltage_reply(
        BROWNOUT_BATTERY_MV)


def test_unload_unknown_ids_and_position_read():
    vc = board()
    vc.receive(codec.servo_move({1: 2000, 2: 1800}, 0), 0.0)
    vc.receive(codec.servo_move({30: 1500}, 0), 0.1)  # valid frame, no such channel here
    assert vc.unknown_ids == 1
    reply = vc.receive(codec.mult_servo_pos_read([1, 2]), 0.2)
    frames = decoder.FrameDecoder("board").feed(reply)
    assert frames[0].message.positions == ((1, 2000), (2, 1800))
    vc.receive(codec.mult_servo_unload([1]), 0.3)
    assert vc.positions_us(1.0)[0] == pytest.approx(1000.0)  # limp, at rest
    assert vc.positions_us(1.0)[1] == pytest.approx(1800.0)


class _ReferenceServos:
    """ServoBank's motion model written per servo with plain floats (the module docstring:
    start where the servo is, take max(T, |dp| / v)): the vectorised bank must agree bit for
    bit, or a displayed position would drift from what the model says."""

    def __init__(self, rest: list[float], speed: list[float]) -> None:
        self.target, self.slope = list(rest), [0.0] * len(rest)
        self.arrive, self.s_per_us = [0.0] * len(rest), [1.0 / v for v in speed]

    def position(self, i: int, t: float) -> float:
        return self.target[i] - self.slope[i] * max(self.arrive[i] - t, 0.0)

    def command(self, index: list[int], targets: list[float], move_s: float, t: float) -> None:
        here = [self.position(i, t) for i in index]
        for i, goal, p in zip(index, targets, here, strict=True):
            delta = goal - p
            duration = max(abs(delta) * self.s_per_us[i], move_s)
            self.slope[i] = delta / duration if duration > 0.0 else delta / 1.0
            self.target[i], self.arrive[i] = goal, t + duration


@settings(max_examples=60, deadline=None)
@given(data=st.data(), sizes=st.lists(st.integers(1, 8), min_size=1, max_size=3))
def test_joined_banks_and_array_commands_match_the_per_servo_model(data, sizes):
    n = sum(sizes)
    speeds = data.draw(st.lists(st.floats(2000.0, 30000.0), min_size=n, max_size=n))
    rests = data.draw(st.lists(st.floats(500.0, 2500.0), min_size=n, max_size=n))
    parts, start = [], 0
    for size in sizes:
        parts.append(ServoBank(np.array(rests[start:start + size]),
                               np.array(speeds[start:start + size])))
        start += size
    joined = ServoBank.joined(parts)
    reference = _ReferenceServos(rests, speeds)
    t = 0.0
    for _ in range(data.draw(st.integers(1, 15))):
        t += data.draw(st.sampled_from([0.0, 0.01, 0.0667, 0.2]))
        which = data.draw(st.integers(0, len(parts) - 1))
        size = sizes[which]
        local = data.draw(st.lists(st.integers(0, size - 1), min_size=1, max_size=size,
                                   unique=True))
        goals = [float(g) for g in data.draw(st.lists(st.integers(500, 2500),
                                                      min_size=len(local),
                                                      max_size=len(local)))]
        move_s = data.draw(st.sampled_from([0.0, 0.067, 0.5]))
        parts[which].command_arrays(np.array(local, dtype=np.intp), np.array(goals), move_s, t)
        offset = sum(sizes[:which])
        reference.command([offset + i for i in local], goals, move_s, t)
        for probe in (t, t + 0.03, t + 1.0):
            expected = [reference.position(i, probe) for i in range(n)]
            assert joined.position(probe).tolist() == expected  # exact, not approximate
            assert np.concatenate([p.position(probe) for p in parts]).tolist() == expected
