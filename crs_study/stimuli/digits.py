"""Digit strokes: the ten digits as polylines, and motion along them at constant speed.

The shipped strokes are in ``crs_study/data/digits.toml`` (documented there: unit box, x right,
y up, strokes in drawing order); a protocol may name its own file. Loading is strict: every
problem is a one-line :class:`~crs_study.errors.ProtocolError` naming the file, the line of
the offending key or array element (``my_digits.toml:42: digits.3.strokes[0][5]: ...``), the
key path and the value.

Size: a protocol's ``digit_width_pitch`` x ``digit_height_pitch`` (w x h) is the *average*
bounding box of the digits of the strokes file. Digit k's bounding box in the unit box is
W_k x H_k (the extents of all its stroke points); the file's mean extents are
W = mean_k W_k and H = mean_k H_k (over every digit the file defines: the ten of the shipped
file, whichever of them a protocol shows). :meth:`Digit.scaled` maps
x -> cx + (x - 1/2) w / W and y -> cy + (y - 1/2) h / H, so the drawn digits' bounding boxes
average exactly w x h (the paper's 0.81 x 0.49 pitch are averages over its digits), each
digit keeps its shape and its size relative to the others (a 1 stays narrow), and the
centre of the unit box goes to the placement point. The shipped digits have
W = 0.8913 and H = 0.9958 (:func:`mean_extent`).

Motion: a stroke is a polyline P_0 .. P_m. Its arc-length parameter is the cumulative chord
length s_0 = 0, s_j = s_{j-1} + |P_j - P_{j-1}|, and the point at arc length s is the linear
interpolation between the chord ends that bracket s (:func:`point_at`). At speed v (mm/s) and
frame rate f (frames/s) the bump centre of frame k is at s_k = min(k v / f, L); the stroke's
last frame is the first one that reaches the end (:func:`sample_stroke`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from crs_study._toml import Section, parse_toml
from crs_study._toml_lines import locate, one_line
from crs_study.errors import ConfigError, ProtocolError
from crs_study.paths import data_dir

#: Format number of the strokes file this module reads.
STROKES_FORMAT = 1
#: The names of the symbols a digit strokes file defines.
DIGIT_NAMES = tuple(str(d) for d in range(10))


def shipped_strokes_path() -> Path:
    """The strokes file that ships with the package."""
    return data_dir() / "digits.toml"


@dataclass(frozen=True, eq=False)
class Digit:
    """One digit: its strokes in the unit box (each an (m, 2) read-only array).

    ``mean_extent`` is (W, H), the mean bounding-box width and height of the digits of the
    file this digit came from (module docstring); :meth:`scaled` divides by it.
    """

    value: int
    strokes: tuple[np.ndarray, ...]
    mean_extent: tuple[float, float] = (1.0, 1.0)

    @property
    def extent(self) -> tuple[float, float]:
        """(W_k, H_k): the bounding box of every stroke point, in the unit box."""
        points = np.concatenate(self.strokes)
        return float(np.ptp(points[:, 0])), float(np.ptp(points[:, 1]))

    def scaled(self, width_mm: float, height_mm: float,
               centre_mm: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, ...]:
        """Strokes in millimetres, sized so that the file's digits average ``width_mm`` x
        ``height_mm``: x -> cx + (x - 1/2) w / W, y -> cy + (y - 1/2) h / H."""
        scale = np.array([width_mm / self.mean_extent[0], height_mm / self.mean_extent[1]],
                         dtype=float)
        offset = np.asarray(centre_mm, dtype=float)
        return tuple((s - 0.5) * scale + offset for s in self.strokes)

    def length_mm(self, width_mm: float, height_mm: float) -> float:
        """Total drawn length (sum of stroke arc lengths) at the given size."""
        return float(sum(arc_lengths(s)[-1] for s in self.scaled(width_mm, height_mm)))


def mean_extent(digits: dict[int, Digit]) -> tuple[float, float]:
    """(W, H): the mean over ``digits`` of each digit's bounding-box width and height."""
    extents = np.array([d.extent for d in digits.values()], dtype=float)
    return float(extents[:, 0].mean()), float(extents[:, 1].mean())


def arc_lengths(points: np.ndarray) -> np.ndarray:
    """Cumulative chord length s_j of a polyline (m, 2): s_0 = 0, s_j = s_{j-1} + |dP_j|."""
    points = np.asarray(points, dtype=float)
    chords = np.hypot(*np.diff(points, axis=0).T)
    return np.concatenate([[0.0], np.cumsum(chords)])


