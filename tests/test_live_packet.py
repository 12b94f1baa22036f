"""The finger packet, version 1 (crs_study/live/packet.py; the table and the published byte
vector in crs_study/live/README.md)."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.live import FingerPacket, PacketError, decode_packet, encode_packet
from crs_study.live.packet import PACKET_SIZE

README = Path(__file__).resolve().parents[1] / "crs_study" / "live" / "README.md"
EXAMPLE = FingerPacket(0x12345678, 1, 2.5, 10.0, -5.0, 3.0)


def published_vector() -> bytes:
    """The example's bytes as the README prints them (the contract a Unity sender follows)."""
    text = README.read_text(encoding="utf-8")
    block = re.search(r"\(10, -5, 3\) mm:\n\n```\n([0-9a-f ]+)\n```", text)
    assert block, "the README's example byte vector is missing"
    return bytes.fromhex(block.group(1))


def test_published_vector_decodes_to_the_example_and_back():
    data = published_vector()
    assert len(data) == PACKET_SIZE == 36
    assert decode_packet(data) == EXAMPLE
    assert encode_packet(EXAMPLE) == data


def test_the_layout_is_the_readme_table():
    # the table's offsets, read with struct one field at a time (an independent reading)
    data = published_vector()
    assert data[0:4] == b"CRSF" and data[4] == 1 and data[5] == 0
    assert struct.unpack_from("<H", data, 6) == (0,)
    assert struct.unpack_from("<I", data, 8) == (0x12345678,)
    assert struct.unpack_from("<I", data, 12) == (1,)
    assert struct.unpack_from("<d", data, 16) == (2.5,)
    assert struct.unpack_from("<3f", data, 24) == (10.0, -5.0, 3.0)


u32 = st.integers(0, 2**32 - 1)
f32 = st.floats(-1e6, 1e6, allow_nan=False, width=32)


@given(u32, u32, st.floats(-1e9, 1e9, allow_nan=False), f32, f32, f32)
def test_round_trip(stream, sequence, sent, x, y, z):
    packet = FingerPacket(stream, sequence, sent, x, y, z)
    assert decode_packet(encode_packet(packet)) == packet


@given(st.binary(max_size=80))
def test_any_bytes_decode_or_raise_packet_error(data):
    try:
        packet = decode_packet(data)
    except PacketError:
        return
    assert len(data) == PACKET_SIZE and data[:4] == b"CRSF"
    assert all(math.isfinite(v) for v in (packet.x_mm, packet.y_mm, packet.z_mm))


def _with(offset: int, fmt: str, value) -> bytes:
    data = bytearray(encode_packet(EXAMPLE))
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


@pytest.mark.parametrize("data, message", [
    pytest.param(encode_packet(EXAMPLE)[:-1], "expected 36 bytes, got 35", id="short"),
    pytest.param(encode_packet(EXAMPLE) + b"\0", "expected 36 bytes, got 37", id="long"),
    pytest.param(b"XRSF" + encode_packet(EXAMPLE)[4:], "magic", id="magic"),
    pytest.param(_with(4, "<B", 2), "version 1, got 2", id="version"),
    pytest.param(_with(5, "<B", 1), "flags and reserved", id="flags"),
    pytest.param(_with(6, "<H", 7), "flags and reserved", id="reserved"),
    pytest.param(_with(24, "<f", float("nan")), "finite", id="nan-x"),
    pytest.param(_with(32, "<f", float("inf")), "finite", id="inf-z"),
    pytest.param(_with(16, "<d", float("nan")), "finite", id="nan-time"),
])
def test_malformed_packets_say_why(data, message):
    with pytest.raises(PacketError, match=re.escape(message)):
        decode_packet(data)


@pytest.mark.parametrize("kwargs, message", [
    ({"stream": -1}, "stream"), ({"sequence": 2**32}, "sequence"), ({"stream": True}, "stream"),
    ({"x_mm": float("nan")}, "x_mm"), ({"z_mm": "3"}, "z_mm"),
])
def test_packet_fields_are_checked(kwargs, message):
    fields = dict(stream=1, sequence=1, sender_time=0.0, x_mm=0.0, y_mm=0.0, z_mm=1.0)
    with pytest.raises(PacketError, match=message):
        FingerPacket(**{**fields, **kwargs})


def test_coordinates_are_float32():
    packet = decode_packet(encode_packet(FingerPacket(1, 1, 0.0, 0.1, 0.2, 0.3)))
    assert packet.x_mm == float(np.float32(0.1)) and packet.x_mm != 0.1
