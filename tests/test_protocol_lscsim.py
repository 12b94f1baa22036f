"""The lscsim:// pyserial handler: byte-timed writes, battery replies, timeouts, a vanishing port.

Wire time (hardware.md): 10 bits a byte, so a 4-byte GET_BATTERY_VOLTAGE plus its 6-byte
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
    assert port.read(6) == bytes.fromhex("55 55 04 0F 4C 1D")  # 7500 mV (hardware.md)
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
