"""SimulatedDevice: the bytes it puts on its virtual wires, wire timing, servo display, faults.

Sources written beside the numbers (docs/device.md, "What the wire allows"): 9600 baud 8N1 is
10 bits a byte; SERVO_MOVE for n servos is 3n + 7 bytes; 18 servos 61 bytes 63.5 ms, 19
servos 64 bytes 66.7 ms. docs/device.md, "The published 2D device": 0.08 s/cm, a 9 mm stroke
in 72 ms.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from _pty_helpers import base0_reversed
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.clock import RealClock, VirtualClock
from crs_study.device import codec
from crs_study.device.base import DeviceWarning, open_device
from crs_study.device.simulated import SimOptions, SimulatedDevice
from crs_study.device.virtual_controller import BROWNOUT_BATTERY_MV
from crs_study.errors import DeviceError

BYTE_S = 10 / 9600
MM_PER_US = 9.0 / 1000  # crs2d calibration: whole-us pulses quantise setpoints to 0.009 mm


def sim(layout, url="sim://", clock=None, **kw) -> SimulatedDevice:
    device = open_device(url, layout, clock or VirtualClock(), **kw)
    device.open()
    return device


def expected_frame(layout, controller, setpoints, only=None, move_ms=0):
    """SERVO_MOVE bytes built independently from the device file's calibration."""
    pairs = []
    for a in layout.actuators:
        if a.controller == controller and (only is None or a.index in only):
            cal = a.calibration  # docs/device.md, "Linear PWM servos": the device file's line
            pulse = cal.zero_us + (cal.full_us - cal.zero_us) * setpoints[a.index] / cal.travel_mm
            pairs.append((a.channel, int(np.rint(pulse))))
    return codec.servo_move(pairs, move_ms)


# -- the bytes ------------------------------------------------------------------------------


def test_boards_receive_the_calibrated_frames_then_only_changed_channels(layout2d, rng):
    device = sim(layout2d, record=True)
    clock = device.clock
    first = rng.uniform(0, 9.0, layout2d.n_actuators)
    device.send(first, move_ms=40)
    clock.advance(0.2)
    second = first.copy()
    second[2] = 1.0  # pixel 2 is A:3
    second[12] = 2.0  # pixel 12 is B:3
    device.send(second, move_ms=40)
    clock.advance(0.2)
    device.displayed_setpoints()
    a, b = device.boards
    moves = [[r.message.encode() for r in board.received if isinstance(r.message, codec.ServoMove)]
             for board in device.boards]
    assert moves[0] == [
        expected_frame(layout2d, "A", first, move_ms=40),
        expected_frame(layout2d, "A", second, only={2}, move_ms=40),
    ]
    assert moves[1] == [
        expected_frame(layout2d, "B", first, move_ms=40),
        expected_frame(layout2d, "B", second, only={12}, move_ms=40),
    ]


def test_channel_base_0_and_a_reversed_servo_reach_the_right_servos(layout1d):
    layout = base0_reversed(layout1d)
    setpoints = np.linspace(0.5, 8.5, layout.n_actuators)
    device = sim(layout, record=True)
    device.send(setpoints)
    device.clock.advance(1.0)
    displayed = device.displayed_setpoints()  # delivers the frame, moves the servos
    (move,) = [r.message for r in device.boards[0].received
               if isinstance(r.message, codec.ServoMove)]
    # ids 0..6 on the wire; actuator 2 runs from 2000 us at 0 mm down to 1000 us at 9 mm
    assert move.encode() == expected_frame(layout, "A", setpoints, move_ms=device.default_move_ms)
    assert [i for i, _ in move.positions] == list(range(7))
    assert dict(move.positions)[2] == round(2000 - 1000 * setpoints[2] / 9)
    assert device.boards[0].unknown_ids == 0
    assert np.allclose(displayed, setpoints, atol=MM_PER_US / 2)


