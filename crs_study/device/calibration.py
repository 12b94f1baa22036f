"""Setpoints (mm) to pulse widths (us) per channel, and back, with limits that never leak.

:meth:`PulseMap.to_pulses` is the one map from millimetres to pulse widths: both devices and
the wire estimate use it, and the ``device calibrate`` command starts each channel from it.
Each actuator's :class:`~crs_study.geometry.layout.Calibration` (the device file's numbers) maps
stroke to pulse width linearly (linear PWM servos: pulse width in proportion to stroke)::

    pulse = zero_us + (full_us - zero_us) * mm / travel_mm,   mm in [0, travel_mm]

with ``zero_us > full_us`` for a reversed servo. Pulses are quantised to whole microseconds, the
LSC's resolution (SERVO_MOVE carries an integer pulse width).

Limits: a setpoint outside ``[0, travel_mm]`` by more than ``tolerance_mm`` (rounding noise) or
a NaN is a :class:`~crs_study.errors.DeviceError` naming the channel (``"A:3 pixel 2"``), the
value and the range; setpoints within the tolerance are clipped onto the range. Every pulse
this module returns lies inside the channel's calibrated range, which the device file keeps
inside the board's 500..2500 us, so nothing outside limits can be encoded.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crs_study.errors import DeviceError, DeviceFileError
from crs_study.geometry.layout import Layout, load_layout

#: Setpoints this far outside [0, travel] are float noise and are clipped, not refused (mm).
DEFAULT_TOLERANCE_MM = 1e-6

#: The pulse resolution (us): :meth:`PulseMap.to_pulses` rounds to the nearest whole
#: microsecond, the LSC's (SERVO_MOVE carries an integer). The renderer's feed cap leaves room
#: for half of it (:data:`crs_study.rendering.feed_cap.PULSE_QUANTUM_US`, the same number: the
#: rendering stage sits below the device's; tests/test_feed_cap.py checks they agree).
PULSE_QUANTUM_US = 1.0


@dataclass(frozen=True, eq=False)
class PulseMap:
    """Vectorised calibration of every channel of a layout, in actuator order.

    Build with :meth:`from_layout`. Arrays are read-only, one entry per actuator.
    """

    labels: tuple[str, ...]  # "A:3 pixel 2"
    controller_index: np.ndarray  # position of the actuator's controller in the device file
    servo_id: np.ndarray  # channel number on that controller (the LSC servo id)
    zero_us: np.ndarray
    full_us: np.ndarray
    travel_mm: np.ndarray
    pulse_low: np.ndarray  # smallest whole-us pulse inside the calibrated range
    pulse_high: np.ndarray  # largest
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    # derived once (to_pulses runs every frame): full_us - zero_us, the accepted setpoint
    # range with its tolerance, and the whole-us pulse range as floats
    _span_us: np.ndarray = field(init=False, repr=False)
    _us_per_mm: np.ndarray = field(init=False, repr=False)
    _accept_high_mm: np.ndarray = field(init=False, repr=False)
    _pulse_low_f: np.ndarray = field(init=False, repr=False)
    _pulse_high_f: np.ndarray = field(init=False, repr=False)
    _whole_endpoints: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # whole-us endpoints: rint of a value inside [zero, full] (off by float noise only)
        # already lies in [pulse_low, pulse_high], so the last clip can be skipped
        object.__setattr__(self, "_whole_endpoints", bool(
            np.all(self.zero_us == np.round(self.zero_us))
            and np.all(self.full_us == np.round(self.full_us))))
        derived = {
            "_span_us": self.full_us - self.zero_us,
            "_us_per_mm": (self.full_us - self.zero_us) / self.travel_mm,
            "_accept_high_mm": self.travel_mm + self.tolerance_mm,
            "_pulse_low_f": np.asarray(self.pulse_low, dtype=float),
            "_pulse_high_f": np.asarray(self.pulse_high, dtype=float),
        }
        for name, value in derived.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @classmethod
    def from_layout(cls, layout: Layout, tolerance_mm: float = DEFAULT_TOLERANCE_MM
                    ) -> PulseMap:
        index = {c.name: c.index for c in layout.controllers}
        acts = layout.actuators
        zero = np.array([a.calibration.zero_us for a in acts], dtype=float)
        full = np.array([a.calibration.full_us for a in acts], dtype=float)
        arrays = dict(
            controller_index=np.array([index[a.controller] for a in acts], dtype=int),
            servo_id=np.array([a.channel for a in acts], dtype=int),
            zero_us=zero, full_us=full,
            travel_mm=np.array([a.calibration.travel_mm for a in acts], dtype=float),
            pulse_low=np.ceil(np.minimum(zero, full)).astype(int),
            pulse_high=np.floor(np.maximum(zero, full)).astype(int),
        )
        for value in arrays.values():
            value.setflags(write=False)
        labels = tuple(f"{a.controller}:{a.channel} {a.name}" for a in acts)
        return cls(labels=labels, tolerance_mm=tolerance_mm, **arrays)

    @property
    def n_channels(self) -> int:
        return len(self.labels)

    def to_pulses(self, setpoints_mm: np.ndarray) -> np.ndarray:
        """Whole-us pulse widths for setpoints: shape (n,) or (n_frames, n); checked, never clipped
        beyond the tolerance. Raises :class:`DeviceError` naming the first bad channel."""
        mm = np.asarray(setpoints_mm, dtype=float)
        if mm.shape[-1:] != (self.n_channels,):
            raise DeviceError(
                f"setpoints: expected {self.n_channels} values per frame (one per actuator), "
                f"got shape {mm.shape!r}"
            )
        ok = mm >= -self.tolerance_mm
        ok &= mm <= self._accept_high_mm  # NaN fails both
        if not ok.all():
            where = np.argwhere(~ok)[0]
            channel = int(where[-1])
            frame = f" in frame {int(where[0])}" if mm.ndim == 2 else ""
            raise DeviceError(
                f"channel {self.labels[channel]}: setpoint {float(mm[tuple(where)])!r} mm{frame} "
                f"is outside its calibrated range 0..{self.travel_mm[channel]:g} mm"
            )
        # np.clip's arithmetic with fewer temporaries: clip onto [0, travel], then
        # zero + (full - zero) * mm / travel, rounded, inside the whole-us range
        pulses = np.maximum(mm, 0.0)
        np.minimum(pulses, self.travel_mm, out=pulses)
        pulses *= self._span_us
        pulses /= self.travel_mm
        pulses += self.zero_us
        np.rint(pulses, out=pulses)
        if not self._whole_endpoints:
            np.maximum(pulses, self._pulse_low_f, out=pulses)
            np.minimum(pulses, self._pulse_high_f, out=pulses)
        return pulses.astype(np.int64)

    def to_mm(self, pulses_us: np.ndarray, check: bool = True) -> np.ndarray:
        """Setpoints (mm) for pulse widths, ``(pulse - zero_us) / ((full_us - zero_us) /
        travel_mm)``: the inverse of :meth:`to_pulses` (before its rounding).

        With ``check`` a pulse outside the calibrated range is a :class:`DeviceError`; without,
        any pulse maps (a modelled servo's position: a limp one sinks below its range).
        """
        if check:
            self.check_pulses(pulses_us)
        return (pulses_us - self.zero_us) / self._us_per_mm  # float arrays for any input

    def check_pulses(self, pulses_us: np.ndarray) -> None:
        """Raise :class:`DeviceError` if any pulse lies outside its channel's calibrated range."""
        pulses = np.asarray(pulses_us, dtype=float)
        low = np.minimum(self.zero_us, self.full_us)
        high = np.maximum(self.zero_us, self.full_us)
        bad = ~((pulses >= low) & (pulses <= high))
        if bad.any():
            where = np.argwhere(bad)[0]
            channel = int(where[-1])
            raise DeviceError(
                f"channel {self.labels[channel]}: pulse width {float(pulses[tuple(where)])!r} us "
                f"is outside its calibrated range {low[channel]:g}..{high[channel]:g} us"
            )

    def neutral_pulses(self, layout: Layout) -> np.ndarray:
        return self.to_pulses(layout.neutral_setpoints())


# ---------------------------------------------------------------------------------------------
# writing a calibrated copy of a device file

_SECTION_RE = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-\"]+)\s*\]\]?\s*(#.*)?$")


