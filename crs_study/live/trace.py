"""Finger traces: where a finger is over time, made up or recorded, for ``live-send``.

A :class:`FingerTrace` is samples (t_k, x_k, y_k, z_k): seconds from its start, and the
packet's coordinates (mm from the recognition area's centre; z the press depth). Made-up
traces (every one a pure function of its arguments and, for jitter, a seed):

* :func:`symbol_trace`: a finger writing a symbol of a stimulus set (the digits, the
  letters, a set file: :mod:`crs_study.stimuli.sets`) with that set's strokes: each stroke at
  constant speed along its arc length (sampled as a session's stimulus is,
  :func:`crs_study.stimuli.digits.point_at`), pressing ``press_mm``; between strokes the
  finger lifts (z = 0: a flat display) and moves straight to the next stroke's start; it rests
  pressed at the first and the last point for ``hold_s``. :func:`digit_trace` is the digit
  set's.
* :func:`stroke_trace`: one straight stroke at constant speed.

Strokes go at constant speed by default, starting and stopping at once. With ``profile =
"minimum-jerk"`` each stroke (and each lifted move between strokes) starts and ends at rest,
its arc length following ``s(tau) = L (10 tau^3 - 15 tau^4 + 6 tau^5)``, the smooth point-to-point
movement of Flash & Hogan (1985, "The coordination of arm movements: an experimentally
confirmed mathematical model", J. Neurosci. 5(7), 1688-1703), at the same mean speed (its
peak is 1.875 times that): a finger cannot stop at once, and the stroke-end figures of the
prediction would be a constant-speed trace's artefact otherwise.
* :func:`hold_trace`: a finger held still; with :meth:`FingerTrace.jittered` a trembling one
  (independent Gaussian noise of ``sd_mm`` on x and y per sample).

:meth:`FingerTrace.resampled` gives the trace at another rate (linear interpolation in time),
:meth:`FingerTrace.faster` the trace played faster or slower. No trace has more than
:data:`MAX_SAMPLES` samples or a position a packet (float32) cannot carry.
A recording made by ``crs-study live --record`` replays as a trace
(:func:`crs_study.live.record.read_trace`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crs_study.errors import ProtocolError
from crs_study.live.errors import LiveError
from crs_study.stimuli.digits import arc_lengths, load_digits, point_at
from crs_study.stimuli.sets import DEFAULT_SET, load_stimulus_set

#: The headset's frame rate (Oculus Quest 2, the paper's): packets a second.
HEADSET_RATE_HZ = 72.0
#: Highest rate a trace may be sent or resampled at (packets/s).
MAX_RATE_HZ = 2000.0
#: Most samples a trace may have (a day at 72 packets/s is 6.2 million): resampling a long
#: recording at a high rate must not ask for gigabytes.
MAX_SAMPLES = 10_000_000
#: Largest coordinate a packet carries (mm): the float32 of the packet format.
MAX_COORDINATE_MM = float(np.finfo(np.float32).max)
#: Speed profiles of a stroke (module docstring).
PROFILES = ("constant", "minimum-jerk")
#: Width of a drawn symbol per unit of its height (the shipped protocols' 0.49 / 0.81 pitch,
#: digits and letters alike).
DIGIT_ASPECT = 0.49 / 0.81


@dataclass(frozen=True, eq=False)
class FingerTrace:
    """Samples of a finger: ``times`` (n,) s from the start, increasing; ``xyz`` (n, 3) mm."""

    times: np.ndarray
    xyz: np.ndarray
    name: str = "trace"

    def __post_init__(self) -> None:
        times = np.array(self.times, dtype=float)
        xyz = np.array(self.xyz, dtype=float).reshape(-1, 3)
        if times.ndim != 1 or len(times) != len(xyz) or len(times) == 0:
            raise LiveError(f"trace {self.name}: expected n times and n (x, y, z) samples, "
                            f"n >= 1, got {times.shape} and {xyz.shape}")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(xyz))):
            raise LiveError(f"trace {self.name}: expected finite times and positions")
        if np.any(np.abs(xyz) > MAX_COORDINATE_MM):
            raise LiveError(f"trace {self.name}: expected positions a packet can carry "
                            f"(|x|, |y|, |z| <= {MAX_COORDINATE_MM:.4g} mm, float32), got "
                            f"{float(np.max(np.abs(xyz))):.4g}")
        if np.any(np.diff(times) <= 0) or times[0] < 0:
            raise LiveError(f"trace {self.name}: expected times from >= 0, strictly increasing")
        for array in (times, xyz):
            array.setflags(write=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "xyz", xyz)

    def __len__(self) -> int:
        return len(self.times)

    @property
    def duration_s(self) -> float:
        return float(self.times[-1])

    def resampled(self, rate_hz: float) -> FingerTrace:
        """The trace at ``rate_hz`` samples a second from its start to its end (the last
        sample included), each coordinate interpolated linearly in time."""
        check_rate(rate_hz)
        n = _samples(self.duration_s * rate_hz, self.name) + 1
        times = np.arange(n) / rate_hz
        xyz = np.column_stack([np.interp(times, self.times, self.xyz[:, i]) for i in range(3)])
        return FingerTrace(times, xyz, self.name)

    def faster(self, speed: float) -> FingerTrace:
        """The trace played ``speed`` times as fast (its times divided by ``speed``)."""
        if isinstance(speed, bool) or not isinstance(speed, int | float) \
                or not (math.isfinite(speed) and 0.01 <= speed <= 100.0):
            raise LiveError(f"speed: expected a factor in [0.01, 100], got {speed!r}")
        if speed == 1:
            return self
        return FingerTrace(self.times / speed, self.xyz, f"{self.name} x{speed:g}")

    def jittered(self, sd_mm: float, seed: int = 0) -> FingerTrace:
        """The trace with independent Gaussian noise of ``sd_mm`` added to x and y of every
        sample (a trembling finger); z is kept."""
        if not (math.isfinite(sd_mm) and sd_mm >= 0):
            raise LiveError(f"jitter: expected a standard deviation >= 0 mm, got {sd_mm!r}")
        noise = np.random.default_rng(seed).normal(0.0, sd_mm, (len(self), 2))
        xyz = self.xyz.copy()
        xyz[:, :2] += noise
        return FingerTrace(self.times, xyz, f"{self.name}, jitter {sd_mm:g} mm")


def _samples(count: float, name: str) -> int:
    """``count`` as a whole number of samples, refused past :data:`MAX_SAMPLES`."""
    if not count < MAX_SAMPLES:
        raise LiveError(f"trace {name}: would have {count:.3g} samples, more than "
                        f"{MAX_SAMPLES:.3g}; send a shorter trace or at a lower rate")
    return int(math.floor(count + 1e-9))


def check_rate(rate_hz: float) -> float:
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, int | float) \
            or not (math.isfinite(rate_hz) and 0 < rate_hz <= MAX_RATE_HZ):
        raise LiveError(f"rate: expected packets a second in (0, {MAX_RATE_HZ:g}], "
                        f"got {rate_hz!r}")
    return float(rate_hz)


def _positive(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not (math.isfinite(value) and value > 0):
        raise LiveError(f"{name}: expected a number > 0, got {value!r}")
    return float(value)


def _path(points: np.ndarray, speed_mm_s: float, rate_hz: float,
          profile: str = "constant") -> np.ndarray:
    """Points along a polyline at ``speed_mm_s`` on average, one per 1 / rate s, the end
    included: at constant speed, or ``"minimum-jerk"`` (module docstring)."""
    length = arc_lengths(points)[-1]
    n = max(1, _samples(math.ceil(length * rate_hz / speed_mm_s - 1e-9), "path")) + 1
    if profile == "minimum-jerk":
        tau = np.minimum(np.arange(n) * speed_mm_s / (rate_hz * length), 1.0)
        return point_at(points, length * tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau ** 2))
    return point_at(points, np.minimum(np.arange(n) * speed_mm_s / rate_hz, length))


def _profile(profile: str) -> str:
    if profile not in PROFILES:
        raise LiveError(f"speed profile: expected one of {', '.join(PROFILES)}, got {profile!r}")
    return profile


def _with_times(rows: list[np.ndarray], rate_hz: float, name: str) -> FingerTrace:
    xyz = np.concatenate(rows)
    return FingerTrace(np.arange(len(xyz)) / rate_hz, xyz, name)


def digit_trace(digit: int, height_mm: float = 60.0, speed_mm_s: float = 30.0,
                press_mm: float = 5.0, rate_hz: float = HEADSET_RATE_HZ,
                centre_mm: tuple[float, float] = (0.0, 0.0), hold_s: float = 0.2,
                strokes_file: str | None = None, profile: str = "constant") -> FingerTrace:
    """A finger writing ``digit`` (module docstring): the digits of the strokes file average
    ``height_mm`` high and ``DIGIT_ASPECT`` times that wide, centred at ``centre_mm``."""
    digits = load_digits(strokes_file)
    if digit not in digits:
        raise LiveError(f"digit: expected one of {sorted(digits)}, got {digit!r}")
    return _written(digits[digit], f"digit {digit}", height_mm, speed_mm_s, press_mm, rate_hz,
                    centre_mm, hold_s, profile)


def symbol_trace(symbol: str, stimulus_set: str = DEFAULT_SET, height_mm: float = 60.0,
                 speed_mm_s: float = 30.0, press_mm: float = 5.0,
                 rate_hz: float = HEADSET_RATE_HZ, centre_mm: tuple[float, float] = (0.0, 0.0),
                 hold_s: float = 0.2) -> FingerTrace:
    """A finger writing ``symbol`` (as written: ``"7"``, ``"A"``) of ``stimulus_set`` (a
    shipped set's name or a set file) with that set's strokes, as :func:`digit_trace`."""
    try:
        shown = load_stimulus_set(stimulus_set)
    except ProtocolError as exc:  # a set file's own errors name the file and line
        raise LiveError(str(exc) if exc.source else f"stimulus set: {exc.reason}") from None
    found = shown.symbol_of(str(symbol))
    if found is None:
        raise LiveError(f"{shown.noun}: expected one of {shown.describe()} (the {shown.name} "
                        f"set), got {str(symbol)!r}")
    try:
        glyph = shown.glyph(found)
    except ProtocolError as exc:
        raise LiveError(str(exc)) from None
    return _written(glyph, f"{shown.noun} {found}", height_mm, speed_mm_s, press_mm, rate_hz,
                    centre_mm, hold_s)


def _written(glyph, what: str, height_mm: float, speed_mm_s: float, press_mm: float,
             rate_hz: float, centre_mm: tuple[float, float], hold_s: float,
             profile: str = "constant") -> FingerTrace:
    """A finger writing ``glyph``'s strokes (module docstring), ``height_mm`` high on
    average and ``DIGIT_ASPECT`` times that wide, centred at ``centre_mm``."""
    height = _positive(f"{what.split()[0]} height", height_mm)
    speed = _positive("finger speed", speed_mm_s)
    rate = check_rate(rate_hz)
    press = _positive("press depth", press_mm)
    profile = _profile(profile)
    strokes = glyph.scaled(height * DIGIT_ASPECT, height, centre_mm)
    rows: list[np.ndarray] = []

    def add(points: np.ndarray, z: float) -> None:
        rows.append(np.column_stack([points, np.full(len(points), z)]))

    held = int(round(hold_s * rate))
    add(np.repeat(strokes[0][:1], held, axis=0), press)
    for i, stroke in enumerate(strokes):
        if i:  # lifted, straight from the last stroke's end to this one's start
            add(_path(np.array([strokes[i - 1][-1], stroke[0]]), speed, rate, profile)[1:-1],
                0.0)
        add(_path(stroke, speed, rate, profile), press)
    add(np.repeat(strokes[-1][-1:], held, axis=0), press)
    how = "" if profile == "constant" else f", {profile}"
    return _with_times(rows, rate, f"{what}, {height:g} mm at {speed:g} mm/s{how}")


def stroke_trace(start_mm: tuple[float, float], end_mm: tuple[float, float],
                 speed_mm_s: float = 30.0, press_mm: float = 5.0,
                 rate_hz: float = HEADSET_RATE_HZ, profile: str = "constant") -> FingerTrace:
    """One straight stroke from ``start_mm`` to ``end_mm`` at ``speed_mm_s`` (on average, by
    ``profile``), pressing."""
    points = np.array([start_mm, end_mm], dtype=float)
    if points.shape != (2, 2) or not np.all(np.isfinite(points)) \
            or np.allclose(points[0], points[1]):
        raise LiveError(f"stroke: expected two different finite points, got {start_mm!r}, "
                        f"{end_mm!r}")
    path = _path(points, _positive("finger speed", speed_mm_s), check_rate(rate_hz),
                 _profile(profile))
    rows = [np.column_stack([path, np.full(len(path), _positive("press depth", press_mm))])]
    return _with_times(rows, rate_hz, f"stroke at {speed_mm_s:g} mm/s")


def hold_trace(centre_mm: tuple[float, float] = (0.0, 0.0), duration_s: float = 2.0,
               press_mm: float = 5.0, rate_hz: float = HEADSET_RATE_HZ) -> FingerTrace:
    """A finger held still at ``centre_mm`` for ``duration_s``, pressing ``press_mm``."""
    rate = check_rate(rate_hz)
    n = _samples(_positive("duration", duration_s) * rate, "held") + 1
    point = np.array([*centre_mm, _positive("press depth", press_mm)], dtype=float)
    return _with_times([np.tile(point, (n, 1))], rate, f"held {duration_s:g} s")
