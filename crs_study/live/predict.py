"""Where the finger will be when a frame's servos are in place: a 1€-filtered constant-velocity
prediction, bounded.

The wire (9600 baud) puts a frame's servos in place some 40-50 ms after the packet it carries
arrived; a finger writing at 100 mm/s is 4-5 mm further on by then. So each frame is rendered
for the finger's predicted position at the time its servos will be in place:

1. **Filter.** Each packet's (x_f, y_f, z_f) passes a 1€ filter (Casiez, Roussel & Vogel 2012):
   an exponential low-pass whose cutoff rises with speed, ``f_c = min_cutoff + beta |v|``, so a
   slow or held finger is smoothed (tracker jitter) and a fast one is followed with little
   lag. ``v`` is the filtered derivative (cutoff ``d_cutoff``). x and y share the cutoff of
   the finger's planar speed; z (the press) has its own.
2. **When: late binding** (:mod:`crs_study.live.timing`). The frame is rendered for the time
   its servos will be in place, computed for its own setpoints when it is handed over (the
   wait for the wire over): its last byte on the boards, from a copy of the device's write
   policy, plus the servos' time for its largest move at 0.08 s/cm, the move's part counted up
   to ``max_lead_s``. So no frame is rendered for more than ``max_lead_s`` (15 ms: haptics
   should not lead vision by more than about that) after the earliest time it can be in place,
   its last byte's arrival: no frame leads the finger by more, by construction. The horizon
   is that time minus the sample's arrival, at most ``max_horizon_s``.
3. **Extrapolate, bounded.** ``p = p_filtered + s(h) v / |v|``: ``s = |v| h`` while the
   filtered planar speed holds or rises; while it falls (its filtered rate ``a < 0``), constant
   deceleration until the finger stops, ``s = |v| h + a h^2 / 2`` up to the stopping distance
   ``|v|^2 / (2 |a|)``: a minimum-jerk stroke (Flash & Hogan 1985) slows down smoothly to its
   end, so the bump stops near it instead of running on. The step is capped at
   ``max_extrapolation_mm`` (a stroke stopped at once, with no slowing to see, is overrun by
   at most that). The press depth is extrapolated at its filtered rate (its step capped
   alike); a press predicted to end (z <= 0) flattens the display.

A gap between packets longer than ``reset_s`` (the sender paused, a new stream) restarts the
filter: a velocity across a gap means nothing. With ``method = "off"`` frames show the newest
packet as it came (the link before prediction).

References
----------
Casiez, G., Roussel, N. & Vogel, D. (2012). 1€ Filter: A Simple Speed-based Low-pass Filter
for Noisy Input in Interactive Systems. Proc. CHI 2012, 2527-2530.
Flash, T. & Hogan, N. (1985). The coordination of arm movements: an experimentally confirmed
mathematical model. Journal of Neuroscience 5(7), 1688-1703.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from crs_study.live.errors import LiveError


@dataclass(frozen=True)
class PredictConfig:
    """How frames are predicted (module docstring); times in s, lengths in mm, rates in Hz.

    Defaults chosen on ``crs-study bench live``'s synthetic traces (the ten digits at 50, 100
    and 200 mm/s with minimum-jerk strokes): ``min_cutoff`` and ``beta`` as the 1€ paper's
    tuning procedure (a low ``min_cutoff`` for a still finger, then ``beta`` until a fast one
    shows little lag; beta 0.5-1 and step caps 6-8 mm differed by under 0.2 mm in median
    error), ``d_cutoff`` 15 Hz (8 Hz: 1.83 against 1.64 mm at 100 mm/s, before late binding);
    the filtered deceleration uses ``d_cutoff`` too. ``max_lead_s`` 15 ms: how far haptics may
    lead vision (a bound, not a tuning: the figures are measured under it).
    """

    method: Literal["one-euro", "off"] = "one-euro"
    min_cutoff_hz: float = 1.0
    beta: float = 0.5  # per mm/s
    d_cutoff_hz: float = 15.0
    max_extrapolation_mm: float = 6.0
    max_horizon_s: float = 0.120
    max_lead_s: float = 0.015
    reset_s: float = 0.1

    def __post_init__(self) -> None:
        if self.method not in ("one-euro", "off"):
            raise LiveError(f"predict method: expected 'one-euro' or 'off', got {self.method!r}")
        for name, low, high in (("min_cutoff_hz", 1e-3, 1e3), ("beta", 0.0, 1e3),
                                ("d_cutoff_hz", 1e-3, 1e3), ("max_extrapolation_mm", 0.0, 100.0),
                                ("max_horizon_s", 0.0, 1.0), ("max_lead_s", 0.0, 0.1),
                                ("reset_s", 1e-3, 10.0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not (math.isfinite(value) and low <= value <= high):
                raise LiveError(f"predict {name}: expected a number in [{low:g}, {high:g}], "
                                f"got {value!r}")

    @property
    def on(self) -> bool:
        return self.method != "off"

    def describe(self) -> str:
        if not self.on:
            return "off (the newest packet as it came)"
        return (f"1€ filter (min cutoff {self.min_cutoff_hz:g} Hz, beta {self.beta:g}, "
                f"d cutoff {self.d_cutoff_hz:g} Hz) + velocity, slowing at the filtered "
                f"deceleration, step <= {self.max_extrapolation_mm:g} mm, horizon <= "
                f"{self.max_horizon_s * 1e3:g} ms, late-bound, lead <= "
                f"{self.max_lead_s * 1e3:g} ms")


def smoothing(cutoff_hz: float, dt: float) -> float:
    """The 1€ paper's ``alpha = 1 / (1 + tau / T_e)``, ``tau = 1 / (2 pi f_c)``."""
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * cutoff_hz * dt))