def calibration_table(endpoints: Mapping[str, tuple[float, float]],
                      default: tuple[float, float]) -> str:
    """The ``[calibration]`` TOML table for per-channel ``{"A:3": (zero_us, full_us)}``."""
    lines = [
        "[calibration]",
        "# Pulse width (us) at 0 mm and at full travel per channel; zero_us > full_us reverses.",
        f"default = {{zero_us = {_num(default[0])}, full_us = {_num(default[1])}}}",
    ]
    for key in sorted(endpoints, key=_channel_sort_key):
        zero, full = endpoints[key]
        lines.append(f'"{key}" = {{zero_us = {_num(zero)}, full_us = {_num(full)}}}')
    return "\n".join(lines) + "\n"


def write_calibrated_copy(source: str | Path, destination: str | Path,
                          endpoints: Mapping[str, tuple[float, float]],
                          overwrite: bool = False) -> Layout:
    """Copy a device file with its ``[calibration]`` table replaced; return the new layout.

    The rest of the file is kept byte for byte. ``destination`` must not exist unless
    ``overwrite``; the copy is validated by loading it, and removed again if it is invalid.
    """
    source_path = Path(source)
    dest = Path(destination)
    if dest.exists() and not overwrite:
        raise DeviceFileError(f"{dest}: already exists; choose another file or pass --overwrite")
    if dest.resolve() == source_path.resolve():
        raise DeviceFileError(f"{dest}: refusing to overwrite the device file being calibrated")
    layout = load_layout(source_path)
    text = source_path.read_text(encoding="utf-8")
    default = previous_default_endpoints(layout, endpoints)
    head, tail = _split_out_section(text, "calibration")
    new_text = head.rstrip("\n") + "\n\n" + calibration_table(endpoints, default)
    if tail.strip():
        new_text += "\n" + tail
    tmp = dest.with_name(dest.name + ".tmp")
    tmp.write_text(new_text, encoding="utf-8")
    try:
        new_layout = load_layout(tmp)
    except DeviceFileError:
        tmp.unlink()
        raise
    tmp.replace(dest)
    return new_layout