def test_full_refresh_resends_every_channel(layout2d):
    device = sim(layout2d, "sim://?refresh_s=0.5")
    same = np.full(layout2d.n_actuators, 3.0)
    assert device.send(same).channels_sent == 37
    device.clock.advance(0.2)
    assert device.send(same).channels_sent == 0
    device.clock.advance(0.4)
    assert device.send(same).channels_sent == 37


@pytest.mark.parametrize(
    ("controller", "servos", "wire_ms"),
    [pytest.param(0, 19, 66.7, id="A-19-servos-66.7ms"),
     pytest.param(1, 18, 63.5, id="B-18-servos-63.5ms")],
)
def test_wire_time_matches_hardware_table(layout2d, controller, servos, wire_ms):
    device = sim(layout2d)
    report = device.send(np.full(layout2d.n_actuators, 4.0))
    assert report.bytes_sent[controller] == 3 * servos + 7
    assert report.latency_s == pytest.approx(66.7e-3, abs=0.05e-3)  # the busiest board
    assert report.bytes_sent[controller] * BYTE_S == pytest.approx(wire_ms * 1e-3, abs=0.05e-3)


def test_frames_faster_than_the_wire_merge_and_latency_never_grows(layout2d, rng):
    device = sim(layout2d)
    clock = device.clock
    frame_s = 64 * BYTE_S
    latencies, merged = [], 0
    for _ in range(300):
        target = rng.uniform(0, 9.0, layout2d.n_actuators)
        report = device.send(target)
        latencies.append(report.latency_s)
        merged += report.merged
        clock.advance(0.01)  # 100 frames/s: far beyond the wire's 15/s
    assert merged > 200
    assert max(latencies) <= 2 * frame_s + 1e-9
    # the last setpoints still reach the servos
    clock.advance(2 * frame_s + 0.1)
    assert device.displayed_setpoints() == pytest.approx(target, abs=0.01)


def test_send_never_advances_a_virtual_clock(layout2d):
    device = sim(layout2d)
    before = device.clock.now()
    for k in range(20):
        device.send(np.full(layout2d.n_actuators, k * 0.4))
        device.displayed_setpoints()
    assert device.clock.now() == before


# -- what is displayed ------------------------------------------------------------------------


def test_displayed_setpoints_follow_wire_then_servo_motion(layout2d):
    device = sim(layout2d)
    clock = device.clock
    start = clock.now()
    target = np.zeros(layout2d.n_actuators)
    target[0] = 9.0  # pixel 0 on A: full stroke
    report = device.send(target)  # first frame: all 19 channels of A, 66.7 ms
    assert device.displayed_setpoints(start + 0.05)[0] == 0.0  # bytes still on the wire
    done = report.wire_done_at
    assert done - start == pytest.approx(64 * BYTE_S)
    assert device.displayed_setpoints(done + 0.036)[0] == pytest.approx(4.5)  # 72 ms stroke
    assert device.displayed_setpoints(done + 0.072)[0] == pytest.approx(9.0)
    assert device.displayed_setpoints(done + 1.0) == pytest.approx(target)


def test_move_time_slows_the_servos(layout2d):
    device = sim(layout2d)
    target = np.full(layout2d.n_actuators, 9.0)
    report = device.send(target, move_ms=500)
    done = report.wire_done_at  # the A board's frame; B's ended 3 bytes earlier
    assert device.displayed_setpoints(done + 0.25)[0] == pytest.approx(4.5)


def test_real_clock_works_without_threads(layout2d):
    with open_device("sim://", layout2d, RealClock()) as device:
        report = device.send(np.full(layout2d.n_actuators, 2.0))
        assert report.latency_s == pytest.approx(64 * BYTE_S)
        later = device.displayed_setpoints(report.wire_done_at + 0.1)
        assert later == pytest.approx(np.full(layout2d.n_actuators, 2.0), abs=MM_PER_US)


