"""Stimuli: a digit's strokes turned into the bump's path over time, frame by frame.

A trial's stimulus is the raised-cosine bump of Eq. 7 (:class:`~crs_study.targets.Bump`)
whose centre moves along the digit's strokes at the protocol's stroke speed, sampled at its
frame rate. Frame k is shown at t_k = k / f from onset. The timeline of a digit:

1. ``start_hold_s``: the bump rests at the first point of the first stroke;
2. each stroke: the centre moves at constant speed along the stroke's arc length
   (:func:`crs_study.digits.sample_stroke`, s_k = min(k v / f, L));
3. between strokes (pen lift): ``stroke_pause_s`` of flat display (height 0, at least one
   frame), during which the centre moves to the next stroke's first point;
4. ``end_hold_s``: the bump rests at the last point. Then the runner returns to neutral.

The stimulus of a digit is the same in every trial (no per-trial randomness), so its
setpoints are rendered once per (digit, level, condition, device) and cached
(:func:`render_frames`): a protocol with ``[levels]`` has one stimulus spec per level
(:meth:`crs_study.protocol.Protocol.stimulus_at`), and the spec is part of every cache key.
:func:`device_limits` renders every digit in every condition with ``policy="error"`` to
check a protocol against its device.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from crs_study.digits import load_digits, sample_stroke
from crs_study.errors import ProtocolError, RenderError
from crs_study.targets import Bump

if TYPE_CHECKING:  # pragma: no cover
    from crs_study.layout import Layout
    from crs_study.protocol import Protocol, StimulusSpec
    from crs_study.render import Renderer


#: Longest time a digit may take to draw (s); longer is surely a typo in the protocol.
MAX_DRAWING_S = 120.0


@dataclass(frozen=True, eq=False)
class Stimulus:
    """The bump's path for one digit: frame k is ``target(k)`` shown at ``frame_times[k]``.

    Attributes
    ----------
    digit : the digit drawn.
    frame_times : (n,) s from onset, k / f.
    centres_mm : (n, 2) bump centre per frame.
    heights_mm : (n,) bump height per frame (0 while the pen is lifted between strokes).
    stroke_index : (n,) the stroke a frame belongs to, -1 during a pen lift.
    diameter_mm : the bump's diameter l.
    duration_s : n / f, from the first frame's onset to the end of the last frame's period.
    key : identifies the stimulus for caches (digit and every parameter that shapes it).
    """

    digit: int
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
    """Where the centre of the digit's box goes: the display centre, plus the offset."""
    cx, cy = display_centre(layout)
    return cx + spec.offset_mm[0], cy + spec.offset_mm[1]


def make_stimulus(protocol: Protocol, layout: Layout, digit: int,
                  level: float | None = None) -> Stimulus:
    """The stimulus of ``digit`` at ``level`` (None: no [levels]) on ``layout`` (cached)."""
    spec = protocol.stimulus_at(level)
    return stimulus_for(spec, layout.pitch_mm, placement_centre(spec, layout), digit)


@lru_cache(maxsize=256)
def stimulus_for(spec: StimulusSpec, pitch_mm: float, centre_mm: tuple[float, float],
                 digit: int) -> Stimulus:
    """The stimulus of ``digit`` for a stimulus spec, pitch and placement (module docstring)."""
    digits = load_digits(spec.strokes_file)
    if digit not in digits:
        raise ProtocolError(f"stimulus.digits: digit {digit!r} has no strokes in "
                            f"{spec.strokes_file or 'the shipped digits.toml'}")
    f = spec.frame_rate_hz
    width = spec.digit_width_pitch * pitch_mm
    height = spec.digit_height_pitch * pitch_mm
    strokes = digits[digit].scaled(width, height, centre_mm)
    drawing_s = digits[digit].length_mm(width, height) / spec.stroke_speed_mm_s
    if drawing_s > MAX_DRAWING_S:
        raise ProtocolError(f"stimulus.stroke_speed_mm_s: digit {digit} would take "
                            f"{drawing_s:.0f} s to draw; expected at most {MAX_DRAWING_S:g} s, "
                            f"got {spec.stroke_speed_mm_s!r} mm/s")
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
    key = (digit, spec, float(pitch_mm), tuple(centre_mm))
    return Stimulus(digit, *arrays, diameter_mm=spec.bump_diameter_mm, duration_s=n / f, key=key)


# --------------------------------------------------------------------------------------------
# Rendering cache

_RENDERED: OrderedDict[tuple, np.ndarray] = OrderedDict()
_RENDERED_MAX = 512


def layout_key(layout: Layout) -> tuple:
    """A hashable fingerprint of everything in a layout that shapes rendered setpoints."""
    return (layout.name, layout.source, layout.pixel_xy.tobytes(), layout.beams,
            layout.travel_mm, layout.boundary_travel_mm, layout.n_actuators)


def render_frames(stimulus: Stimulus, renderer: Renderer) -> np.ndarray:
    """Setpoints (n, n_actuators) of every frame, rendered once per stimulus, device and
    condition and then served from a cache (read-only array)."""
    key = (stimulus.key, layout_key(renderer.layout), renderer.condition, renderer.policy)
    frames = _RENDERED.get(key)
    if frames is not None:
        _RENDERED.move_to_end(key)
        return frames
    frames = np.array([renderer.render(stimulus.target(k)).setpoints
                       for k in range(stimulus.n_frames)])
    frames.setflags(write=False)
    _RENDERED[key] = frames
    if len(_RENDERED) > _RENDERED_MAX:
        _RENDERED.popitem(last=False)
    return frames


