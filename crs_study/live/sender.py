"""Send a finger trace as packets, on a fixed schedule: the stand-in for the VR scene.

Packet k goes at ``start + t_k`` (the trace's own times, or ``k / rate`` after
:meth:`~crs_study.live.trace.FingerTrace.resampled`), on an absolute schedule so delays never
add up; a packet the sender could not send on time goes at once and is counted late. Each run
is one stream (a random id unless given), sequence numbers from ``first_sequence``.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from dataclasses import asdict, dataclass

from crs_study.live.errors import LiveError
from crs_study.live.packet import MAX_U32, FingerPacket, encode_packet
from crs_study.live.trace import FingerTrace

#: A packet sent this much after its time counts as late (s).
LATE_S = 0.002


@dataclass(frozen=True)
class SendReport:
    """What :func:`send_trace` did: packets sent, how long it took, how late the latest was."""

    packets: int
    stream: int
    first_sequence: int
    duration_s: float
    late: int  # packets sent more than LATE_S after their time
    latest_s: float  # the largest delay behind schedule (s)
    stopped: bool  # ``stop`` was set before the end

    def to_json(self) -> dict:
        return asdict(self)


def random_stream() -> int:
    return int.from_bytes(os.urandom(4), "little")


def send_trace(trace: FingerTrace, address: tuple[str, int], stream: int | None = None,
               first_sequence: int = 0, stop: threading.Event | None = None,
               repeat: int = 1) -> SendReport:
    """Send ``trace`` to ``address`` (host, port), ``repeat`` times end to end (module
    docstring); returns a :class:`SendReport`. ``stop`` ends it early."""
    stream = random_stream() if stream is None else stream
    if isinstance(repeat, bool) or not isinstance(repeat, int) or not 1 <= repeat <= 10**6:
        raise LiveError(f"repeat: expected a whole number >= 1, got {repeat!r}")
    try:
        infos = socket.getaddrinfo(address[0], address[1], type=socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise LiveError(f"send address {address[0]}:{address[1]}: {exc}") from None
    family, _, _, _, target = infos[0]
    period = trace.duration_s + (trace.times[1] - trace.times[0] if len(trace) > 1 else 0.0)
    sent = late = 0
    latest = 0.0
    stopped = False
    sequence = first_sequence
    with socket.socket(family, socket.SOCK_DGRAM) as sock:
        start = time.monotonic()
        for lap in range(repeat):
            for t, (x, y, z) in zip(trace.times.tolist(), trace.xyz.tolist(), strict=True):
                due = start + lap * period + t
                while (wait := due - time.monotonic()) > 0:
                    if stop is not None and stop.wait(wait):
                        break
                    if stop is None:
                        time.sleep(wait)
                if stop is not None and stop.is_set():
                    stopped = True
                    break
                now = time.monotonic()
                data = encode_packet(FingerPacket(stream, sequence & MAX_U32, now, x, y, z))
                try:
                    sock.sendto(data, target)
                except OSError as exc:
                    raise LiveError(f"sending to {address[0]}:{address[1]}: {exc}") from None
                behind = time.monotonic() - due
                latest = max(latest, behind)
                late += int(behind > LATE_S)
                sent += 1
                sequence += 1
            if stopped:
                break
        duration = time.monotonic() - start
    return SendReport(sent, stream, first_sequence, duration, late, latest, stopped)