def test_close_goes_to_neutral_and_is_idempotent(layout2d):
    device = sim(layout2d)
    device.send(np.full(layout2d.n_actuators, 5.0))
    device.close()
    device.close()
    assert device.neutral_attempted
    assert device.displayed_setpoints(device.clock.now() + 1.0) == pytest.approx(
        np.zeros(layout2d.n_actuators))
    with pytest.raises(DeviceError, match="closed"):
        device.send(np.zeros(layout2d.n_actuators))


def test_out_of_range_setpoint_never_reaches_the_wire(layout2d):
    device = sim(layout2d, record=True)
    bad = np.full(layout2d.n_actuators, 1.0)
    bad[25] = 9.5
    with pytest.raises(DeviceError, match=r"A:\d+ beam .*9\.5 mm.*0\.\.9 mm"):
        device.send(bad)
    device.clock.advance(1.0)
    device.displayed_setpoints()
    assert [len(b.received) for b in device.boards] == [1, 1]  # the battery query only


def test_low_battery_is_refused_on_open(layout2d):
    device = open_device("sim://?battery_mv=5200", layout2d, VirtualClock())
    with pytest.raises(DeviceError, match="battery reads 5200 mV"):
        device.open()


# -- URL options --------------------------------------------------------------------------------


# -- the battery, over the wire ----------------------------------------------------------------


def test_battery_is_asked_over_the_wire_and_takes_its_bytes_time(layout2d):
    # docs/device.md: GET_BATTERY_VOLTAGE is 55 55 02 0F (4 bytes), the reply 55 55 04 0F lo hi
    # (6 bytes); the query waits for the frame already on the wire (64 bytes on A)
    device = sim(layout2d, "sim://?battery_mv=7100", record=True)
    for board in device.boards:
        assert [type(r.message) for r in board.received] == [codec.GetBatteryVoltage]
    device.send(np.full(layout2d.n_actuators, 2.0))
    t = device.clock.now()
    assert device.battery_mv() == [7100.0, 7100.0]
    a, b = device.boards
    asked = [r.t for r in a.received if isinstance(r.message, codec.GetBatteryVoltage)]
    assert asked[-1] == pytest.approx(t + (64 + 4) * BYTE_S)  # after A's full frame
    assert device.clock.now() == pytest.approx(t + (64 + 4 + 6) * BYTE_S)  # A's reply is in
    device.close()
    assert device.battery_mv() == [7100.0, 7100.0]  # after close: what was read last


def test_the_battery_reading_is_the_reply_bytes_decoded_not_the_boards_state(layout2d,
                                                                           monkeypatch):
    # a board whose reply comes after a false header (55 55 05 06 would take the reply's
    # first bytes for a frame) and reads one volt lower than the board's own state: the device
    # reports what the bytes say
    from crs_study.device import virtual_controller

    monkeypatch.setattr(virtual_controller, "battery_voltage_reply",
                        lambda mv: bytes.fromhex("55 55 05 06") + codec.battery_voltage_reply(
                            mv - 1000))
    device = sim(layout2d)
    assert device.battery_mv() == [6400.0, 6400.0]
    assert [b.battery_mv() for b in device.boards] == [7400, 7400]


def test_a_battery_reply_lost_on_the_wire_is_a_warning_and_none(layout2d):
    # every byte preceded by a random one (garbage_rate=1): no query or reply survives
    device = open_device("sim://?garbage_rate=1&seed=2", layout2d, VirtualClock())
    with pytest.warns(DeviceWarning, match=r"controller [AB]: no answer to GET_BATTERY_VOLTAGE; "
                      r"battery unknown") as caught:
        device.open()
    assert len(caught) == 2  # both boards
    assert device.battery_mv() == [None, None]
    # a port that vanished at open gives no answer either; the other board does
    device = open_device("sim://?disconnect_at=B@0", layout2d, VirtualClock())
    with pytest.warns(DeviceWarning, match="controller B: no answer") as caught:
        device.open()
    assert len(caught) == 1 and device.battery_mv() == [7400.0, None]


