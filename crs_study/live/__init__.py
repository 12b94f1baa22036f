"""Live mode: the paper's VR link. Finger packets over UDP in, the bump of Eq. 7 out.

The paper's system (Wang, Meng & Chen 2025, Fig. 5 and Methods) sends the fingertip's
position relative to the display, (x_f, y_f, z_f), from a Unity scene over UDP; the computer
renders the raised cosine of Eq. 7 under the finger and drives the two LSC-24 boards. This
package is that link, with its latency measured as the paper's figure is. The packet format
and a Unity C# sender are in ``crs_study/live/README.md``.

Modules (each imports only those above it)::

    errors    LiveError, PacketError
    packet    the finger packet, version 1: FingerPacket, encode_packet, decode_packet
    area      the recognition area; a finger to a Bump (or a flat display)
    link      the UDP socket, kernel arrival stamps
    latency   median / 95th / 99th percentile summaries
    trace     finger traces: a digit written with our strokes, a straight stroke, a held
              (jittered) finger; resampling
    sender    send a trace as packets at a set rate (``crs-study live-send``)
    record    a session recorded to JSON lines, read back as a trace (it replays)
    predict   where the finger will be when a frame lands: the 1€ filter, bounded extrapolation
    landing   position error at landing, lead, overshoot at stroke ends; FingerHistory
    boards    when frames reached the boards: the virtual boards' own record, or the host's
    result    LiveResult: counts, latency, ``to_json()``, ``to_frame()``
    session   LiveConfig, LiveSession, serve(): the loop, newest packet wins, the safe stop
    view      the terminal view (``crs-study live``)
    simulate  a session on a virtual clock: the position error as a deterministic result

``serve("sim://", config=LiveConfig(listen="127.0.0.1:5005"))`` runs a session and returns a
:class:`LiveResult`.
"""

from crs_study.live.area import RecognitionArea
from crs_study.live.errors import LiveError, PacketError
from crs_study.live.packet import FingerPacket, decode_packet, encode_packet
from crs_study.live.predict import PredictConfig
from crs_study.live.record import read_trace
from crs_study.live.result import LiveResult
from crs_study.live.sender import SendReport, send_trace
from crs_study.live.session import LiveConfig, LiveSession, serve
from crs_study.live.trace import (
    FingerTrace,
    digit_trace,
    hold_trace,
    stroke_trace,
    symbol_trace,
)

__all__ = [
    "FingerPacket", "FingerTrace", "LiveConfig", "LiveError", "LiveResult", "LiveSession",
    "PacketError", "PredictConfig", "RecognitionArea", "SendReport", "decode_packet", "digit_trace",
    "encode_packet", "hold_trace", "read_trace", "send_trace", "serve", "stroke_trace",
    "symbol_trace",
]