class OneEuro:
    """The 1€ filter of one coordinate (Casiez, Roussel & Vogel 2012, their reference
    algorithm): :meth:`filter` returns the filtered value; :attr:`derivative` the filtered
    rate of change. ``speed`` given: the cutoff follows it instead of this coordinate's
    own |derivative| (x and y of one finger share their planar speed)."""

    def __init__(self, min_cutoff_hz: float, beta: float, d_cutoff_hz: float) -> None:
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff_hz, beta, d_cutoff_hz
        self.value: float | None = None
        self.derivative = 0.0
        self.time = -math.inf

    def rate(self, t: float, x: float) -> float:
        """Filtered derivative after a sample ``x`` at ``t`` (updates it; call before
        :meth:`filter`)."""
        if self.value is None or t <= self.time:
            return self.derivative
        dt = t - self.time
        raw = (x - self.value) / dt
        self.derivative += smoothing(self.d_cutoff, dt) * (raw - self.derivative)
        return self.derivative

    def filter(self, t: float, x: float, speed: float | None = None) -> float:
        if self.value is None:
            self.value, self.time = float(x), t
            return self.value
        if t <= self.time:  # two samples at one time: the newer one wins, unfiltered
            self.value = float(x)
            return self.value
        dt = t - self.time
        if speed is None:
            speed = abs(self.rate(t, x))
        cutoff = self.min_cutoff + self.beta * speed
        self.value += smoothing(cutoff, dt) * (x - self.value)
        self.time = t
        return self.value


class Predictor:
    """Filters packets (:meth:`update`) and predicts the finger at a time (:meth:`at`), module
    docstring. :attr:`state` says what the last prediction did (the live view)."""

    def __init__(self, config: PredictConfig) -> None:
        self.config = config
        self.state: dict[str, float | bool] = {}
        self.reset()

    def reset(self) -> None:
        c = self.config
        self.axes = [OneEuro(c.min_cutoff_hz, c.beta, c.d_cutoff_hz) for _ in range(3)]
        self.sample_at = -math.inf
        self.speed = 0.0  # filtered planar speed (mm/s)
        self.accel = 0.0  # its filtered rate of change (mm/s^2; < 0: slowing down)

    def update(self, t: float, x: float, y: float, z: float) -> None:
        """A packet's position, arrived at ``t``."""
        if t - self.sample_at > self.config.reset_s:
            self.reset()
        ax, ay, az = self.axes
        vx, vy = ax.rate(t, x), ay.rate(t, y)
        speed = math.hypot(vx, vy)
        ax.filter(t, x, speed)
        ay.filter(t, y, speed)
        az.filter(t, z)
        if math.isfinite(self.sample_at) and t > self.sample_at:
            dt = t - self.sample_at
            raw = (speed - self.speed) / dt
            self.accel += smoothing(self.config.d_cutoff_hz, dt) * (raw - self.accel)
        self.speed = speed
        self.sample_at = max(self.sample_at, t)

    def step(self, horizon: float) -> float:
        """How far along its velocity the finger is extrapolated over ``horizon`` s (mm):
        ``v h`` while the speed holds or rises; slowing down (``a < 0``), at that constant
        deceleration until it stops, ``v h - |a| h^2 / 2`` for ``h < v / |a|``, at most
        ``v^2 / (2 |a|)``; capped at ``max_extrapolation_mm``."""
        v, a = self.speed, self.accel
        if a < 0.0:
            h = min(horizon, v / -a)
            distance = v * h + 0.5 * a * h * h
        else:
            distance = v * horizon
        return min(distance, self.config.max_extrapolation_mm)

    def at(self, t: float, raw: tuple[float, float, float]
           ) -> tuple[tuple[float, float, float], float]:
        """The position to render for the finger at time ``t``, and the time it is rendered
        for (``t``, or earlier where the horizon is capped; the sample's own time when off:
        ``raw``, the newest packet as it came)."""
        c = self.config
        if not c.on or not math.isfinite(self.sample_at):
            self.state = {"horizon_ms": 0.0, "step_mm": 0.0, "capped": False}
            return raw, self.sample_at if math.isfinite(self.sample_at) else t
        horizon = min(max(0.0, t - self.sample_at), c.max_horizon_s)
        ax, ay, az = self.axes
        step = self.step(horizon)
        scale = step / self.speed if self.speed > 0 else 0.0
        dx, dy = ax.derivative * scale, ay.derivative * scale
        dz = max(-c.max_extrapolation_mm, min(c.max_extrapolation_mm, az.derivative * horizon))
        self.state = {"horizon_ms": horizon * 1e3, "step_mm": step, "speed_mm_s": self.speed,
                      "capped": step >= c.max_extrapolation_mm, "slowing": self.accel < 0}
        return (ax.value + dx, ay.value + dy, az.value + dz), self.sample_at + horizon
