"""The live terminal view: packets, frames, frame rate, latency, the predictor and the position
error, and a text map of the pixels' heights, redrawn in place.

:class:`TerminalView` is called with the running :class:`~crs_study.live.session.LiveSession`
a few times a second and redraws a block of 21 lines of at most 79 characters (ANSI: cursor
up, clear to the end), so an 80 x 24 terminal shows one up-to-date screen without wrapping or
scrolling. Latency percentiles are over the last
:data:`~crs_study.live.session.VIEW_WINDOW` counted frames; counts are since the start.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

import numpy as np

#: Widest line of the view: fits an 80-column terminal without wrapping (a wrapped line breaks
#: the in-place redraw, which moves the cursor up by lines drawn).
WIDTH = 79


def screen(session, window: int = 300) -> list[str]:
    """The lines of the view for ``session`` now, each at most :data:`WIDTH` characters."""
    p, f = session.packets, session.frames
    elapsed = time.monotonic() - session.started
    state = {"waiting": "waiting for packets", "live": "live",
             "silent": f"silent > {session.config.silence_s:g} s: display flat"}[session.state]
    if session.state == "live" and session.stream is not None:
        state += f" (stream {session.stream:08x})"
    delays = session.log.delays(last=window)
    counted = len(session.log.columns["done"])
    recent = session.log.columns["done"].array()[-window:]
    if len(recent) > 1 and recent[-1] > recent[0]:
        rate_text = f"{(len(recent) - 1) / (recent[-1] - recent[0]):.1f}/s"
    else:
        rate_text = "-/s"
    software = delays["software"]
    device = str(getattr(session.device, "url", ""))
    lines = [
        f"crs-study live  {session.listen_address} -> {device[:24]}  "
        f"{session.config.condition} on {session.layout.name}  {elapsed:.1f} s",
        f"state     {state}",
        f"packets   {p.received} received  {p.shown} shown  {p.superseded} superseded  "
        f"{p.out_of_area} out of area",
        f"dropped   {p.stale} stale  {p.malformed} malformed  {p.other_stream} other sender",
        f"frames    {f.written} written {rate_text}  {f.unchanged} unchanged  "
        f"{f.flat + f.silence} flat  {f.lost} lost  {f.clamped} clamped",
        "bytes     " + " ".join(f"{c.name}:{n}" for c, n in zip(session.layout.controllers,
                                                               f.bytes, strict=True)),
        f"latency, ms, last {min(counted, window):<4d}        median    p95    p99    max",
        f"  arrival -> last byte on wire   {delays['wire'].describe()}",
        f"  arrival -> servos in place     {delays['in_place'].describe()}",
        f"  display behind newest packet   {delays['newest'].describe()}",
        f"  frame wire time                {delays['frame_wire'].describe()}",
        "software  " + (f"{software.median * 1e3:.3f} ms a packet, "
                        f"{delays['software_share'].median:.2%} of its frame's wire time"
                        if software.n else "-"),
        "predict   " + _predictor(session),
        "error     " + _error(delays["position_error"]),
        "heights   mm, each pixel where it sits (. = flat)",
        *_height_map(session),
        f"timing    {session.tap.source if session.tap else '-'}; Ctrl-C stops (neutral, "
        f"ports released)",
    ]
    return [line[:WIDTH] for line in lines]


def _predictor(session) -> str:
    config = session.config.predict
    if not config.on:
        return "off: each frame shows the newest packet as it came"
    state = session.predictor.state
    if not state:
        return "1€ filter + velocity, late-bound: no frame yet"
    return (f"1€ + velocity: {state.get('speed_mm_s', 0.0):5.0f} mm/s, "
            f"{state['horizon_ms']:3.0f} ms ahead, step {state['step_mm']:.1f} mm"
            + (f" (capped at {config.max_extrapolation_mm:g})" if state["capped"] else ""))


def _error(summary) -> str:
    if not summary.n:
        return "bump to finger at landing: - (no frame on a pressing finger yet)"
    return (f"bump to finger at landing: median {summary.median:.1f} mm, "
            f"p95 {summary.p95:.1f} mm, max {summary.max:.1f} mm")


def _height_map(session, height: int = 5) -> list[str]:
    """The pixels' commanded heights (whole mm, one digit; '.' for flat) at their places,
    +y up: a text map of the display the last frame asked for."""
    layout = session.layout
    pixels = [a for a in layout.actuators if a.kind == "pixel"]
    xy = layout.pixel_xy
    values = session.timing.last
    span = np.ptp(xy, axis=0)
    half = layout.pitch_mm / 2.0
    cols = np.round((xy[:, 0] - xy[:, 0].min()) / half).astype(int) * 2
    rows = (np.round((xy[:, 1].max() - xy[:, 1]) / (span[1] / (height - 1))).astype(int)
            if span[1] > 0 else np.zeros(len(xy), dtype=int))
    grid = [[" "] * (int(cols.max()) + 1) for _ in range(int(rows.max()) + 1)]
    for pixel, r, c in zip(pixels, rows, cols, strict=True):
        mm = float(values[pixel.index])
        grid[r][c] = "." if mm < 0.5 else str(min(9, int(round(mm))))
    return ["          " + "".join(row).rstrip() for row in grid]


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
        out += "\n".join(lines) + "\n"
        self.stream.write(out)
        self.stream.flush()
        self.drawn = len(lines)
