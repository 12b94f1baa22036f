"""The finger packet: one UDP datagram from the VR scene per headset frame (format version 1).

The paper's scene (Wang, Meng & Chen 2025, Methods) sends the fingertip's position
relative to the centre of the display's recognition area, (x_f, y_f, z_f), over UDP. This
module is that datagram as bytes and back, pure (no sockets). 36 bytes, little-endian::

    offset  type     field
     0      4 bytes  magic        b"CRSF"
     4      uint8    version      1
     5      uint8    flags        0 (reserved: a version-1 receiver drops a packet with any set)
     6      uint16   reserved     0
     8      uint32   stream       chosen at random when the sender starts; a new stream is a new
                                  sequence (a restarted scene counts from 0 again)
    12      uint32   sequence     +1 per packet within a stream, wrapping from 2^32 - 1 to 0
                                  (compared as RFC 1982 serial numbers: :func:`newer`)
    16      float64  sender_time  seconds on the sender's own clock (recorded, never compared
                                  with ours)
    24      float32  x_f          mm, in the display's plane, from the area's centre
    28      float32  y_f          mm, in the display's plane (ignored by a 1D display)
    32      float32  z_f          mm, press depth along the area's normal: the bump's height;
                                  <= 0 is a finger that does not press (a flat display)

(``struct`` format ``<4sBBHIIdfff``.) Anything else is malformed: another length, magic or
version, a flag or reserved bit set, a coordinate that is not finite, a sender time that is
not finite. The example in ``crs_study/live/README.md`` (stream 0x12345678, sequence 1, sender
time 2.5 s, (10, -5, 3) mm) is the published byte vector the tests check.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from crs_study.live.errors import PacketError

MAGIC = b"CRSF"
VERSION = 1
_FORMAT = struct.Struct("<4sBBHIIdfff")
#: Bytes of a version-1 packet.
PACKET_SIZE = _FORMAT.size
#: Largest stream id and sequence number (uint32).
MAX_U32 = 0xFFFF_FFFF


@dataclass(frozen=True)
class FingerPacket:
    """One finger position (module docstring); coordinates in mm, in the display's frame
    relative to the recognition area's centre."""

    stream: int
    sequence: int
    sender_time: float
    x_mm: float
    y_mm: float
    z_mm: float

    def __post_init__(self) -> None:
        for name in ("stream", "sequence"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_U32:
                raise PacketError(f"{name}: expected a whole number 0..{MAX_U32}, got {value!r}")
        for name in ("sender_time", "x_mm", "y_mm", "z_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value):
                raise PacketError(f"{name}: expected a finite number, got {value!r}")


def newer(sequence: int, last: int, bits: int = 32) -> bool:
    """Whether ``sequence`` comes after ``last`` in serial-number arithmetic.

    Notes
    -----
    RFC 1982 (Elz & Bush 1996, "Serial Number Arithmetic"), section 3.2, with SERIAL_BITS = 32:
    ``s1 < s2`` when ``s1 < s2 and s2 - s1 < 2^31`` or ``s1 > s2 and s1 - s2 > 2^31``. So
    ``0`` comes after ``2^32 - 1`` (the wrap), and a packet more than 2^31 behind is newer
    again. Two numbers exactly 2^31 apart are not comparable (the RFC leaves them undefined):
    not newer. ``last = -1`` (nothing accepted yet) makes every sequence newer. ``bits``: the
    RFC's SERIAL_BITS (its worked examples use 8).
    """
    if last < 0:
        return True
    half = 1 << (bits - 1)
    return (last < sequence and sequence - last < half) or \
        (last > sequence and last - sequence > half)


def encode_packet(packet: FingerPacket) -> bytes:
    """The 36 bytes of ``packet`` (module docstring). Coordinates are rounded to float32."""
    return _FORMAT.pack(MAGIC, VERSION, 0, 0, packet.stream, packet.sequence,
                        float(packet.sender_time), packet.x_mm, packet.y_mm, packet.z_mm)


def decode_packet(data: bytes) -> FingerPacket:
    """The packet in ``data``; :class:`PacketError` saying what is wrong when it is none."""
    if len(data) != PACKET_SIZE:
        raise PacketError(f"expected {PACKET_SIZE} bytes, got {len(data)}")
    magic, version, flags, reserved, stream, sequence, sent, x, y, z = _FORMAT.unpack(data)
    if magic != MAGIC:
        raise PacketError(f"expected magic {MAGIC!r}, got {magic!r}")
    if version != VERSION:
        raise PacketError(f"expected format version {VERSION}, got {version}")
    if flags or reserved:
        raise PacketError(f"expected flags and reserved bytes 0, got {flags}, {reserved}")
    if not (math.isfinite(sent) and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise PacketError(f"expected finite numbers, got sender time {sent!r}, "
                          f"position ({x!r}, {y!r}, {z!r})")
    return FingerPacket(stream, sequence, sent, x, y, z)
