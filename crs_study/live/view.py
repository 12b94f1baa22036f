"""The live terminal view: packets, frames, frame rate and latency, redrawn in place.

:class:`TerminalView` is called with the running :class:`~crs_study.live.session.LiveSession`
a few times a second and redraws a block of lines (ANSI: cursor up, clear to the end), so the
terminal shows one up-to-date screen. Latency percentiles are over the last
:data:`~crs_study.live.session.VIEW_WINDOW` counted frames; counts are since the start.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def screen(session, window: int = 300) -> list[str]:
    """The lines of the view for ``session`` now."""
    p, f = session.packets, session.frames
    now = time.monotonic()
    elapsed = now - session.started
    state = {"waiting": "waiting for packets", "live": "live",
             "silent": f"silent > {session.config.silence_s:g} s: display flat"}[session.state]
    if session.state == "live" and session.stream is not None:
        state += f" (stream {session.stream:08x})"
    delays = session.log.delays(last=window)
    rate = len(session.log.columns["done"])
    recent = session.log.columns["done"].array()[-window:]
    if len(recent) > 1 and recent[-1] > recent[0]:
        rate_text = f"{(len(recent) - 1) / (recent[-1] - recent[0]):5.1f} frames/s"
    else:
        rate_text = "    - frames/s"
    share = delays["software_share"]
    software = delays["software"]
    lines = [
        f"crs-study live  {session.listen_address} -> {getattr(session.device, 'url', '')}  "
        f"{session.config.condition} on {session.layout.name}  {elapsed:7.1f} s",
        f"state     {state}",
        f"packets   {p.received} received  {p.shown} shown  {p.superseded} superseded  "
        f"dropped: {p.stale} stale  {p.malformed} malformed  {p.other_stream} other sender  "
        f"{p.out_of_area} out of area",
        f"frames    {f.written} written  {rate_text}  {f.unchanged} unchanged  "
        f"{f.flat + f.silence} flat  {f.lost} lost  {f.clamped} clamped  bytes "
        + " ".join(f"{c.name}:{n}" for c, n in zip(session.layout.controllers, f.bytes,
                                                    strict=True)),
        f"latency   last {min(rate, window)} frames, ms   median    p95    p99    max",
        f"  arrival -> last byte on the wire   {delays['wire'].describe()}",
        f"  arrival -> servos in place         {delays['in_place'].describe()}",
        f"  display behind the newest packet   {delays['newest'].describe()}",
        f"  frame wire time                    {delays['frame_wire'].describe()}",
        "software  " + (f"{software.median * 1e3:.3f} ms a packet, {share.median:.2%} of its "
                        f"frame's wire time (median)" if software.n else "-"),
        f"timing    {session.tap.source if session.tap else '-'}; Ctrl-C stops "
        f"(neutral pose, ports released)",
    ]
    return lines


class TerminalView:
    """Redraws :func:`screen` on ``stream`` (default stdout), in place on a terminal."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stdout
        self.drawn = 0

    def __call__(self, session) -> None:
        lines = screen(session)
        out = ""
        if self.drawn:
            out += f"\x1b[{self.drawn}F\x1b[J"  # to the first line drawn, clear below
        out += "\n".join(line[:200] for line in lines) + "\n"
        self.stream.write(out)
        self.stream.flush()
        self.drawn = len(lines)
