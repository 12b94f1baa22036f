"""The lscsim:// pyserial handler: byte-timed writes, battery replies, timeouts, a vanishing port.

Wire time (docs/device.md): 10 bits a byte, so a 4-byte GET_BATTERY_VOLTAGE plus its 6-byte
reply take 10 x 1.0417 ms at 9600 baud.
"""

from __future__ import annotations

import time

import pytest
import serial

from crs_study.device import codec, protocol_lscsim


@pytest.fixture
def port():
    protocol_lscsim.register()
    name = f"t{time.monotonic_ns()}"
    handle = serial.serial_for_url(f"lscsim://{name}?battery_mv=7500", baudrate=9600,
                                   timeout=0.2, write_timeout=0.2)
    yield handle
    handle.close()
    protocol_lscsim.detach(name)


def test_battery_reply_arrives_after_its_wire_time(port):
    start = time.monotonic()
    port.write(codec.get_battery_voltage())
    assert port.read(6) == bytes.fromhex("55 55 04 0F 4C 1D")  # 7500 mV (docs/device.md)
    assert time.monotonic() - start >= 10 * 10 / 9600 - 1e-3


def test_read_times_out_with_nothing_to_read(port):
    start = time.monotonic()
    assert port.read(1) == b""
    assert 0.15 <= time.monotonic() - start < 1.0


def test_out_waiting_drains_at_the_baud_rate_and_frames_reach_the_board(port):
    frame = codec.servo_move({i: 1500 for i in range(1, 20)}, 0)  # 64 bytes, 66.7 ms
    port.write(frame)
    assert 55 <= port.out_waiting <= 64
    port.flush()
    assert port.out_waiting == 0
    assert port.controller.good_frames == 1


def test_write_timeout_when_the_wire_is_far_behind(port):
    frame = codec.servo_move({i: 1500 for i in range(1, 20)}, 0)
    with pytest.raises(serial.SerialTimeoutException):
        for _ in range(10):  # 10 x 66.7 ms queued: beyond the 0.2 s write timeout
            port.write(frame)


def test_vanished_port_raises_on_write(port):
    port.vanish()
    with pytest.raises(serial.SerialException, match="Input/output error"):
        port.write(codec.get_battery_voltage())


def test_malformed_url_is_refused():
    protocol_lscsim.register()
    with pytest.raises(serial.SerialException, match="unknown option 'speed'"):
        serial.serial_for_url("lscsim://x?speed=3")


def test_threads_sharing_a_port_deliver_frames_in_order():
    # SerialDevice reads a port (read, in_waiting) in one thread and writes it (write,
    # out_waiting) in another; every one of those calls delivers what has arrived to the board.
    # Without the port's lock two threads could each pop a frame and hand them over in the
    # wrong order: with a tiny switch interval every one of 5 runs failed (A:1 = 1356, 1357,
    # 1355, 1358 and arrival times going backwards); with it, 0 failures in 20.
    import sys
    import threading

    from crs_study.device.virtual_controller import VirtualController

    protocol_lscsim.register()
    name = f"stress{time.monotonic_ns()}"
    board = protocol_lscsim.attach(name, VirtualController(name, record=True,
                                                           t0=time.monotonic()))
    port = serial.serial_for_url(f"lscsim://{name}", baudrate=1_000_000, timeout=0.001,
                                 write_timeout=None)
    interval = sys.getswitchinterval()
    done = threading.Event()

    def poll(read: bool) -> None:
        while not done.is_set():
            if read:
                port.read(1)
            else:
                port.in_waiting  # noqa: B018 - the property pumps the wire
                port.out_waiting  # noqa: B018

    pollers = [threading.Thread(target=poll, args=(flag,)) for flag in (True, False, False)]
    sys.setswitchinterval(1e-6)
    try:
        for thread in pollers:
            thread.start()
        for k in range(2000):
            port.write(codec.servo_move({1: 500 + k}, 0))
        port.flush()
    finally:
        done.set()
        for thread in pollers:
            thread.join()
        sys.setswitchinterval(interval)
        port.close()
        protocol_lscsim.detach(name)
    values = [dict(r.message.positions)[1] for r in board.received]
    assert values == [500 + k for k in range(2000)]
    times = [r.t for r in board.received]
    assert times == sorted(times)
    assert board.bad_frames == 0
