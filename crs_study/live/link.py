"""The UDP end of the link: an address, a listening socket, datagrams with their arrival time.

Arrival time
    A datagram's arrival is the time the kernel received it (``SO_TIMESTAMPNS`` on Linux),
    not the time this process read it: a packet that waited in the socket while a frame was
    being rendered still counts its wait. The kernel stamps ``CLOCK_REALTIME``; it is moved
    onto ``time.monotonic`` (the clock of every other time here) by the offset between the two
    read right after the datagrams (microseconds apart). Where no stamp comes (another
    system), the time the datagram was read stands in, and :attr:`Listener.kernel_stamps`
    says so.
"""

from __future__ import annotations

import errno
import math
import socket
import struct
import sys
import time
from dataclasses import dataclass

from crs_study.live.errors import LiveError

#: Linux (asm-generic) ``SO_TIMESTAMPNS``; the control message type is the same number.
SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@ll")
#: Largest datagram read: a finger packet is 36 bytes; longer ones are read whole and dropped.
MAX_DATAGRAM = 2048
#: Datagrams read in one go at most (the rest wait for the next round).
MAX_BATCH = 256


def parse_address(text: str, what: str = "address") -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6) as (host, port); one-line LiveError otherwise."""
    host, sep, port = str(text).rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise LiveError(f"{what}: expected HOST:PORT like 127.0.0.1:5005, got {text!r}")
    return host, int(port)


@dataclass(frozen=True)
class Datagram:
    """One datagram: its bytes, when it arrived and was read (``time.monotonic`` s), whence."""

    data: bytes
    arrival: float
    read_at: float
    sender: tuple


class Listener:
    """A UDP socket bound to (host, port), read without blocking (module docstring)."""

    def __init__(self, host: str, port: int) -> None:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise LiveError(f"listen address {host}:{port}: {exc}") from None
        family, _, _, _, address = infos[0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self.sock.bind(address)
        except OSError as exc:
            self.sock.close()
            reason = ("in use by another program" if exc.errno == errno.EADDRINUSE
                      else exc.strerror or str(exc))
            raise LiveError(f"cannot listen on {host}:{port}: {reason}") from None
        self.sock.setblocking(False)
        self.kernel_stamps = False
        if sys.platform.startswith("linux"):
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
                self.kernel_stamps = True
            except OSError:
                pass
        self.address = self.sock.getsockname()[:2]

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self, limit: int = MAX_BATCH) -> list[Datagram]:
        """Every datagram waiting (at most ``limit``), oldest first; [] when none."""
        raw = []
        for _ in range(min(limit, MAX_BATCH)):
            try:
                raw.append(self.sock.recvmsg(MAX_DATAGRAM, 64))
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # e.g. ICMP errors reported on a UDP socket: not ours
                if exc.errno in (errno.ECONNREFUSED, errno.EHOSTUNREACH):
                    continue
                raise LiveError(f"receiving on {self.address}: {exc}") from None
        if not raw:
            return []
        read_at = time.monotonic()
        offset = time.time() - time.monotonic()
        out = []
        for data, ancillary, _, sender in raw:
            arrival = read_at
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS \
                        and len(payload) >= _TIMESPEC.size:
                    seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
                    stamped = seconds + nanoseconds * 1e-9 - offset
                    # a stamp from the future or minutes old is not one to trust
                    if math.isfinite(stamped) and read_at - 60.0 < stamped <= read_at + 1e-3:
                        arrival = min(stamped, read_at)
            out.append(Datagram(data, arrival, read_at, sender))
        return out

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> Listener:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
