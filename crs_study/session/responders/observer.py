"""A simulated participant who feels the displayed surface and names the closest symbol.

The perceptual observer (:class:`PerceptualObserver`) answers a trial from what a hand on the
display could sense, never from the true symbol (of any stimulus set: digits, letters, ...):

1. **Surface.** Each sensed frame's displayed setpoints go through the display model the
   trial's condition names (:attr:`crs_study.rendering.Condition.display_model`, built by
   :func:`crs_study.display.get_model`): ``pixel-only`` meets the pixel tips under the
   stretched fabric of the paper (spandex sewn to every pixel; Wang, Meng & Chen 2025,
   Methods), a tent between the pixels: the ``linear`` model. (``nearest``, the paper's
   pixel-only theory, is a staircase that a fabric never shows.) ``crs`` mounts the skeleton:
   the compressed ``beam`` network. The options ``pixel_model`` and ``skeleton_model`` replace
   the model of every condition on the pixels alone, or with the beams driven. The surface is
   evaluated on a square grid (``grid_spacing_mm``) over the sensing window
   (``sense_radius_mm`` around the symbol's placement).
2. **Skin.** Receptor noise (white, ``noise_mm`` standard deviation, in mm of indentation) is
   added and the result is blurred by a Gaussian of ``skin_blur_mm`` (the skin's spatial
   spread): sensed = G * (z + e). G * z is noise-free and cached per frame; G * e is drawn
   fresh in every trial.
3. **Peak.** Frames whose sensed maximum is below ``detect_mm`` are flat (the pen lifted).
   Elsewhere the peak is the centroid of the part of the sensed surface above
   ``peak_fraction`` of its maximum (a soft argmax: sub-grid, and between two equal pixels
   it lands between them, as a finger would judge it).
4. **Decision.** The peak path (active frames in order) and each symbol's template (the bump
   centre path of that symbol under the protocol, drawn frames only: the set's strokes as
   the protocol sizes and moves them) are resampled to
   ``path_points`` points at equal fractions of their duration and centred on their means;
   the distance d_k is the root-mean-square gap (mm). The choice is drawn from
   p_k = (1 - lapse) softmax(-d_k / T) + lapse / n (Luce choice with lapses), with the
   participant's own T = temperature_mm exp(ability_sd z), z ~ N(0, 1) drawn from the seed.
5. **Response time** from onset: the stimulus duration plus a lognormal decision time,
   ln t = ln(rt_median_s) + rt_uncertainty * H + rt_sigma * z, with H the entropy of p over
   ln n (0 certain, 1 guessing): uncertain decisions are slower, errors slower on average.
   A response past the time limit (from offset) becomes a time-out.

**Participants** differ in two ways, each a standard normal drawn once from the seed: their
skill, ``T exp(ability_sd z)``, and how much the skeleton helps them, a factor ``exp(+-
benefit_sd w / 2)`` on the temperature, ``-`` on the pixels alone and ``+`` with the skeleton.
``benefit_sd = 0.25`` is chosen so that people differ in their CRS benefit about as much as
in their overall skill: on a 24-participant dry-run of the shipped protocol the maximal GLMM
estimates a by-participant CRS slope SD of 0.47 on the logit scale beside an intercept SD of
0.38. That is the normal case in within-participant studies, the case a model with random
intercepts alone gets wrong (its p-value far too small); 0 gives everyone the same benefit.

**Levels** (protocols with ``[levels]``). The templates are per level: the template of symbol
k at a trial's level is the bump path of k drawn at that level (the observer knows how big
and how fast the symbols of a trial are, as a participant soon learns, but never which one).
Distances stay in mm, so nothing is rescaled: a bigger symbol spreads its templates further
apart while the sensed peak's noise (receptor noise, pixel quantisation) stays the same in
mm, which makes it easier to identify (8 simulated participants on
protocols/digit_size_psychometric.toml: pixel-only 18 % at 0.3 pitch to 81 % at 1.5, CRS 28 %
to 90 %). Stroke
speed acts only through what is displayed: at the fixed frame rate a faster stroke is drawn
in fewer frames (at 15 frames/s a 20 mm/s stroke moves 1.3 mm a frame, 160 mm/s 10.7 mm), so
the path is sampled more coarsely, the holds and pen lifts take a larger share of the
``max_sensed_frames`` sensed frames, and the simulated device's servo speed limit makes the
displayed bump lag and cut the corners of fast strokes. The effect is weak: with 16 sensed
frames a trial a slow stroke gives no more samples than a fast one, and the skin has no
temporal blur here (8 participants, 10 to 160 mm/s: pixel-only 44 % to 41 %, CRS 68 % to 79 %
with no trend). The sensing window grows when needed to hold the largest symbol (``sense_radius_mm``
is a minimum). In an adaptive protocol (``[adaptive]``) a test trial carries the level its
block's procedure chose (:func:`crs_study.session.adaptive.choose`), one of the levels the
protocol lists, so the observer answers it as any other level: 8 simulated participants on
protocols/digit_size_adaptive.toml put the CRS threshold (QUEST+, 50 % correct) at 0.715 times
the pixel-only one (95 % CI 0.576 to 0.887).

Randomness comes from ``np.random.default_rng([seed, trial.index])`` only, so a resumed session
answers exactly as an uninterrupted one. Cost: at most ``max_sensed_frames`` frames a trial are
sensed (spread evenly); display models linear in the setpoints (``linear``, ``nearest``) are
reduced to one matrix product per frame, and noise-free sensed surfaces are cached per
displayed frame, so repeated presentations of a symbol cost only the noise and the decision.

Calibration: the defaults were chosen (noise, peak fraction and temperature swept on the
displayed frames of the simulated device) so that the shipped protocol on the published 2D
device gives pixel-only accuracy near the paper's 50.3 % and CRS near 67.8 %. The temperature
was re-tuned (1.6 -> 1.9 mm) when the digits were sized by their average bounding box
(crs_study/stimuli/digits.py), which made them 12 % wider and easier: ``crs-study demo
--participants 12`` (protocols/digit_identification.toml, 600 test trials a condition, the
report's headline) gives 51.3 % pixel-only and 69.7 % CRS (49.7 % and 68.3 % before
participants differed in their benefit); the demo's 20 participants give 50.8 % and 70.4 %.
tests/test_observer.py checks the gap and the range. ``detect_mm`` (2 mm, 40 % of the 5 mm
bump) sits above the maximum of the blurred receptor noise (~1 mm), so a flat frame is not
felt as a phantom peak. Decision times: median rt_median_s e^(rt_uncertainty H), about 2 s
at the typical H of 0.75.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from crs_study.clock import Clock
from crs_study.display import get_model
from crs_study.errors import ConfigError, DisplayModelError
from crs_study.geometry.layout import Layout, layout_key
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import PlannedTrial
from crs_study.rendering.conditions import get_condition
from crs_study.session.responders.base import (
    Responder,
    Response,
    StimulusRecord,
    respond_at,
    trial_rng,
)
from crs_study.stimuli.stimulus import make_stimulus, placement_centre
from crs_study.stimuli.strokes import Symbol

#: Models whose surface is linear in the setpoints (evaluated as one matrix product).
LINEAR_MODELS = ("nearest", "linear")


@dataclass(frozen=True)
class ObserverOptions:
    """Parameters of the perceptual observer (module docstring for their meaning)."""

    pixel_model: str | None = None  # None: the condition's own display model
    skeleton_model: str | None = None
    grid_spacing_mm: float = 3.0
    sense_radius_mm: float = 33.0
    skin_blur_mm: float = 3.0
    noise_mm: float = 1.5
    peak_fraction: float = 0.75
    detect_mm: float = 2.0
    max_sensed_frames: int = 16
    reuse_tolerance_mm: float = 0.02
    path_points: int = 16
    temperature_mm: float = 1.9
    ability_sd: float = 0.25
    benefit_sd: float = 0.25
    lapse: float = 0.05
    rt_median_s: float = 0.5
    rt_uncertainty: float = 2.0
    rt_sigma: float = 0.3

    def __post_init__(self) -> None:
        positive = ("grid_spacing_mm", "sense_radius_mm", "temperature_mm", "rt_median_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"observer option {name}: expected a number > 0, "
                                  f"got {getattr(self, name)!r}")
        for name in ("skin_blur_mm", "noise_mm", "detect_mm", "rt_uncertainty", "rt_sigma",
                     "reuse_tolerance_mm", "ability_sd", "benefit_sd"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"observer option {name}: expected a number >= 0, "
                                  f"got {getattr(self, name)!r}")
        if not 0 <= self.lapse <= 1:
            raise ConfigError(f"observer option lapse: expected 0..1, got {self.lapse!r}")
        if not 0 <= self.peak_fraction < 1:
            raise ConfigError(f"observer option peak_fraction: expected 0..1 (exclusive), "
                              f"got {self.peak_fraction!r}")
        for name in ("max_sensed_frames", "path_points"):
            if getattr(self, name) < 2:
                raise ConfigError(f"observer option {name}: expected at least 2, "
                                  f"got {getattr(self, name)!r}")


class _SurfaceCache:
    """Noise-free sensed surfaces of one (model, device, grid, blur), shared by every observer
    in the process, keyed by the displayed setpoints rounded to ``tolerance`` mm.

    The surface is computed from the *rounded* setpoints, so what a frame feels depends on that
    frame alone, never on which frames were sensed before: a resumed session, or participants
    spread over processes in any order, answer exactly as one uninterrupted run. Rounding to
    0.02 mm (about two pulse steps of the simulated servos) is far below what the skin
    resolves, and a beam solve costs milliseconds. Least recently used entries are dropped."""

    def __init__(self, tolerance: float, capacity: int = 4096) -> None:
        self.tolerance = tolerance
        self.capacity = capacity
        self.surfaces: OrderedDict[bytes, np.ndarray | None] = OrderedDict()

    def rounded(self, setpoints: np.ndarray) -> tuple[bytes, np.ndarray]:
        if self.tolerance == 0:
            return setpoints.tobytes(), setpoints
        steps = np.round(setpoints / self.tolerance).astype(np.int64)
        return steps.tobytes(), steps * self.tolerance

    def get(self, key: bytes) -> tuple[bool, np.ndarray | None]:
        if key not in self.surfaces:
            return False, None
        self.surfaces.move_to_end(key)
        return True, self.surfaces[key]

    def add(self, key: bytes, surface: np.ndarray | None) -> None:
        self.surfaces[key] = surface
        if len(self.surfaces) > self.capacity:
            self.surfaces.popitem(last=False)


_CACHES: dict[tuple, _SurfaceCache] = {}
_MODELS: dict[tuple, Any] = {}


class PerceptualObserver(Responder):
    """Senses the displayed surface, reconstructs the peak's path, names the closest symbol."""

    name = "observer"
    simulated = True

    def __init__(self, layout: Layout, protocol: Protocol, seed: int, **options: Any) -> None:
        known = {f.name for f in fields(ObserverOptions)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ConfigError(f"unknown observer option {unknown[0]!r}; "
                              f"known: {', '.join(sorted(known))}")
        self.options = ObserverOptions(**options)
        self.layout = layout if layout is not None else protocol.layout()
        self.protocol = protocol
        self.seed = int(seed)
        # Participants differ: each simulated person's decision noise is the default times
        # exp(ability_sd z), z ~ N(0, 1) drawn once from the seed (a stream apart from the
        # per-trial ones), so a group has a real between-participant variance to estimate;
        # and in how much the skeleton helps them: a second draw, exp(+-benefit_sd w / 2)
        # (module docstring, "Participants").
        ability = np.random.default_rng([self.seed, 1, 0]).standard_normal()
        self.benefit_z = float(np.random.default_rng([self.seed, 1, 1]).standard_normal())
        self.temperature_mm = self.options.temperature_mm * float(
            np.exp(self.options.ability_sd * ability))
        self._layout_key = layout_key(self.layout)
        o = self.options
        cx, cy = placement_centre(protocol.stimulus, self.layout)
        radius = max(o.sense_radius_mm, _largest_half_diagonal(protocol, self.layout)
                     + o.grid_spacing_mm)
        axis = np.arange(-radius, radius + 1e-9, o.grid_spacing_mm)
        self._gx, self._gy = np.meshgrid(cx + axis, cy + axis)
        self._points = np.column_stack([self._gx.ravel(), self._gy.ravel()])
        self._sigma_cells = o.skin_blur_mm / o.grid_spacing_mm
        self._templates: dict[tuple[Symbol, float | None], np.ndarray] = {}
        self.last_decision: dict[str, Any] = {}

    # -- sensing ---------------------------------------------------------------------------

    def model_name(self, condition: str) -> str:
        """The display model the skin meets in ``condition``: the condition's own, unless
        the ``pixel_model`` (pixels alone) or ``skeleton_model`` (beams driven) option
        replaces it."""
        meaning = get_condition(condition)
        chosen = self.options.skeleton_model if meaning.drives_beams else \
            self.options.pixel_model
        return meaning.display_model if chosen is None else chosen

    def temperature(self, condition: str) -> float:
        """This participant's decision noise in ``condition`` (mm): the ability's temperature
        times ``exp(benefit_sd w s / 2)``, ``s`` = -1 on the pixels alone, +1 on the
        skeleton."""
        side = benefit_side(condition)
        return self.temperature_mm * float(np.exp(0.5 * side * self.options.benefit_sd
                                                  * self.benefit_z))

    def _surface_function(self, model_name: str):
        key = (model_name, self._layout_key, self._points.tobytes())
        if key not in _MODELS:
            model = get_model(model_name, self.layout)
            if model_name in LINEAR_MODELS:
                # z(s) = z(0) + A s for a model linear in the setpoints: A column by column.
                base = model.surface(np.zeros(self.layout.n_actuators), self._points)
                columns = [model.surface(unit, self._points) - base
                           for unit in np.eye(self.layout.n_actuators)]
                matrix = np.column_stack(columns)
                _MODELS[key] = lambda s, b=base, a=matrix: b + a @ s
            else:
                _MODELS[key] = lambda s, m=model: m.surface(s, self._points)
        return _MODELS[key]

    def sensed_surface(self, condition: str, setpoints: np.ndarray) -> np.ndarray | None:
        """Noise-free sensed surface G * z on the grid (mm), cached per displayed frame.

        None when the display model cannot produce the frame's surface (collapse, yield).
        """
        from scipy.ndimage import gaussian_filter

        model_name = self.model_name(condition)
        setpoints = np.asarray(setpoints, dtype=float)
        key = (model_name, self._layout_key, self._points.tobytes(), self._sigma_cells,
               self.options.reuse_tolerance_mm)
        cache = _CACHES.get(key)
        if cache is None:
            cache = _CACHES[key] = _SurfaceCache(self.options.reuse_tolerance_mm)
        frame_key, rounded = cache.rounded(setpoints)
        found, z = cache.get(frame_key)
        if found:
            return z
        # Built outside the try: a model that cannot be built at all (a device file it cannot
        # mesh) is an error of the whole run, never a session of skipped frames and guesses.
        surface = self._surface_function(model_name)
        try:
            z = surface(rounded).reshape(self._gx.shape)
        except DisplayModelError:
            # The model has no shape for this frame (a beam collapsing or yielding while the
            # servos are between two frames): nothing reliable to feel, the frame is skipped.
            z = None
        if z is not None and self._sigma_cells > 0:
            z = gaussian_filter(z, self._sigma_cells, mode="nearest")
        if z is not None:
            z.setflags(write=False)
        cache.add(frame_key, z)
        return z

    def peak_path(self, stimulus: StimulusRecord, rng: np.random.Generator) -> np.ndarray:
        """Sensed peak positions (m, 2) over the active sensed frames, in order."""
        from scipy.ndimage import gaussian_filter

        o = self.options
        n = len(stimulus.setpoints)
        if n == 0:
            return np.zeros((0, 2))
        chosen = np.unique(np.round(np.linspace(0, n - 1, min(n, o.max_sensed_frames)))
                           .astype(int))
        surfaces = [z for z in (self.sensed_surface(stimulus.condition, stimulus.setpoints[k])
                                for k in chosen) if z is not None]
        if surfaces and o.noise_mm > 0:
            # every frame's noise in one draw and one filter along the grid's two axes: the
            # same numbers, bit for bit, as a draw and a filter per frame in turn
            noise = rng.normal(0.0, o.noise_mm, (len(surfaces), *surfaces[0].shape))
            if self._sigma_cells > 0:
                noise = gaussian_filter(noise, self._sigma_cells, mode="nearest", axes=(1, 2))
            surfaces = [z + frame_noise for z, frame_noise in zip(surfaces, noise, strict=True)]
        peaks = []
        for z in surfaces:
            top = float(z.max())
            if top < o.detect_mm:
                continue  # flat: the pen is lifted
            weight = np.clip(z - o.peak_fraction * top, 0.0, None)
            total = weight.sum()
            peaks.append(((weight * self._gx).sum() / total, (weight * self._gy).sum() / total))
        return np.array(peaks).reshape(-1, 2)

    # -- deciding --------------------------------------------------------------------------

    def template(self, symbol: Symbol, level: float | None = None) -> np.ndarray:
        """A symbol's bump-centre path (drawn frames) at ``level``, resampled and centred."""
        key = (symbol, level)
        if key not in self._templates:
            stim = make_stimulus(self.protocol, self.layout, symbol, level)
            self._templates[key] = _normalise(stim.centres_mm[stim.drawn],
                                              self.options.path_points)
        return self._templates[key]

    def choice_probabilities(self, path: np.ndarray, choices: tuple[int, ...],
                             level: float | None = None, condition: str | None = None
                             ) -> tuple[np.ndarray, np.ndarray]:
        """(p, d): choice probabilities and template distances (mm) for each choice, against
        the templates at the trial's ``level`` (None: no levels), at this participant's
        temperature in ``condition`` (None: the ability's alone)."""
        o = self.options
        n = len(choices)
        if len(path) < 2:
            return np.full(n, 1.0 / n), np.full(n, np.nan)
        shape = _normalise(path, o.path_points)
        d = np.array([np.sqrt(np.mean(np.sum((shape - self.template(c, level)) ** 2, axis=1)))
                      for c in choices])
        temperature = self.temperature_mm if condition is None else self.temperature(condition)
        logits = -(d - d.min()) / temperature
        p = np.exp(logits)
        p /= p.sum()
        return (1.0 - o.lapse) * p + o.lapse / n, d

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        o = self.options
        rng = trial_rng(self.seed, trial.index)
        choices = tuple(stimulus.symbol_choices)
        path = self.peak_path(stimulus, rng)
        p, d = self.choice_probabilities(path, choices, getattr(trial, "level", None),
                                         stimulus.condition)
        u = rng.random()
        index = min(int(np.searchsorted(np.cumsum(p), u * p.sum(), side="right")),
                    len(choices) - 1)
        entropy = float(-np.sum(p * np.log(p)) / np.log(len(choices))) if len(choices) > 1 \
            else 0.0
        decision_s = float(np.exp(np.log(o.rt_median_s) + o.rt_uncertainty * entropy
                                  + o.rt_sigma * rng.standard_normal()))
        self.last_decision = {"path": path, "probabilities": p, "distances": d,
                              "entropy": entropy, "decision_s": decision_s}
        return respond_at(clock, stimulus, stimulus.duration_s + decision_s, time_limit_s,
                          choices[index])


def benefit_side(condition: str) -> float:
    """-1 for the pixels alone, +1 for a condition with the skeleton: the sign of a
    participant's benefit draw in that condition's decision noise
    (:attr:`crs_study.rendering.Condition.benefit_side`)."""
    return get_condition(condition).benefit_side


def _largest_half_diagonal(protocol: Protocol, layout: Layout) -> float:
    """How far (mm) the drawn bump centre gets from the placement point, over the protocol's
    symbols and levels: the drawn paths themselves, so the window holds the widest symbol
    whatever the strokes (the protocol's width x height is the symbols' *average* size,
    crs_study/stimuli/strokes.py, and the widest symbols exceed it)."""
    centre = np.asarray(placement_centre(protocol.stimulus, layout), dtype=float)
    reach = 0.0
    for level in getattr(protocol, "level_values", (None,)):
        for symbol in protocol.symbols:
            stim = make_stimulus(protocol, layout, symbol, level)
            drawn = stim.centres_mm[stim.drawn] - centre
            reach = max(reach, float(np.hypot(drawn[:, 0], drawn[:, 1]).max(initial=0.0)))
    return reach


def _normalise(path: np.ndarray, points: int) -> np.ndarray:
    """Resample a path to ``points`` at equal fractions of its length in frames; centre it."""
    path = np.asarray(path, dtype=float)
    t = np.linspace(0.0, 1.0, len(path))
    u = np.linspace(0.0, 1.0, points)
    out = np.column_stack([np.interp(u, t, path[:, 0]), np.interp(u, t, path[:, 1])])
    return out - out.mean(axis=0)
