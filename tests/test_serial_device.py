"""SerialDevice over pyserial: pseudo-terminal pairs and fake ports play the LSC boards.

The far end of each pty decodes what SerialDevice writes with the codec (host direction) and
answers GET_BATTERY_VOLTAGE like a board (docs/device.md: reply ``55 55 04 0F lo hi``).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from _pty_helpers import (  # noqa: F401 - the fixture
    STALLED_S,
    base0_reversed,
    boards_fixture,
    url_of,
)

from crs_study.benchmarks.device import PacedPort
from crs_study.clock import RealClock
from crs_study.device import codec, decoder
from crs_study.device.base import BYTE_TIME_S, open_device
from crs_study.device.serial_device import DeviceWarning, SerialDevice
from crs_study.device.serial_port import OUT_WAITING_LOW_BYTES, SerialOptions, parse_serial_url
from crs_study.errors import DeviceError

FRAME_S = 64 * BYTE_TIME_S  # a full 19-servo frame, 66.7 ms


FAST = dict(pace=False, refresh_s=0.0)  # tests that count frames: no pacing, no refreshes


# ---------------------------------------------------------------------------------------------
# URL and options


def test_url_syntax_one_port_per_controller(layout2d):
    assert parse_serial_url("serial:///dev/ttyUSB0,/dev/ttyUSB1") == ["/dev/ttyUSB0",
                                                                      "/dev/ttyUSB1"]
    assert parse_serial_url("serial://spy:///dev/ttyUSB0?file=x.txt,loop://") == [
        "spy:///dev/ttyUSB0?file=x.txt", "loop://"]
    with pytest.raises(DeviceError, match=r"expected 2 port\(s\), one per controller \(A, B\)"):
        SerialDevice.from_url("serial:///dev/ttyUSB0", layout2d)
    with pytest.raises(DeviceError, match="got an empty port"):
        parse_serial_url("serial:///dev/ttyUSB0,")
    with pytest.raises(DeviceError, match=r"unknown serial option\(s\) 'refresh'; known:"):
        SerialDevice.from_url("serial://loop://,loop://", layout2d, refresh=2)
    with pytest.raises(DeviceError, match=r"serial option deadband_us: expected .* got -1"):
        SerialOptions(deadband_us=-1)
    with pytest.raises(DeviceError, match=r"move_ms: .* got 40000"):
        SerialOptions(move_ms=40000)


def test_open_device_dispatches_serial_urls(layout1d):
    device = open_device("serial://loop://", layout1d, check_battery=False)
    assert isinstance(device, SerialDevice) and device.options.check_battery is False


def test_missing_port_is_a_one_line_device_error(layout1d):
    device = SerialDevice.from_url("serial:///dev/does-not-exist-crs", layout1d)
    with pytest.raises(DeviceError, match=r"controller A on /dev/does-not-exist-crs: cannot open"):
        device.open()


# ---------------------------------------------------------------------------------------------
# battery


def test_battery_is_read_on_open_even_after_garbage(layout2d, boards):
    pair = boards(2, battery_mv=7400, garbage=bytes.fromhex("00 55 55 09 FF 13"))
    with SerialDevice.from_url(url_of(pair), layout2d) as device:
        assert device.battery_mv() == [7400.0, 7400.0]


@pytest.mark.parametrize("garbage", ["55 55 05 06", "00 55 55 04 0F 12", "55 55 0C 15"],
                         ids=["eats-3-bytes", "eats-1-byte", "cut-off-by-silence"])
def test_battery_is_read_on_open_after_a_false_header(layout1d, boards, garbage):
    # garbage that starts a plausible frame which, glued to the reply, passes every check
    # (codec module docstring, "False headers"): the reply is still found, not swallowed
    (board,) = boards(1, battery_mv=7400, garbage=bytes.fromhex(garbage))
    with SerialDevice.from_url(url_of([board]), layout1d, **FAST) as device:
        assert device.battery_mv() == [7400.0]


def test_silent_board_gives_none_and_a_warning(layout1d):
    # loop:// echoes our own request, which is not a battery reply
    device = SerialDevice.from_url("serial://loop://", layout1d, battery_timeout_s=0.05)
    start = time.monotonic()
    with pytest.warns(DeviceWarning, match=r"controller A on loop://: no answer to "
                      r"GET_BATTERY_VOLTAGE within 0\.05 s"):
        device.open()
    assert time.monotonic() - start < 1.0  # the wait is bounded (0.05 s + one 0.05 s read)
    try:
        assert device.battery_mv() == [None]
    finally:
        device.close()


def test_a_port_already_driven_by_another_device_is_refused(layout1d, boards):
    # two programs writing one board would interleave their frames (no checksum catches it)
    (board,) = boards(1)
    with SerialDevice.from_url(url_of([board]), layout1d, **FAST):
        second = SerialDevice.from_url(url_of([board]), layout1d, **FAST)
        with pytest.raises(DeviceError, match=r"controller A on .*: cannot open the port: "
                           r".*exclusively lock"):
            second.open()
    with SerialDevice.from_url(url_of([board]), layout1d, **FAST):
        pass  # released on close: the port opens again


def test_low_battery_refuses_to_open_and_releases_ports(layout2d, boards):
    pair = boards(2, battery_mv=5400)
    device = SerialDevice.from_url(url_of(pair), layout2d)
    with pytest.raises(DeviceError, match=r"controller A on .*: battery 5400 mV is below the "
                       r"6000 mV minimum"):
        device.open()
    assert all(p.serial is None or not p.serial.is_open for p in device.ports)


# ---------------------------------------------------------------------------------------------
# frames on the wire


def test_frames_arrive_complete_changed_only_and_in_order(layout2d, boards):
    pair = boards(2)
    with SerialDevice.from_url(url_of(pair), layout2d, **FAST) as device:
        setpoints = np.zeros(layout2d.n_actuators)
        first = device.send(setpoints, move_ms=50)
        assert first.bytes_sent == (64, 61) and first.channels_sent == 37
        for board in pair:
            board.wait_for(1)
        expected = []
        for k in range(1, 30):
            setpoints = setpoints.copy()
            setpoints[2] = 0.09 * k  # pixel 2 is A:3; 10 us a frame
            report = device.send(setpoints, move_ms=50)
            assert report.bytes_sent == (10, 0) and report.channels_sent == 1
            expected.append(((3, 1000 + 10 * k),))
            pair[0].wait_for(k + 1)
    # then close()'s neutral pose, with its slow move
    a_moves = pair[0].wait_for_last(lambda m: m.time_ms == 500, count=31)
    b_moves = pair[1].wait_for_last(lambda m: m.time_ms == 500, count=2)
    assert a_moves[0] == codec.ServoMove(tuple((ch, 1000) for ch in range(1, 20)), 50)
    assert [m.positions for m in a_moves[1:30]] == expected
    assert len(b_moves) >= 1 and b_moves[0].positions == tuple((ch, 1000) for ch in range(1, 19))
    # close: every channel to neutral with the slow neutral move time
    assert a_moves[-1] == codec.ServoMove(tuple((ch, 1000) for ch in range(1, 20)), 500)
    assert b_moves[-1].time_ms == 500 and len(b_moves[-1].positions) == 18
    for board in pair:
        assert board.decoder.skipped == [] and board.decoder.pending == b""


def test_deadband_holds_tiny_changes_back(layout1d, boards):
    (board,) = boards(1)
    with SerialDevice.from_url(url_of([board]), layout1d, deadband_us=2, **FAST) as device:
        device.send(np.zeros(7))
        board.wait_for(1)
        step = np.zeros(7)
        step[0] = 0.018  # 2 us: within the dead-band
        assert device.send(step).bytes_sent == (0,)
        step[0] = 0.027  # 3 us: sent
        assert device.send(step).bytes_sent == (10,)
        assert board.wait_for(2)[1].positions == ((1, 1003),)


def test_channel_base_0_and_a_reversed_servo_on_the_wire(layout1d, boards):
    (board,) = boards(1)
    layout = base0_reversed(layout1d)
    setpoints = np.linspace(0.5, 8.5, layout.n_actuators)
    with SerialDevice.from_url(url_of([board]), layout, **FAST) as device:
        device.send(setpoints)
        assert device.wait_sent(STALLED_S)
    first = board.wait_for(2)[0]
    assert [i for i, _ in first.positions] == list(range(7))
    assert dict(first.positions)[2] == round(2000 - 1000 * setpoints[2] / 9)  # reversed
    assert [p for _, p in board.moves()[-1].positions] == [1000, 1000, 2000, 1000, 1000, 1000,
                                                            1000]  # neutral 0 mm, reversed too


def test_out_of_range_setpoint_never_reaches_the_wire(layout2d, boards):
    pair = boards(2)
    with SerialDevice.from_url(url_of(pair), layout2d, **FAST) as device:
        device.send(np.zeros(37))
        for board in pair:
            board.wait_for(1)
        bad = np.zeros(37)
        bad[30] = 9.5
        with pytest.raises(DeviceError, match=r"channel B:12 beam 5 end: setpoint 9\.5 mm is "
                           r"outside its calibrated range 0\.\.9 mm"):
            device.send(bad)
        time.sleep(0.05)
        assert len(pair[0].moves()) == 1 and len(pair[1].moves()) == 1
    for board in pair:
        for move in board.moves():
            assert all(1000 <= p <= 2000 for _, p in move.positions)


def test_frames_faster_than_the_wire_merge_and_latency_stays_bounded(layout2d, boards):
    pair = boards(2)
    with SerialDevice.from_url(url_of(pair), layout2d, refresh_s=0.0) as device:  # paced
        reports = []
        for k in range(12):  # every channel changes, 4 ms apart: far beyond the wire
            reports.append(device.send(np.full(37, 0.1 * (k + 1))))
            time.sleep(0.004)
        assert any(r.merged for r in reports)
        # merged, not queued: 12 queued frames would wait ~12 frame times; the margin
        # allows a machine several times oversubscribed
        assert max(r.latency_s for r in reports) <= 4 * FRAME_S + 0.1
        last_wanted = device.pulse_map.to_pulses(np.full(37, 1.2))
        assert device.wait_sent(STALLED_S)
    moves = pair[0].wait_for_last(lambda m: m.time_ms == 500, count=2)   # close()'s
    assert len(moves) < 12  # merged, not queued
    wanted_a = last_wanted[device.split.members[0]].tolist()
    assert [p for _, p in moves[-2].positions] == wanted_a  # the newest frame went out
    assert len(moves[-1].positions) == 19 and moves[-1].time_ms == 500  # then neutral


def test_full_refresh_resends_every_channel(layout1d, boards):
    # The refresh rides on the first frame written refresh_s after the last full one, even
    # when nothing changed; a held pose is not rewritten on its own (the write policy,
    # device/writes.py, says why). This test once asserted the opposite: three full writes
    # within a second after a single frame, the serial device's own rule before the policy
    # was one for all three writers.
    (board,) = boards(1)
    with SerialDevice.from_url(url_of([board]), layout1d, pace=False, refresh_s=0.5) as device:
        device.send(np.zeros(7))
        assert device.wait_sent(STALLED_S)
        time.sleep(0.6)
        assert len(board.wait_for(2, timeout=0.1)) == 1  # the held pose: not rewritten
        device.send(np.zeros(7))  # nothing changed, but the refresh is due: every channel
        assert device.wait_sent(STALLED_S)
        device.send(np.zeros(7))  # right after: nothing changed, nothing written
        assert device.wait_sent(STALLED_S)
        moves = board.wait_for(3, timeout=0.3)
        assert len(moves) == 2 and all(len(m.positions) == 7 for m in moves)


def test_controllers_are_written_concurrently(layout2d):
    # ports that take time to write (4 x the 9600-baud wire's: 0.27 s a frame, a margin
    # against a loaded machine starting one writer thread late)
    ports = [PacedPort(c.name, 4 * BYTE_TIME_S) for c in layout2d.controllers]
    device = SerialDevice(layout2d, ports, RealClock(),
                          SerialOptions(check_battery=False, refresh_s=0.0))
    with device:
        device.send(np.full(37, 1.0))
        assert device.wait_sent(STALLED_S)
    (a_start, a_end, _), (b_start, b_end, _) = ports[0].writes[0], ports[1].writes[0]
    assert a_start < b_end and b_start < a_end  # the two writes overlap in time


# ---------------------------------------------------------------------------------------------
# faults


def test_vanished_port_raises_within_one_frame_period_and_close_releases(layout2d, boards):
    pair = boards(2)
    device = SerialDevice.from_url(url_of(pair), layout2d)
    device.open()
    try:
        for k in range(5):
            device.send(np.full(37, 0.5 * k))
            time.sleep(0.02)
        pair[1].vanish()
        gone = time.monotonic()
        with pytest.raises(DeviceError, match=r"controller B on .*: port failed"):
            while time.monotonic() - gone < 1.0:
                device.send(np.full(37, 3.0))
                time.sleep(0.005)
        assert time.monotonic() - gone <= FRAME_S
    finally:
        device.close()
    assert any("controller B" in f and "neutral pose not sent" in f for f in device.faults)
    assert not device.ports[1].serial.is_open and not device.ports[0].serial.is_open
    # the healthy controller still got its neutral pose
    assert pair[0].wait_for_last(lambda m: m.time_ms == 500)[-1].time_ms == 500


def test_stalled_writer_is_reported_not_waited_for(layout1d):
    release = threading.Event()

    entered = threading.Event()

    class StuckPort(PacedPort):
        def write(self, data: bytes) -> int:
            entered.set()
            release.wait(3.0)  # ignores its write timeout, like a wedged driver
            return len(data)

    device = SerialDevice(layout1d, [StuckPort("stuck", 0.0)], RealClock(),
                          SerialOptions(check_battery=False, write_timeout_s=0.05, refresh_s=0))
    device.open()
    try:
        device.send(np.zeros(7))
        # timed from when the writer is stuck (a loaded machine may start the thread late):
        # reported once a write has taken write_timeout_s + 0.5 s
        assert entered.wait(2.0)
        time.sleep(0.6)
        start = time.monotonic()
        with pytest.raises(DeviceError, match=r"controller A on stuck: a write has not finished"):
            device.send(np.ones(7))
        # send() never blocks: it returned while the write it found stuck (3 s) still hangs
        assert time.monotonic() - start < 0.5 and not release.is_set()
        assert device.ports[0].writing_since is not None
    finally:
        release.set()
        device.close()


def test_writer_waits_for_the_output_buffer_and_reports_one_that_never_drains(layout1d):
    # out_waiting is the port's own count of bytes not yet on the wire: the writer waits for
    # it (at most OUT_WAITING_LOW_BYTES), so a slow wire can never queue frames in the OS
    # buffer; a buffer that does not drain within write_timeout_s is a port failure.
    class Backlogged(PacedPort):
        backlog = 0

        @property
        def out_waiting(self) -> int:
            return self.backlog

    port = Backlogged("A", 0.0)
    device = SerialDevice(layout1d, [port], RealClock(),
                          SerialOptions(check_battery=False, refresh_s=0.0, write_timeout_s=0.2))
    device.open()
    try:
        device.send(np.zeros(7))
        assert device.wait_sent(STALLED_S) and len(port.writes) == 1
        port.backlog = OUT_WAITING_LOW_BYTES + 1  # the wire is behind: nothing more is written
        for k in range(1, 4):
            device.send(np.full(7, float(k)))  # merged while the writer waits
        time.sleep(0.1)
        assert len(port.writes) == 1
        port.backlog = OUT_WAITING_LOW_BYTES  # drained: the newest frame goes, once
        assert device.wait_sent(STALLED_S) and len(port.writes) == 2
        assert decoder.decode_all(bytes(port.data))[0][-1].message.positions[0] == (1, 1333)
        port.backlog = 100  # stuck (flow control held, a wedged adapter)
        device.send(np.full(7, 4.0))
        time.sleep(0.5)
        with pytest.raises(DeviceError, match=r"controller A on A: port failed: output not "
                           r"draining: 100 bytes still waiting after 0\.2\d s"):
            device.send(np.full(7, 5.0))
    finally:
        device.close()
    assert len(port.writes) == 3  # the neutral pose was still attempted, directly


def test_ctrl_c_inside_a_session_still_sends_neutral_and_releases(layout1d, boards):
    (board,) = boards(1)
    device = SerialDevice.from_url(url_of([board]), layout1d, **FAST)
    with pytest.raises(KeyboardInterrupt), device:
        device.send(np.full(7, 4.0))
        raise KeyboardInterrupt
    moves = board.wait_until(lambda m: any(x.time_ms == 500 for x in m))
    assert moves[-1] == codec.ServoMove(tuple((ch, 1000) for ch in range(1, 8)), 500)
    assert not device.ports[0].serial.is_open
    with pytest.raises(DeviceError, match="send\\(\\) on a device that is closed"):
        device.send(np.zeros(7))
    device.close()  # idempotent


def test_neutral_on_a_failed_port_waits_for_the_write_in_progress(layout1d):
    # the reader notices the port failing while the writer is still inside a write: the
    # neutral frame close() writes directly must not overlap it (the bytes would interleave)
    failing = threading.Event()

    class FailingReads(PacedPort):
        def read(self, n: int) -> bytes:
            time.sleep(0.005)
            if failing.is_set():
                raise OSError(5, "Input/output error")
            return b""

    port = FailingReads("A", 0.003)  # a 7-servo frame, 28 bytes, takes 84 ms to write
    device = SerialDevice(layout1d, [port], RealClock(),
                          SerialOptions(check_battery=False, refresh_s=0.0))
    device.open()
    device.send(np.full(7, 3.0))
    deadline = time.monotonic() + 2.0
    while device.ports[0].writing_since is None and time.monotonic() < deadline:
        time.sleep(0.001)  # until the writer is inside write()
    failing.set()
    while device.ports[0].error is None and time.monotonic() < deadline:
        time.sleep(0.001)
    device.close()
    (first_start, first_end, _), (second_start, _, _) = sorted(port.writes)
    assert second_start >= first_end  # one after the other
    frames, skipped = decoder.decode_all(bytes(port.data))
    assert skipped == [] and frames[-1].message.time_ms == 500  # neutral, whole
