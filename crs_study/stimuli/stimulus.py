"""Stimuli: a symbol's strokes turned into the bump's path over time, frame by frame.

A trial's stimulus is the raised-cosine bump of Eq. 7 (:class:`~crs_study.stimuli.targets.Bump`)
whose centre moves along the symbol's strokes at the protocol's stroke speed, sampled at its
frame rate. Frame k is shown at t_k = k / f from onset. The timeline of a symbol:

1. ``start_hold_s``: the bump rests at the first point of the first stroke;
2. each stroke: the centre moves at constant speed along the stroke's arc length
   (:func:`crs_study.stimuli.strokes.sample_stroke`, s_k = min(k v / f, L));
3. between strokes (pen lift): ``stroke_pause_s`` of flat display (height 0, at least one
   frame), during which the centre moves to the next stroke's first point;
4. ``end_hold_s``: the bump rests at the last point. Then the runner returns to neutral.

What is drawn is a :class:`StimulusSpec` (a protocol's ``[stimulus]`` table, checked on
construction): the symbols of a stimulus set (:mod:`crs_study.stimuli.sets`; digits unless
the protocol names another set), their size, the bump, its speed. The stimulus of a symbol
is the same in every trial (no per-trial randomness), so its path is made once per (symbol,
spec, pitch, placement) (:func:`stimulus_for`) and its setpoints are rendered once per
stimulus, condition and device by the one cache of rendered frames,
:func:`crs_study.rendering.frames.render_frames` (the rendering stage, a layer above this
one). A protocol with ``[levels]`` has one stimulus spec per level
(:meth:`crs_study.protocol.Protocol.stimulus_at`), and the spec is part of every cache key.
The checks of a protocol against its device are in :mod:`crs_study.protocol.feasibility`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal, Protocol, get_args

import numpy as np
from scipy.spatial import ConvexHull

from crs_study._toml import number_problem
from crs_study.errors import ProtocolError
from crs_study.geometry.layout import Layout
from crs_study.stimuli.sets import DEFAULT_SET, load_stimulus_set
from crs_study.stimuli.strokes import Symbol, sample_stroke
from crs_study.stimuli.symbol_set import StimulusSet
from crs_study.stimuli.targets import Bump

Placement = Literal["centre", "offset"]
#: Where the symbols are drawn: the display centre, or that plus ``offset_mm``.
PLACEMENTS: tuple[str, ...] = get_args(Placement)
#: Slowest stroke speed accepted (mm/s): a 60 mm symbol then takes a minute.
MIN_STROKE_SPEED_MM_S = 1.0
#: Slowest frame rate a protocol may ask for (frames/s). Below one frame a second a moving
#: bump is a slide show, and the frame count of a stroke (L f / v) loses meaning as f -> 0
#: (hypothesis found f = 5e-324).
MIN_FRAME_RATE_HZ = 1.0
#: The range of each number of ``[stimulus]``: field -> (minimum, maximum, minimum excluded).
#: The size fields are spelled by the set in a protocol file (``digit_height_pitch``).
NUMBER_RANGES: dict[str, tuple[float, float, bool]] = {
    "symbol_height_pitch": (0.01, 20.0, False),
    "symbol_width_pitch": (0.01, 20.0, False),
    "bump_diameter_mm": (0.0, 1000.0, True),
    "bump_height_mm": (0.0, 100.0, True),
    "stroke_speed_mm_s": (MIN_STROKE_SPEED_MM_S, 1000.0, False),
    "frame_rate_hz": (MIN_FRAME_RATE_HZ, 1000.0, False),
    "stroke_pause_s": (0.0, 10.0, False),
    "start_hold_s": (0.0, 10.0, False),
    "end_hold_s": (0.0, 10.0, False),
}
#: Longest time a symbol may take to draw (s); longer is surely a typo in the protocol.
MAX_DRAWING_S = 120.0


@dataclass(frozen=True)
class StimulusSpec:
    """The ``[stimulus]`` table: what is drawn, how big, how fast. Lengths in mm, times in s.

    ``symbols`` are those of the stimulus set ``set_name`` (a shipped set's name, or a set
    file's resolved path; :func:`crs_study.stimuli.sets.load_stimulus_set`) that trials
    show; ``strokes_file`` (the digit set only) replaces its strokes. Sizes are in pixel
    pitches (the set's mean bounding box, :mod:`crs_study.stimuli.strokes`). In a protocol
    file the keys naming symbols are spelled by the set (:meth:`file_key`: ``digits``,
    ``digit_height_pitch`` for the digit set). Every field is checked on construction
    (ranges :data:`NUMBER_RANGES`): a bad value is a
    :class:`~crs_study.errors.ProtocolError` whose ``key_path`` is ``stimulus.<key>``, in
    Python (``dataclasses.replace``) as in a protocol file. Numbers are stored as floats, the
    symbols and the offset as tuples.
    """

    symbols: tuple[Symbol, ...]
    strokes_file: str | None  # resolved path, None for the set's own strokes
    symbol_height_pitch: float
    symbol_width_pitch: float
    bump_diameter_mm: float
    bump_height_mm: float
    stroke_speed_mm_s: float
    placement: Placement
    offset_mm: tuple[float, float]
    frame_rate_hz: float
    stroke_pause_s: float
    start_hold_s: float
    end_hold_s: float
    set_name: str = DEFAULT_SET

    def __post_init__(self) -> None:
        if not isinstance(self.set_name, str) or not self.set_name.strip():
            raise ProtocolError(f"expected a stimulus set, got {self.set_name!r}",
                                key_path="stimulus.set")
        alphabet = load_stimulus_set(self.set_name)  # its symbols; strokes come later

        def fail(key: str, reason: str) -> ProtocolError:
            return ProtocolError(reason, key_path=f"stimulus.{alphabet.spelled(key)}")

        _check_symbols(self.symbols, alphabet, fail)
        if self.strokes_file is not None and (not isinstance(self.strokes_file, str)
                                              or not self.strokes_file.strip()):
            raise fail("strokes_file", f"expected a strokes file, got {self.strokes_file!r}")
        numbers: dict[str, Any] = {}
        for key, (low, high, exclusive) in NUMBER_RANGES.items():
            value = getattr(self, key)
            problem = number_problem(value, minimum=low, maximum=high,
                                     exclusive_minimum=exclusive)
            if problem:
                raise fail(key, problem)
            numbers[key] = float(value)
            if key == "stroke_speed_mm_s":  # the file's order: placement, offset, then rate
                self._check_placement(fail)
        set_field = object.__setattr__
        set_field(self, "symbols", tuple(self.symbols))
        set_field(self, "offset_mm", tuple(float(c) for c in self.offset_mm))
        for key, value in numbers.items():
            set_field(self, key, value)

    def _check_placement(self, fail) -> None:
        if self.placement not in PLACEMENTS:
            raise fail("placement", f"expected one of {list(PLACEMENTS)}, got "
                       f"{self.placement!r}")
        offset = self.offset_mm
        if (not isinstance(offset, list | tuple) or len(offset) != 2
                or any(number_problem(c) for c in offset)):
            raise fail("offset_mm", f"expected [x, y] in mm, got {offset!r}")
        if self.placement != "offset" and tuple(offset) != (0.0, 0.0):
            raise fail("offset_mm", f"only used with placement = \"offset\", got placement = "
                       f"{self.placement!r}")

    @property
    def symbol_set(self) -> StimulusSet:
        """The stimulus set drawn, with the protocol's own strokes when it names a file."""
        return load_stimulus_set(self.set_name, self.strokes_file)

    def file_key(self, field: str) -> str:
        """The protocol key of ``field`` as the set spells it (``symbol_height_pitch`` ->
        ``digit_height_pitch`` for the digit set; ``set_name`` -> ``set``)."""
        return "set" if field == "set_name" else load_stimulus_set(self.set_name).spelled(field)


def _check_symbols(symbols: Any, alphabet: StimulusSet, fail) -> None:
    """The symbols shown: at least 2, distinct, each of the set (its own type: an int for a
    digit, a string for a letter)."""
    noun, plural = alphabet.noun, alphabet.plural
    if not isinstance(symbols, list | tuple):
        raise fail("symbols", f"expected an array, got {symbols!r}")
    known = set(alphabet.symbols)
    for i, s in enumerate(symbols):
        if isinstance(s, bool) or not isinstance(s, int | str) or s not in known \
                or type(s) is not type(alphabet.symbols[0]):
            raise fail(f"symbols[{i}]", f"expected a {noun} {alphabet.describe()}, got {s!r}")
    if len(set(symbols)) != len(symbols):
        raise fail("symbols", f"a {noun} appears twice in {list(symbols)!r}")
    if len(symbols) < 2:
        raise fail("symbols", f"expected at least 2 {plural} to choose from, got "
                   f"{list(symbols)!r}")


class StimulusSource(Protocol):
    """What :func:`make_stimulus` draws from: the stimulus spec of each level."""

    def stimulus_at(self, level: float | None) -> StimulusSpec: ...


@dataclass(frozen=True, eq=False)
class Stimulus:
    """The bump's path for one symbol: frame k is ``target(k)`` shown at ``frame_times[k]``.

    Attributes
    ----------
    symbol : the symbol drawn.
    frame_times : (n,) s from onset, k / f.
    centres_mm : (n, 2) bump centre per frame.
    heights_mm : (n,) bump height per frame (0 while the pen is lifted between strokes).
    stroke_index : (n,) the stroke a frame belongs to, -1 during a pen lift.
    diameter_mm : the bump's diameter l.
    duration_s : n / f, from the first frame's onset to the end of the last frame's period.
    key : identifies the stimulus for caches (symbol and every parameter that shapes it).
    """

    symbol: Symbol
    frame_times: np.ndarray
    centres_mm: np.ndarray
    heights_mm: np.ndarray
    stroke_index: np.ndarray
    diameter_mm: float
    duration_s: float
    key: tuple

    @property
    def n_frames(self) -> int:
        return len(self.frame_times)

    def target(self, k: int) -> Bump:
        """The bump of frame ``k``."""
        x, y = self.centres_mm[k]
        return Bump((float(x), float(y)), self.diameter_mm, float(self.heights_mm[k]))

    @property
    def targets(self) -> list[Bump]:
        return [self.target(k) for k in range(self.n_frames)]

    @property
    def drawn(self) -> np.ndarray:
        """Boolean mask (n,) of frames where the bump is up."""
        return self.heights_mm > 0


def display_centre(layout: Layout) -> tuple[float, float]:
    """Centre of the display: the centroid of the pixel positions (the centre pixel on crs2d)."""
    c = np.mean(layout.pixel_xy, axis=0)
    return float(c[0]), float(c[1])


def placement_centre(spec: StimulusSpec, layout: Layout) -> tuple[float, float]:
    """Where the centre of the symbol's box goes: the display centre, plus the offset."""
    cx, cy = display_centre(layout)
    return cx + spec.offset_mm[0], cy + spec.offset_mm[1]


def make_stimulus(protocol: StimulusSource, layout: Layout, symbol: Symbol,
                  level: float | None = None) -> Stimulus:
    """The stimulus of ``symbol`` at ``level`` (None: no [levels]) on ``layout`` (cached).

    ``protocol`` is a :class:`~crs_study.protocol.Protocol` or anything else with a
    ``stimulus_at(level)`` giving the :class:`StimulusSpec` of that level."""
    spec = protocol.stimulus_at(level)
    return stimulus_for(spec, layout.pitch_mm, placement_centre(spec, layout), symbol)


@lru_cache(maxsize=256)
def stimulus_for(spec: StimulusSpec, pitch_mm: float, centre_mm: tuple[float, float],
                 symbol: Symbol) -> Stimulus:
    """The stimulus of ``symbol`` for a stimulus spec, pitch and placement (module docstring)."""
    symbol_set = spec.symbol_set
    glyph = symbol_set.glyph(symbol)
    f = spec.frame_rate_hz
    width = spec.symbol_width_pitch * pitch_mm
    height = spec.symbol_height_pitch * pitch_mm
    strokes = glyph.scaled(width, height, centre_mm)
    drawing_s = glyph.length_mm(width, height) / spec.stroke_speed_mm_s
    if drawing_s > MAX_DRAWING_S:
        raise ProtocolError(f"{symbol_set.noun} {symbol} would take {drawing_s:.0f} s to draw; "
                            f"expected at most {MAX_DRAWING_S:g} s, got "
                            f"{spec.stroke_speed_mm_s!r} mm/s",
                            key_path="stimulus.stroke_speed_mm_s")
    centres: list[np.ndarray] = []
    heights: list[np.ndarray] = []
    index: list[np.ndarray] = []

    def add(points: np.ndarray, h: float, stroke: int) -> None:
        centres.append(points)
        heights.append(np.full(len(points), h))
        index.append(np.full(len(points), stroke, dtype=int))

    hold = int(round(spec.start_hold_s * f))
    add(np.repeat(strokes[0][:1], hold, axis=0), spec.bump_height_mm, 0)
    for i, stroke in enumerate(strokes):
        if i > 0:
            lift = max(1, int(round(spec.stroke_pause_s * f)))
            add(np.repeat(stroke[:1], lift, axis=0), 0.0, -1)
        add(sample_stroke(stroke, spec.stroke_speed_mm_s, f), spec.bump_height_mm, i)
    hold = int(round(spec.end_hold_s * f))
    add(np.repeat(strokes[-1][-1:], hold, axis=0), spec.bump_height_mm, len(strokes) - 1)

    centre_array = np.concatenate(centres)
    n = len(centre_array)
    arrays = (np.arange(n) / f, centre_array, np.concatenate(heights), np.concatenate(index))
    for a in arrays:
        a.setflags(write=False)
    key = (symbol, spec, float(pitch_mm), tuple(centre_mm))
    return Stimulus(symbol, *arrays, diameter_mm=spec.bump_diameter_mm, duration_s=n / f,
                    key=key)


# --------------------------------------------------------------------------------------------
# Geometry against the display


def inside_convex_hull(points: np.ndarray, polygon_xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Which points lie in the convex hull of ``polygon_xy``, and the smallest margin (mm).

    The margin is min over points and hull edges of the signed distance to the edge line
    (positive inside); a negative margin means some point lies outside.
    """
    hull = ConvexHull(polygon_xy)
    # hull.equations: rows (a, b, c) with a x + b y + c <= 0 inside, (a, b) unit normals.
    signed = -(points @ hull.equations[:, :2].T + hull.equations[:, 2])
    margins = signed.min(axis=1)
    return margins >= -1e-9, float(margins.min())
