"""A live session on a virtual clock: the position error at landing as a deterministic result.

:func:`simulate` runs the session's own code (:meth:`LiveSession.take`, :meth:`~LiveSession.
show`, :meth:`~LiveSession.finish`: packet acceptance, prediction, rendering, the write policy)
on the simulated device (``sim://``: its virtual boards decode the frames' bytes at 9600 baud
and model the servos at 0.08 s/cm) with a :class:`~crs_study.clock.VirtualClock`. Packet k
arrives at ``t_k + network_s``; a frame is handed over as soon as the wire can take one
(``lead_s`` before it frees), as the real loop does, and none waits for the machine. So the
result is the link's physics and the predictor, the same on any machine: the figures of
``crs-study bench live`` and assertions in tests. The real loop adds the machine's own delays
(measured there: ``position_error`` of a session's result).
"""

from __future__ import annotations

from dataclasses import dataclass

from crs_study.clock import VirtualClock
from crs_study.device import open_device
from crs_study.geometry.layout import Layout, load_layout
from crs_study.live.landing import LandingErrors, landing_errors
from crs_study.live.link import Datagram
from crs_study.live.packet import FingerPacket, encode_packet
from crs_study.live.predict import PredictConfig
from crs_study.live.session import LiveConfig, LiveSession
from crs_study.live.trace import FingerTrace

#: The virtual clock's start (s): any time; frames are measured from the trace's start.
CLOCK_START_S = 1000.0
#: The trace starts this long after the display's neutral pose was handed over (s).
SETTLE_S = 0.5


@dataclass(frozen=True)
class SimulatedRun:
    """A simulated session: its result (:class:`~crs_study.live.result.LiveResult`) and the
    errors against the true trace (:class:`~crs_study.live.landing.LandingErrors`)."""

    result: object
    errors: LandingErrors


def simulate(trace: FingerTrace, predict: PredictConfig | None = None,
             truth: FingerTrace | None = None, layout: str | Layout = "crs2d",
             condition: str = "crs", network_s: float = 0.0) -> SimulatedRun:
    """Send ``trace`` to a session on ``sim://`` in virtual time (module docstring); errors
    against ``truth`` (default: the trace itself; a jittered trace's clean one)."""
    layout = load_layout(layout) if isinstance(layout, str) else layout
    clock = VirtualClock(CLOCK_START_S)
    device = open_device("sim://", layout, clock, record=True)
    config = LiveConfig(listen="127.0.0.1:0", condition=condition,
                        predict=predict or PredictConfig())
    session = LiveSession(device, config)
    session.start()
    finished = []

    def until(t: float) -> None:
        """Show every frame due before ``t``, then move the clock to ``t``."""
        while session.newest is not None and session.next_frame_at <= t:
            clock.sleep_until(session.next_frame_at)
            session.show()
            collect()
        clock.sleep_until(t)
        collect()

    def collect() -> None:
        frames = session.tap.poll(clock.now())
        session.finish(frames)
        finished.extend(f for f in frames if f.kind == "finger")

    t0 = clock.now() + SETTLE_S + network_s
    for k, (t, (x, y, z)) in enumerate(zip(trace.times.tolist(), trace.xyz.tolist(),
                                           strict=True)):
        arrival = t0 + t
        until(arrival)
        data = encode_packet(FingerPacket(1, k, t, x, y, z))
        session.take(Datagram(data, arrival, arrival, ("simulated", 0)))
        until(arrival)
    until(clock.now() + 1.0)
    session.stopped_by = "end of trace"
    session.ended = clock.now()
    device.close()
    return SimulatedRun(session.result(), landing_errors(finished, truth or trace, t0))