def point_at(points: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points (k, 2) at arc lengths ``s`` (k,) along the polyline, clipped to [0, L]."""
    points = np.asarray(points, dtype=float)
    cumulative = arc_lengths(points)
    s = np.clip(np.asarray(s, dtype=float), 0.0, cumulative[-1])
    return np.column_stack([np.interp(s, cumulative, points[:, 0]),
                            np.interp(s, cumulative, points[:, 1])])


def frames_for_stroke(length_mm: float, speed_mm_s: float, frame_rate_hz: float) -> int:
    """Frames that draw a stroke of ``length_mm``: ceil(L f / v) + 1 (first and last point)."""
    steps = length_mm * frame_rate_hz / speed_mm_s
    # Guard against 3.0000000001 from rounding: a stroke exactly k steps long takes k + 1.
    return int(math.ceil(steps - 1e-9)) + 1


def sample_stroke(points_mm: np.ndarray, speed_mm_s: float, frame_rate_hz: float
                  ) -> np.ndarray:
    """Bump centres (n, 2) for one stroke at speed v and frame rate f: s_k = min(k v / f, L)."""
    length = arc_lengths(points_mm)[-1]
    n = frames_for_stroke(length, speed_mm_s, frame_rate_hz)
    s = np.arange(n) * (speed_mm_s / frame_rate_hz)
    return point_at(points_mm, s)


def resample_by_arc_length(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` points equally spaced in arc length along a polyline (ends included)."""
    cumulative = arc_lengths(points)
    return point_at(points, np.linspace(0.0, cumulative[-1], n))


@lru_cache(maxsize=16)
def _load_cached(path: str, mtime_ns: int) -> dict[int, Digit]:
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{path}: cannot read the strokes file: {one_line(exc)}") from None
    data = parse_toml(text, path, ProtocolError)
    try:
        return _parse(data, path, text)
    except ConfigError as exc:
        raise locate(exc, path, text) from None


def load_digits(path: str | Path | None = None) -> dict[int, Digit]:
    """Read a strokes file (the shipped one when ``path`` is None), strictly.

    Returns a dict digit -> :class:`Digit`. Cached per file and modification time. Errors
    name the file and the line: ``PATH:LINE: digits.3.strokes[0][5]: expected ...``.
    """
    path = Path(path) if path is not None else shipped_strokes_path()
    try:
        mtime = path.stat().st_mtime_ns
    except FileNotFoundError:
        raise ProtocolError(f"{path}: no such strokes file") from None
    except OSError as exc:
        raise ProtocolError(f"{path}: cannot read the strokes file: {exc}") from None
    if not path.is_file():
        raise ProtocolError(f"{path}: expected a strokes file, got a directory")
    return _load_cached(str(path), mtime)


def _parse(data: dict, source: str, text: str | None = None) -> dict[int, Digit]:
    root = Section(data, source, error=ProtocolError, keys=("format", "digits"), text=text)
    version = root.integer("format")
    if version != STROKES_FORMAT:
        raise root.fail("format", f"expected {STROKES_FORMAT}, got {version!r}")
    strokes_of = read_strokes(root.table("digits"), _digit_name)
    root.done()
    if not strokes_of:
        raise root.fail("digits", "expected at least one digit, got none")
    digits = {int(k): Digit(int(k), v) for k, v in sorted(strokes_of.items())}
    width, height = mean_extent(digits)
    # The size of a protocol is the mean extent (module docstring): it must not be zero.
    if width <= 0.0 or height <= 0.0:
        flat = "width" if width <= 0.0 else "height"
        raise root.fail("digits", f"expected digits whose mean bounding-box {flat} is > 0 "
                        f"(the protocol's digit size is that mean), got {flat} 0 for digits "
                        f"{sorted(digits)}")
    return {k: Digit(k, d.strokes, (width, height)) for k, d in digits.items()}


def _digit_name(name: str) -> str | None:
    """Why ``name`` names no digit (None when it does)."""
    return None if name in DIGIT_NAMES else f"expected a digit 0 to 9 as the key, got {name!r}"


def read_strokes(table: Section, check_name: Callable[[str], str | None]
                 ) -> dict[str, tuple[np.ndarray, ...]]:
    """The strokes of each symbol of a strokes table: ``[NAME] strokes = [[[x, y], ...], ...]``.

    Generic over the symbols' names (digits here; letters or shapes would do):
    ``check_name`` says why a name is refused, or None. Each stroke is an (m, 2) read-only
    array of at least 2 points in the unit box with a length > 0 (:func:`_parse_stroke`).
    """
    strokes_of: dict[str, tuple[np.ndarray, ...]] = {}
    for name in list(table.data):
        problem = check_name(name)
        if problem is not None:
            raise table.fail(name, problem)
        entry = table.table(name, keys=("strokes",))
        raw_strokes = entry.array("strokes")
        entry.done()
        if not raw_strokes:
            raise entry.fail("strokes", "expected at least one stroke, got []")
        strokes_of[name] = tuple(
            _parse_stroke(stroke, entry, f"strokes[{i}]") for i, stroke in enumerate(raw_strokes)
        )
    table.done()
    return strokes_of


def _parse_stroke(raw: object, entry: Section, key: str) -> np.ndarray:
    if not isinstance(raw, list) or len(raw) < 2:
        raise entry.fail(key, f"expected a list of at least 2 [x, y] points, got {raw!r}")
    points = []
    for j, point in enumerate(raw):
        if (not isinstance(point, list) or len(point) != 2
                or any(isinstance(c, bool) or not isinstance(c, int | float) for c in point)):
            raise entry.fail(f"{key}[{j}]", f"expected [x, y] numbers, got {point!r}")
        if not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in point):
            raise entry.fail(f"{key}[{j}]", f"expected x and y in the unit box [0, 1], "
                             f"got {point!r}")
        points.append((float(point[0]), float(point[1])))
    array = np.array(points)
    if arc_lengths(array)[-1] <= 0.0:
        raise entry.fail(key, f"a stroke must have a length > 0, got all points at {raw[0]!r}")
    array.setflags(write=False)
    return array
