"""Recording a live session to a file that replays, and reading it back as a finger trace.

JSON lines, one object a line, written as things happen (line-buffered, so a session killed
hard keeps everything up to its last line). Times are seconds from the session's start
(``t0``, ``time.monotonic``)::

    {"format": "crs-study live recording", "version": 1, "layout": ..., "condition": ...,
     "device": ..., "listen": ..., "started": UTC ISO time, "config": {...}}
    {"packet": {"t": arrival, "read": read time, "from": "host:port", "status": ...,
                "stream", "seq", "sender_time", "x", "y", "z"}}   status: accepted, stale,
               other_stream, malformed (then "reason" and the first 64 bytes as "hex")
    {"frame": {"index", "kind", "seq", "t": handed over, "host_done", "bytes": [per board],
               "clamped", "setpoints": [mm, actuator order]}}
    {"landed": {"index", "done", "in_place", "lost"}}   when a frame's bytes had arrived
    {"end": the session's result (LiveResult.to_json())}

:func:`read_trace` gives the accepted packets' positions at their arrival times: what
``crs-study live-send --replay FILE`` sends again.
"""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from crs_study.live.errors import LiveError
from crs_study.live.trace import FingerTrace

FORMAT = "crs-study live recording"
VERSION = 1


def _clean(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), 7)


class Recorder:
    """Writes a recording (module docstring); refuses to overwrite an existing file."""

    def __init__(self, path: str | Path, header: dict[str, Any], t0: float) -> None:
        self.path = Path(path)
        self.t0 = t0
        try:
            self.file = self.path.open("x", encoding="utf-8", buffering=1)
        except FileExistsError:
            raise LiveError(f"{self.path}: already exists; choose another recording file "
                            f"(nothing is overwritten)") from None
        except OSError as exc:
            raise LiveError(f"{self.path}: cannot write the recording: {exc.strerror or exc}"
                            ) from None
        started = datetime.now(UTC).isoformat(timespec="seconds")
        self._line({"format": FORMAT, "version": VERSION, "started": started, **header})

    def _line(self, obj: dict) -> None:
        self.file.write(json.dumps(obj, separators=(",", ":")) + "\n")

    def packet(self, datagram, status: str, packet=None, reason: str | None = None) -> None:
        entry: dict[str, Any] = {"t": _clean(datagram.arrival - self.t0),
                                 "read": _clean(datagram.read_at - self.t0),
                                 "from": ":".join(map(str, datagram.sender[:2])),
                                 "status": status}
        if packet is not None:
            entry.update(stream=packet.stream, seq=packet.sequence,
                         sender_time=packet.sender_time, x=packet.x_mm, y=packet.y_mm,
                         z=packet.z_mm)
        if reason is not None:
            entry.update(reason=reason, hex=datagram.data[:64].hex())
        self._line({"packet": entry})

    def frame(self, frame, clamped: bool) -> None:
        self._line({"frame": {
            "index": frame.index, "kind": frame.kind, "seq": frame.sequence,
            "t": _clean(frame.handed_at - self.t0), "host_done": _clean(frame.host_done - self.t0),
            "bytes": list(frame.bytes_sent), "clamped": clamped,
            "setpoints": [round(float(v), 5) for v in frame.setpoints]}})

    def landed(self, frame) -> None:
        self._line({"landed": {"index": frame.index, "done": _clean(frame.done_at - self.t0),
                               "in_place": _clean(frame.in_place_at - self.t0),
                               "lost": frame.lost}})

    def end(self, result: dict) -> None:
        self._line({"end": result})

    def close(self) -> None:
        self.file.close()


def read_recording(path: str | Path) -> tuple[dict, list[dict]]:
    """The header and the other lines of a recording; LiveError naming the line when the
    file is not one."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise LiveError(f"{path}: no such recording") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LiveError(f"{path}: cannot read the recording: {exc}") from None
    entries = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
        except json.JSONDecodeError as exc:
            if number == len(lines):  # a session killed mid-line: keep what came before
                break
            raise LiveError(f"{path}:{number}: not a JSON line ({exc.msg})") from None
        if not isinstance(entry, dict):
            raise LiveError(f"{path}:{number}: expected a JSON object, got {line[:40]!r}")
        entries.append(entry)
    if not entries or entries[0].get("format") != FORMAT:
        raise LiveError(f"{path}:1: expected a {FORMAT!r} header line")
    if entries[0].get("version") != VERSION:
        raise LiveError(f"{path}:1: expected recording version {VERSION}, got "
                        f"{entries[0].get('version')!r}")
    return entries[0], entries[1:]


def read_trace(path: str | Path) -> FingerTrace:
    """The accepted packets of a recording as a trace, timed by their arrivals."""
    _, entries = read_recording(path)
    rows = []
    for entry in entries:
        packet = entry.get("packet")
        if isinstance(packet, dict) and packet.get("status") == "accepted":
            try:
                rows.append([float(packet[k]) for k in ("t", "x", "y", "z")])
            except (KeyError, TypeError, ValueError):
                raise LiveError(f"{path}: an accepted packet without t, x, y, z: "
                                f"{packet!r}") from None
    if not rows:
        raise LiveError(f"{path}: no accepted packet to replay")
    data = np.array(rows)
    times = data[:, 0] - data[0, 0]
    # packets read in one batch may share a stamp; keep their order a microsecond apart
    for k in range(1, len(times)):
        times[k] = max(times[k], times[k - 1] + 1e-6)
    return FingerTrace(times, data[:, 1:], f"recording {Path(path).name}")
