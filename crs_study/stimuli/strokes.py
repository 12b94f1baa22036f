"""Strokes: a symbol as polylines in a unit box, its size, and motion along it at constant speed.

Generic over the stimulus set (digits, letters, a lab's own shapes): a :class:`Glyph` is one
symbol's strokes, read from a strokes table (:func:`read_strokes`: ``[NAME] strokes = [[[x,
y], ...], ...]``, unit box, x right, y up, strokes in drawing order). The sets that use them
are :mod:`crs_study.stimuli.symbol_set` (any set, from a set file) and
:mod:`crs_study.stimuli.digits` (the digit set).

Size: a protocol's width x height (w x h, in pixel pitches) is the *average* bounding box of
the symbols of the set. Symbol k's bounding box in the unit box is W_k x H_k (the extents of
all its stroke points); the set's mean extents are W = mean_k W_k and H = mean_k H_k (over
every symbol the set defines, whichever of them a protocol shows). :meth:`Glyph.scaled` maps
x -> cx + (x - 1/2) w / W and y -> cy + (y - 1/2) h / H, so the drawn symbols' bounding boxes
average exactly w x h (the paper's 0.81 x 0.49 pitch are averages over its digits), each
symbol keeps its shape and its size relative to the others (a 1 stays narrow), and the
centre of the unit box goes to the placement point.

Motion: a stroke is a polyline P_0 .. P_m. Its arc-length parameter is the cumulative chord
length s_0 = 0, s_j = s_{j-1} + |P_j - P_{j-1}|, and the point at arc length s is the linear
interpolation between the chord ends that bracket s (:func:`point_at`). At speed v (mm/s) and
frame rate f (frames/s) the bump centre of frame k is at s_k = min(k v / f, L); the stroke's
last frame is the first one that reaches the end (:func:`sample_stroke`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass

import numpy as np

from crs_study._toml import Section

#: A symbol of a stimulus set: an int for the digit set (as every dataset records it), the
#: label as written in the set file (a string) for every other set.
Symbol = Hashable


@dataclass(frozen=True, eq=False)
class Glyph:
    """One symbol: its strokes in the unit box (each an (m, 2) read-only array).

    ``mean_extent`` is (W, H), the mean bounding-box width and height of the symbols of the
    set this glyph belongs to (module docstring); :meth:`scaled` divides by it.
    """

    symbol: Symbol
    strokes: tuple[np.ndarray, ...]
    mean_extent: tuple[float, float] = (1.0, 1.0)

    @property
    def extent(self) -> tuple[float, float]:
        """(W_k, H_k): the bounding box of every stroke point, in the unit box."""
        points = np.concatenate(self.strokes)
        return float(np.ptp(points[:, 0])), float(np.ptp(points[:, 1]))

    def scaled(self, width_mm: float, height_mm: float,
               centre_mm: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, ...]:
        """Strokes in millimetres, sized so that the set's symbols average ``width_mm`` x
        ``height_mm``: x -> cx + (x - 1/2) w / W, y -> cy + (y - 1/2) h / H."""
        scale = np.array([width_mm / self.mean_extent[0], height_mm / self.mean_extent[1]],
                         dtype=float)
        offset = np.asarray(centre_mm, dtype=float)
        return tuple((s - 0.5) * scale + offset for s in self.strokes)

    def length_mm(self, width_mm: float, height_mm: float) -> float:
        """Total drawn length (sum of stroke arc lengths) at the given size."""
        return float(sum(arc_lengths(s)[-1] for s in self.scaled(width_mm, height_mm)))


def mean_extent(glyphs: Mapping[Symbol, Glyph]) -> tuple[float, float]:
    """(W, H): the mean over ``glyphs`` of each glyph's bounding-box width and height."""
    extents = np.array([g.extent for g in glyphs.values()], dtype=float)
    return float(extents[:, 0].mean()), float(extents[:, 1].mean())


def sized_glyphs(strokes_of: Mapping[Symbol, tuple[np.ndarray, ...]], root: Section,
                 key: str, noun: str) -> dict[Symbol, Glyph]:
    """Glyphs of ``strokes_of`` (in its order) carrying their set's mean extent, which must not
    be zero (a protocol's size is that mean); an error names ``root``'s ``key`` (the strokes
    table), ``noun`` names one symbol."""
    glyphs = {s: Glyph(s, strokes) for s, strokes in strokes_of.items()}
    width, height = mean_extent(glyphs)
    if width <= 0.0 or height <= 0.0:
        flat = "width" if width <= 0.0 else "height"
        raise root.fail(key, f"expected {noun}s whose mean bounding-box {flat} is > 0 "
                        f"(the protocol's {noun} size is that mean), got {flat} 0 for "
                        f"{noun}s {list(glyphs)}")
    return {s: Glyph(s, g.strokes, (width, height)) for s, g in glyphs.items()}


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


def read_strokes(table: Section, check_name: Callable[[str], str | None],
                 extra_keys: tuple[str, ...] = (),
                 read_extra: Callable[[str, Section], None] | None = None,
                 ) -> dict[str, tuple[np.ndarray, ...]]:
    """The strokes of each symbol of a strokes table: ``[NAME] strokes = [[[x, y], ...], ...]``.

    Generic over the symbols' names: ``check_name`` says why a name is refused, or None.
    ``extra_keys`` are the other keys a symbol's table may hold (a set file's ``key``),
    taken by ``read_extra(name, entry)``. Each stroke is an (m, 2) read-only array of at
    least 2 points in the unit box with a length > 0.
    """
    strokes_of: dict[str, tuple[np.ndarray, ...]] = {}
    for name in list(table.data):
        problem = check_name(name)
        if problem is not None:
            raise table.fail(name, problem)
        entry = table.table(name, keys=("strokes", *extra_keys))
        raw_strokes = entry.array("strokes")
        if read_extra is not None:
            read_extra(name, entry)
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