def test_url_options_parse(layout2d):
    options = SimOptions.parse(
        "sim://?baud=19200&disconnect_at=3.5&garbage_rate=0.01&stall=A:3@2.0,B:4@1"
        "&brownout_at=B@5&seed=7&move_ms=30&refresh_s=0", layout2d)
    assert options.baud == 19200
    assert options.disconnect_at == ((None, 3.5),)
    assert options.garbage_rate == 0.01
    assert options.stall == (("A", 3, 2.0), ("B", 4, 1.0))
    assert options.brownout_at == (("B", 5.0),)
    assert (options.seed, options.move_ms, options.refresh_s) == (7, 30, 0.0)


@pytest.mark.parametrize(
    ("url", "message"),
    [pytest.param("sim://?baud=fast", r"option baud: expected a whole number.*'fast'", id="baud"),
     pytest.param("sim://?speed=3", r"unknown option 'speed'; valid: baud", id="unknown"),
     pytest.param("sim://?garbage_rate=2", r"garbage_rate: expected a number in \[0.0, 1.0\]",
                  id="rate"),
     pytest.param("sim://?stall=A3@1", r"expected CONTROLLER:CHANNEL@SECONDS.*'A3@1'",
                  id="stall-form"),
     pytest.param("sim://?stall=A:24@1", r"'A:24' drives no actuator", id="stall-channel"),
     pytest.param("sim://?disconnect_at=C@1", r"unknown controller 'C'", id="controller"),
     pytest.param("sim://?disconnect_at=soon", r"disconnect_at: expected a number.*'soon'",
                  id="time"),
     pytest.param("sim://host/x", r"expected sim://\[\?key=value", id="netloc")],
)
def test_malformed_options_are_one_line_errors(layout2d, url, message):
    with pytest.raises(DeviceError, match=message) as info:
        SimOptions.parse(url, layout2d)
    assert "\n" not in str(info.value)


def test_keyword_options_override_the_url(layout2d):
    assert SimOptions.parse("sim://?seed=1", layout2d, seed=5).seed == 5
    with pytest.raises(DeviceError, match="seed: expected a whole number"):
        SimOptions.parse("sim://", layout2d, seed=1.5)


@settings(max_examples=80, deadline=None)
@given(st.text(max_size=40))
def test_any_query_parses_or_fails_with_a_device_error(layout1d, query):
    try:
        SimOptions.parse("sim://?" + query, layout1d)
    except DeviceError as exc:
        assert "\n" not in str(exc)


# -- faults -------------------------------------------------------------------------------------


def test_port_vanishing_raises_within_a_frame_and_close_survives(layout2d):
    device = sim(layout2d, "sim://?disconnect_at=0.5")
    clock = device.clock
    frame_s = 64 * BYTE_S
    setpoints = np.full(layout2d.n_actuators, 1.0)
    raised_at = None
    while clock.now() < 2.0:
        setpoints = 9.0 - setpoints
        try:
            device.send(setpoints)
        except DeviceError as exc:
            assert "port vanished" in str(exc)
            raised_at = clock.now()
            break
        clock.advance(frame_s)
    assert raised_at is not None
    assert raised_at - (device.opened_at + 0.5) <= frame_s
    device.close()  # attempts neutral, cannot reach it, does not raise
    assert device.neutral_attempted and device.closed
    assert any("neutral pose not reached" in f for f in device.faults)
    # the frame cut off on the wire is a bad frame at the board
    assert sum(b.bad_frames for b in device.boards) >= 1


def test_one_port_vanishing_is_reported_by_name(layout2d):
    device = sim(layout2d, "sim://?disconnect_at=B@0.1")
    device.clock.advance(0.2)
    with pytest.raises(DeviceError, match="controller B: port vanished at 0.100 s"):
        device.send(np.zeros(layout2d.n_actuators))