def previous_default_endpoints(layout: Layout, endpoints: Mapping[str, tuple[float, float]]
                       ) -> tuple[float, float]:
    """The previous default: the calibration of any channel without an override."""
    for a in layout.actuators:
        if f"{a.controller}:{a.channel}" not in endpoints:
            return a.calibration.zero_us, a.calibration.full_us
    first = layout.actuators[0].calibration
    return first.zero_us, first.full_us


def _split_out_section(text: str, name: str) -> tuple[str, str]:
    """Text without table ``[name]``: (before, after). Missing table: (text, "")."""
    lines = text.splitlines(keepends=True)
    start = end = None
    for i, line in enumerate(lines):
        match = _SECTION_RE.match(line)
        if not match:
            continue
        if start is None and match.group(1) == name and not line.lstrip().startswith("[["):
            start = i
        elif start is not None:
            end = i
            break
    if start is None:
        return text, ""
    end = len(lines) if end is None else end
    # keep comment lines right above the next table with that table
    while end > start + 1 and lines[end - 1].lstrip().startswith("#"):
        end -= 1
    return "".join(lines[:start]), "".join(lines[end:])


def _channel_sort_key(key: str) -> tuple[str, int]:
    name, _, number = key.partition(":")
    return name, int(number) if number.isdigit() else -1


def _num(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))

