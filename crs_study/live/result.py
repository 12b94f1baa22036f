"""What a live session did: packet and frame counts, latency figures, per-frame rows.

Latency, per packet a frame carried (the paper's device latency, 75 ms: Wang, Meng & Chen
2025, Methods), measured at three points of the path from the finger to the skin:

``handed``   arrival (the kernel's stamp) -> the frame carrying it handed to the device
``wire``     arrival -> that frame's last byte arrived at its board (the later board)
``in_place`` arrival -> every servo at that frame's position (virtual boards only)
``newest``   every accepted packet, carried or superseded: arrival -> the first frame carrying
             it *or a newer one* has its last byte at the boards: how far the display lags a
             finger at any moment (newest wins, so most packets are never shown themselves)
``lead``     the time a frame's position was predicted for minus when its servos were in
             place (virtual boards) or its last byte arrived: > 0, the bump ahead of the finger
``software`` decode + render + hand-over of a carried packet: CPU time of the session's
             thread (``time.thread_time``: the work, not the waits of a loaded machine), and
             ``frame_wire``, the frame's own time on the wire (its busiest board's bytes at 10
             bits a byte), the figure it is compared with: ``software_share``, their ratio per
             frame (a fraction, not a time).

Per frame also the **position error** (mm): the distance between the bump's centre and the
finger when the frame's servos were in place, the finger's position then interpolated between
the packets that arrived around it (:class:`~crs_study.live.landing.FingerHistory`): what the
finger meets, as well as the link can know it.

Only ``finger`` frames that put bytes on the wire, all of them arrived, count: a frame whose
channels were all unchanged carries its packet with no wire time (counted ``unchanged``), a
write lost on the way (replaced, garbled) has no landing (counted ``lost``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from crs_study.live.latency import Series, Summary

#: Columns of :meth:`LiveResult.to_frame`, one row per counted frame.
FRAME_COLUMNS = ("frame", "sequence", "arrival", "handed", "done", "in_place", "software_s",
                 "frame_wire_s", "host_error_s", "position_error_mm", "lead_s")


@dataclass
class PacketCounts:
    """Datagrams by what became of them."""

    received: int = 0  # every datagram
    accepted: int = 0  # valid, newer than the last, from the stream being shown
    shown: int = 0  # accepted and carried by a frame
    superseded: int = 0  # accepted, replaced by a newer one before a frame could carry it
    stale: int = 0  # dropped: not newer than the last accepted (late, reordered, repeated)
    malformed: int = 0  # dropped: not a version-1 finger packet
    other_stream: int = 0  # dropped: from another sender while one is being shown
    out_of_area: int = 0  # accepted, outside the recognition area: flattens the display


@dataclass
class FrameCounts:
    """Frames handed to the device, by kind and fate."""

    handed: int = 0
    finger: int = 0
    flat: int = 0  # out of area or not pressing
    silence: int = 0  # flattened after the silence timeout
    written: int = 0  # put bytes on the wire
    unchanged: int = 0  # every channel within the dead-band: nothing written
    lost: int = 0  # a write that never arrived whole (replaced, garbled, port gone)
    clamped: int = 0  # the renderer clipped a setpoint or capped a beam's feed
    bytes: list[int] = field(default_factory=list)  # per board


class LatencyLog:
    """The per-packet delays of a session (module docstring), as growing columns."""

    def __init__(self) -> None:
        self.columns = {name: Series() for name in FRAME_COLUMNS}
        self.newest = Series()

    def add(self, frame, frame_wire_s: float, position_error_mm: float = float("nan")) -> None:
        c = self.columns
        c["frame"].add(frame.index)
        c["sequence"].add(frame.sequence)
        c["arrival"].add(frame.arrivals[0])
        c["handed"].add(frame.handed_at)
        c["done"].add(frame.done_at)
        c["in_place"].add(frame.in_place_at)
        c["software_s"].add(frame.software_s)
        c["frame_wire_s"].add(frame_wire_s)
        c["host_error_s"].add(frame.done_at - frame.host_done)
        c["position_error_mm"].add(position_error_mm)
        landed = frame.in_place_at if frame.in_place_at == frame.in_place_at else frame.done_at
        c["lead_s"].add(frame.rendered_for - landed)

    def delays(self, last: int | None = None) -> dict[str, Summary]:
        c = {k: s.array() for k, s in self.columns.items()}
        cut = slice(-last, None) if last else slice(None)
        arrival = c["arrival"][cut]
        software = c["software_s"][cut]
        wire = c["frame_wire_s"][cut]
        with np.errstate(divide="ignore", invalid="ignore"):
            share = software / wire
        return {
            "handed": Summary.of(c["handed"][cut] - arrival),
            "wire": Summary.of(c["done"][cut] - arrival),
            "in_place": Summary.of(c["in_place"][cut] - arrival),
            "newest": self.newest.summary(last),
            "software": Summary.of(software),
            "frame_wire": Summary.of(wire),
            "software_share": Summary.of(share),
            "host_error": Summary.of(c["host_error_s"][cut]),
            "position_error": Summary.of(c["position_error_mm"][cut]),
            "lead": Summary.of(c["lead_s"][cut]),
        }


@dataclass
class LiveResult:
    """A live session's outcome (:func:`crs_study.live.serve`). ``to_json()`` for machines,
    ``to_frame()`` for the per-frame rows (:data:`FRAME_COLUMNS`; times ``time.monotonic``)."""

    device: str
    layout: str
    condition: str
    listen: str
    area: str
    source: str  # "boards" (virtual boards' own record) or "host model"
    duration_s: float
    stopped_by: str
    faults: list[str]
    packets: PacketCounts
    frames: FrameCounts
    silences: int
    unmatched_board_frames: int
    kernel_stamps: bool
    log: LatencyLog = field(repr=False)
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """No device fault ended the session."""
        return not self.stopped_by.startswith("device fault")

    @property
    def latency(self) -> dict[str, Summary]:
        return self.log.delays()

    @property
    def frame_rate_hz(self) -> float:
        return self.frames.written / self.duration_s if self.duration_s > 0 else 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "device": self.device, "layout": self.layout, "condition": self.condition,
            "listen": self.listen, "area": self.area, "latency_source": self.source,
            "arrival_stamps": "kernel" if self.kernel_stamps else "read",
            "duration_s": round(self.duration_s, 4), "stopped_by": self.stopped_by,
            "faults": list(self.faults), "silences": self.silences,
            "packets": asdict(self.packets), "frames": asdict(self.frames),
            "frames_written_per_s": round(self.frame_rate_hz, 3),
            "unmatched_board_frames": self.unmatched_board_frames,
            "latency": {k: v.to_json() for k, v in self.latency.items()
                        if k not in ("software_share", "position_error")},
            "position_error_mm": self.latency["position_error"].to_json(scale=1.0),
            "software_share": self.latency["software_share"].to_json(scale=1.0),
            "config": self.config,
        }

    def to_frame(self):
        """One row per counted frame (module docstring), columns :data:`FRAME_COLUMNS`."""
        import pandas as pd

        data = {k: s.array() for k, s in self.log.columns.items()}
        frame = pd.DataFrame(data, columns=list(FRAME_COLUMNS))
        return frame.astype({"frame": "int64", "sequence": "int64"})
