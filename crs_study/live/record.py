"""Recording a live session to a file that replays, and reading it back as a finger trace.

JSON lines, one object a line, written as things happen (line-buffered, so a session killed
hard keeps everything up to its last line). Times are seconds from the session's start
(``t0``, ``time.monotonic``)::

    {"format": "crs-study live recording", "version": 1, "layout": ..., "condition": ...,
     "device": ..., "listen": ..., "started": UTC ISO time, "config": {... "predict": {the
     predictor's parameters}}, "predictor": its description}
    {"packet": {"t": arrival, "read": read time, "from": "host:port", "status": ...,
                "stream", "seq", "sender_time", "x", "y", "z"}}   status: accepted, stale,
               other_stream, malformed (then "reason" and the first 64 bytes as "hex")
    {"frame": {"index", "kind", "seq", "t": handed over, "host_done", "bytes": [per board],
               "clamped", "shown": [x, y, z] rendered (predicted) or null, "for": the time
               that position was predicted for, "setpoints": [mm, actuator order]}}
    {"landed": {"index", "done", "in_place", "lost"}}   when a frame's bytes had arrived
    {"end": the session's result (LiveResult.to_json())}

:func:`read_trace` gives the accepted packets' positions at their arrival times: what
``crs-study live-send --replay FILE`` sends again. A damaged or hand-edited file is a one-line
LiveError naming its line (a coordinate no packet can carry, a line nested too deeply or longer
than :data:`MAX_LINE_CHARS`, times going backwards), never a crash; long pauses are shortened
(:func:`replay_times`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from crs_study.live.errors import LiveError
from crs_study.live.trace import MAX_COORDINATE_MM, FingerTrace, check_rate

FORMAT = "crs-study live recording"
VERSION = 1
#: Longest line read (characters): a frame line of a large display is a few kilobytes.
MAX_LINE_CHARS = 1 << 20
#: Longest pause replayed as recorded (s); longer ones are shortened to it. Longer than the
#: live session's default silence timeout (0.5 s), so a recorded silence flattens on replay too.
MAX_GAP_S = 2.0
#: Packets read in one batch may carry times this far out of order (s).
TIME_SLACK_S = 1e-3


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
            "shown": None if frame.shown is None else [round(float(v), 4) for v in frame.shown],
            "for": _clean(frame.rendered_for - self.t0),
            "setpoints": [round(float(v), 5) for v in frame.setpoints]}})

    def landed(self, frame) -> None:
        self._line({"landed": {"index": frame.index, "done": _clean(frame.done_at - self.t0),
                               "in_place": _clean(frame.in_place_at - self.t0),
                               "lost": frame.lost}})

    def end(self, result: dict) -> None:
        self._line({"end": result})

    def close(self) -> None:
        self.file.close()


def _lines(path: Path) -> Iterator[tuple[int, dict]]:
    """(line number, object) of every line of the recording at ``path``, read one at a time;
    the header is checked first. A torn last line (no newline: a session killed mid-line) ends
    the file; any other line that is not a JSON object is a LiveError naming it."""
    try:
        handle = path.open(encoding="utf-8")
    except FileNotFoundError:
        raise LiveError(f"{path}: no such recording") from None
    except OSError as exc:
        raise LiveError(f"{path}: cannot read the recording: {exc.strerror or exc}") from None
    with handle:
        number = 0
        while True:
            try:
                line = handle.readline(MAX_LINE_CHARS + 1)
            except (OSError, UnicodeDecodeError) as exc:
                raise LiveError(f"{path}:{number + 1}: cannot read the recording: {exc}"
                                ) from None
            if not line:
                if number == 0:
                    raise LiveError(f"{path}:1: expected a {FORMAT!r} header line")
                return
            number += 1
            if len(line) > MAX_LINE_CHARS:
                raise LiveError(f"{path}:{number}: a line longer than {MAX_LINE_CHARS} "
                                f"characters is not a recording's")
            if not line.strip():
                continue
            try:
                entry = json.loads(line)
            except json.JSONDecodeError as exc:
                if number > 1 and not line.endswith("\n"):
                    return  # a session killed mid-line: keep what came before
                raise LiveError(f"{path}:{number}: not a JSON line ({exc.msg})") from None
            except ValueError as exc:  # e.g. an integer of more digits than Python reads
                raise LiveError(f"{path}:{number}: not a recording's line ({exc})") from None
            except RecursionError:
                raise LiveError(f"{path}:{number}: not a recording's line (nested too deeply)"
                                ) from None
            if not isinstance(entry, dict):
                raise LiveError(f"{path}:{number}: expected a JSON object, got {line[:40]!r}")
            if number == 1:
                if entry.get("format") != FORMAT:
                    raise LiveError(f"{path}:1: expected a {FORMAT!r} header line")
                if entry.get("version") != VERSION:
                    raise LiveError(f"{path}:1: expected recording version {VERSION}, got "
                                    f"{entry.get('version')!r}")
            yield number, entry


def read_recording(path: str | Path) -> tuple[dict, list[dict]]:
    """The header and the other lines of a recording; LiveError naming the line when the
    file is not one."""
    entries = [entry for _, entry in _lines(Path(path))]
    return entries[0], entries[1:]


def _coordinate(path: Path, number: int, packet: dict, key: str) -> float:
    value = packet.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not abs(value) <= MAX_COORDINATE_MM:  # NaN too; ints of any size compare
        what = "time" if key == "t" else f"{key} (mm)"
        raise LiveError(f"{path}:{number}: an accepted packet's {what} must be a finite number"
                        f"{'' if key == 't' else ' a packet can carry (float32)'}, got "
                        f"{value!r:.40}")
    return float(value)


def replay_times(times: np.ndarray, lines: list[int], path: Path) -> tuple[np.ndarray, int]:
    """Send times (s from the first packet) for a recording's arrival ``times``, and how many
    pauses were shortened.

    Packets read in one batch share a time (no kernel stamp) or come a little out of order: a
    step back of up to :data:`TIME_SLACK_S` is kept in order, and a run of equal times is
    spread evenly up to the next time (the batch arrived over that interval), so it does not go
    as one burst. A pause longer than :data:`MAX_GAP_S` (the sender away, a clock jump) is
    shortened to it. Times going back further, or one time for every packet, are a LiveError:
    ``--rate`` replays such a recording at a fixed rate.
    """
    back = np.flatnonzero(np.diff(times) < -TIME_SLACK_S)
    if back.size:
        k = int(back[0])
        raise LiveError(f"{path}:{lines[k + 1]}: packet times go backwards ({times[k + 1]:.6g} "
                        f"s after {times[k]:.6g} s); replay it at a fixed rate with --rate")
    t = np.asarray(times, dtype=float) - times[0]
    t = np.maximum.accumulate(t)
    if len(t) > 1 and t[-1] - t[0] <= 0.0:
        raise LiveError(f"{path}: all {len(t)} accepted packets have one time; replay it at a "
                        f"fixed rate with --rate")
    first = np.searchsorted(t, t, side="left")
    after = np.searchsorted(t, t, side="right")
    steps = np.diff(np.unique(t))
    typical = float(np.median(steps)) if steps.size else 0.0
    end = np.where(after < len(t), t[np.minimum(after, len(t) - 1)],
                   t + typical * (after - first))
    t = t[first] + (np.arange(len(t)) - first) / (after - first) * (end - t[first])
    gaps = np.diff(t)
    long = gaps > MAX_GAP_S
    t = np.concatenate([[0.0], np.cumsum(np.minimum(gaps, MAX_GAP_S))])
    return t, int(long.sum())


def read_trace(path: str | Path, rate_hz: float | None = None) -> FingerTrace:
    """The accepted packets of a recording as a trace, timed by their arrivals
    (:func:`replay_times`), or with ``rate_hz`` one every 1 / rate_hz s in their order (the
    recorded times not used). Read line by line: a recording of any length needs memory for
    its accepted positions only."""
    path = Path(path)
    rows: list[tuple[float, float, float, float]] = []
    lines: list[int] = []
    for number, entry in _lines(path):
        packet = entry.get("packet")
        if isinstance(packet, dict) and packet.get("status") == "accepted":
            rows.append(tuple(_coordinate(path, number, packet, k) for k in ("t", "x", "y", "z")))
            lines.append(number)
    if not rows:
        raise LiveError(f"{path}: no accepted packet to replay")
    data = np.array(rows)
    name = f"recording {path.name}"
    if rate_hz is not None:
        rate = check_rate(rate_hz)
        return FingerTrace(np.arange(len(data)) / rate, data[:, 1:], f"{name} at {rate:g}/s")
    times, shortened = replay_times(data[:, 0], lines, path)
    if shortened:
        name += f" ({shortened} pause{'s' * (shortened > 1)} over {MAX_GAP_S:g} s shortened)"
    return FingerTrace(times, data[:, 1:], name)