# --------------------------------------------------------------------------------------------
# Device checks


def inside_convex_hull(points: np.ndarray, polygon_xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Which points lie in the convex hull of ``polygon_xy``, and the smallest margin (mm).

    The margin is min over points and hull edges of the signed distance to the edge line
    (positive inside); a negative margin means some point lies outside.
    """
    from scipy.spatial import ConvexHull

    hull = ConvexHull(polygon_xy)
    # hull.equations: rows (a, b, c) with a x + b y + c <= 0 inside, (a, b) unit normals.
    signed = -(points @ hull.equations[:, :2].T + hull.equations[:, 2])
    margins = signed.min(axis=1)
    return margins >= -1e-9, float(margins.min())


def collapse_delta(layout: Layout) -> float:
    """The no-collapse number of Eq. 4 for a device (inf when the skin has no stiffness)."""
    from crs_study.quality.mechanics import layout_delta

    return layout_delta(layout)


def device_limits(spec: StimulusSpec, conditions: tuple[str, ...], layout: Layout
                  ) -> list[str]:
    """Check a stimulus against a device for every condition; one line per check passed.

    Raises :class:`~crs_study.errors.ProtocolError` whose message starts with the protocol
    key at fault (``stimulus.bump_height_mm: ...``). Cached per (spec, conditions, device).
    """
    return list(_device_limits(spec, conditions, layout_key(layout), _LayoutBox(layout)))


class _LayoutBox:
    """Carries a layout through lru_cache without hashing it (the key is layout_key)."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout

    def __hash__(self) -> int:
        return 0

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _LayoutBox)


@lru_cache(maxsize=64)
def _device_limits(spec: StimulusSpec, conditions: tuple[str, ...], key: tuple,
                   box: _LayoutBox) -> tuple[str, ...]:
    from crs_study.device.base import full_frame_rate_hz, full_frame_wire_time_s
    from crs_study.quality.mechanics import stimulus_limits
    from crs_study.render import Renderer

    layout = box.layout
    passed: list[str] = []
    if layout.lattice != "hex":
        raise ProtocolError(f"study.device: digits need a 2D display, got {layout.name!r} "
                            f"with a {layout.lattice!r} lattice")
    limits = stimulus_limits(layout, Bump((0.0, 0.0), spec.bump_diameter_mm,
                                          spec.bump_height_mm))
    problems = limits.problems()
    if "height" in problems:
        raise ProtocolError(f"stimulus.bump_height_mm: expected at most the pixel travel "
                            f"{limits.travel:g} mm, got {spec.bump_height_mm!r}")
    passed.append(f"bump height {limits.height:g} mm <= pixel travel {limits.travel:g} mm")

    wire_rate = full_frame_rate_hz(layout)
    if spec.frame_rate_hz > wire_rate * (1 + 1e-9):
        raise ProtocolError(
            f"stimulus.frame_rate_hz: expected at most {wire_rate:.2f} frames/s (a full frame "
            f"takes {full_frame_wire_time_s(layout) * 1e3:.1f} ms on the wire at 9600 baud), "
            f"got {spec.frame_rate_hz!r}")
    passed.append(f"frame rate {spec.frame_rate_hz:g}/s <= {wire_rate:.2f}/s (every channel "
                  "of the busiest controller in every frame)")

    centre = placement_centre(spec, layout)
    stimuli = [stimulus_for(spec, layout.pitch_mm, centre, d) for d in spec.digits]
    path = np.concatenate([s.centres_mm[s.drawn] for s in stimuli])
    inside, margin = inside_convex_hull(path, layout.pixel_xy)
    if not inside.all():
        worst = path[np.argmin(inside)]
        key_name = "stimulus.offset_mm" if spec.placement == "offset" else \
            "stimulus.digit_height_pitch"
        raise ProtocolError(
            f"{key_name}: the bump centre leaves the pixel area (by {-margin:.1f} mm at "
            f"({worst[0]:.1f}, {worst[1]:.1f}) mm); expected the digit inside the display")
    passed.append(f"bump centre path inside the pixel area (margin {margin:.1f} mm)")

    beams = [c for c in conditions if c != "pixel-only"]
    if beams:
        if "curvature" in problems:
            raise ProtocolError(f"stimulus.bump_height_mm: {problems['curvature']}, got "
                                f"{spec.bump_height_mm!r}")
        passed.append(f"curvature {limits.curvature:.4f}/mm <= yield "
                      f"{limits.yield_curvature:.4f}/mm")
        delta = collapse_delta(layout)
        if delta < 1.0:
            raise ProtocolError(f"conditions.names: the beams collapse on this device "
                                f"(Eq. 4: Delta = {delta:.2f} < 1); got conditions {beams!r}")
        passed.append(f"no collapse: Delta = {delta:.2f} >= 1 (Eq. 4)")

    for condition in conditions:
        renderer = Renderer(layout, condition, policy="error")
        peak_feed = 0.0
        for stim in stimuli:
            try:
                frames = render_frames(stim, renderer)
            except RenderError as exc:
                raise ProtocolError(f"stimulus.bump_height_mm: digit {stim.digit} cannot be "
                                    f"shown: {exc}") from None
            if layout.boundary_actuators:
                feeds = frames[:, layout.n_pixels:]
                peak_feed = max(peak_feed, float(feeds.max()))
        if condition != "pixel-only":
            passed.append(f"{condition}: every frame within travel (largest boundary feed "
                          f"{peak_feed:.2f} mm <= {layout.boundary_travel_mm:g} mm)")
        else:
            passed.append(f"{condition}: every frame within travel")
    return tuple(passed)