def test_one_port_vanishing_still_sends_neutral_to_the_other_board(layout2d):
    # a lab's safety need: the board whose port survived must still reach the neutral pose
    device = sim(layout2d, "sim://?disconnect_at=B@0.5", record=True)
    device.send(np.full(layout2d.n_actuators, 4.0))
    device.clock.advance(1.0)
    with pytest.raises(DeviceError, match="controller B: port vanished"):
        device.send(np.full(layout2d.n_actuators, 5.0))
    device.close()
    a, b = device.boards
    last_a = [r.message for r in a.received if isinstance(r.message, codec.ServoMove)][-1]
    neutral = expected_frame(layout2d, "A", layout2d.neutral_setpoints(), move_ms=500)
    assert last_a.encode() == neutral
    assert not any(isinstance(r.message, codec.ServoMove) and r.message.time_ms == 500
                   for r in b.received)
    assert any("controller B" in f and "neutral pose not reached" in f for f in device.faults)
    assert not any("controller A" in f for f in device.faults)


def test_garbage_is_counted_resynchronised_and_never_hangs(layout2d):
    def run(seed):
        rng = np.random.default_rng(11)
        device = sim(layout2d, f"sim://?garbage_rate=0.01&seed={seed}")
        for _ in range(400):
            device.send(rng.uniform(0, 9.0, layout2d.n_actuators))
            device.clock.advance(0.07)
        device.close()
        return device

    start = time.monotonic()
    device = run(3)
    assert time.monotonic() - start < 10.0
    bad = sum(b.bad_frames for b in device.boards)
    good = sum(b.good_frames for b in device.boards)
    # 1 % of ~60 bytes: about half the frames carry one garbage byte; most still frame
    assert bad > 50
    assert good > 0.5 * 2 * 400
    assert run(3).boards[0].bad_frames == device.boards[0].bad_frames  # seeded


def test_stalled_servo_is_displayed_where_it_stuck(layout2d):
    device = sim(layout2d, "sim://?stall=A:3@1.0")  # A:3 drives pixel 2
    clock = device.clock
    device.send(np.full(layout2d.n_actuators, 6.0))
    clock.advance(1.5)
    device.send(np.full(layout2d.n_actuators, 2.0))
    clock.advance(1.0)
    shown = device.displayed_setpoints()
    assert shown[2] == pytest.approx(6.0, abs=MM_PER_US)
    assert np.delete(shown, 2) == pytest.approx(np.full(layout2d.n_actuators - 1, 2.0),
                                                abs=MM_PER_US)


def test_brownout_is_a_device_error_servos_sink_and_battery_reads_low(layout2d):
    device = sim(layout2d, "sim://?brownout_at=1.0")
    clock = device.clock
    device.send(np.full(layout2d.n_actuators, 9.0))
    clock.advance(1.5)
    with pytest.raises(DeviceError, match=r"controller A: brown-out at 1.000 s.*4800 mV"):
        device.send(np.full(layout2d.n_actuators, 9.0))
    assert device.displayed_setpoints() == pytest.approx(np.zeros(layout2d.n_actuators))
    assert device.battery_mv() == [BROWNOUT_BATTERY_MV] * 2
    device.close()
    assert device.neutral_attempted and len(device.faults) >= 1


def test_remembered_frames_change_nothing(layout2d, rng):
    # the encode/decode caches are pure speed: the boards see and do exactly the same
    frames = rng.uniform(0, 9.0, (30, layout2d.n_actuators))
    frames[10:20] = frames[:10]  # recurring frames hit the caches

    def run(clear):
        device = sim(layout2d, record=True)
        shown = []
        for f in frames:
            if clear:
                device.clear_caches()
            device.send(f)
            device.clock.advance(0.05)
            shown.append(device.displayed_setpoints())
        return device, np.array(shown)

    cached, shown_cached = run(False)
    fresh, shown_fresh = run(True)
    assert np.array_equal(shown_cached, shown_fresh)
    for a, b in zip(cached.boards, fresh.boards, strict=True):
        assert [r.message for r in a.received] == [r.message for r in b.received]
