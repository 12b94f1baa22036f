"""A synthetic DIC stand-in: what a stereo DIC would export of the simulated device.

``crs-study quality measure --device sim:// --capture synthetic[?options]`` rehearses the
whole lab workflow without cameras: at each capture window the stand-in takes the servo
positions the simulated device reached, makes the surface the display model gives for them
(the condition's model of the protocol) and writes what a DIC export of it would hold, in a
frame of its own, with noise and holes; and once, the fiducials a person would mark on the
reference capture. It plays a rig, not an ideal measurement:

* the DIC frame is turned, shifted and (optionally) scaled against the display's, and its z
  axis carries an offset and a small tilt;
* each export is VIC-3D style: ``X, Y, Z`` (mm, the reference configuration), ``U, V, W``
  (displacement from the reference image, here out of plane only), ``sigma`` (-1 where a
  point has no data, the points then written as zeros, as VIC-3D does) and the image
  coordinates ``x, y`` in pixels that a reader must not take for millimetres;
* Gaussian noise on every measured height, a random fraction of points without data;
* servos that do not follow their calibration: ``servo=A:3:0.4`` puts pixel channel A:3
  0.4 mm above its command at every stroke (an offset at neutral), ``gain=A:5:1.1`` makes it
  travel 1.1 mm per commanded mm. A beam fed for its commanded pixels is then held to its
  longest stable shape through the true ones (the feed cap of
  :mod:`crs_study.rendering.feed_cap`), as the steel would.

Options (``synthetic?key=value&...``; ``servo`` and ``gain`` repeat):
``spacing_mm`` (1.0; 0.5 on a line), ``noise_mm`` (0.01), ``holes`` (0.01),
``rotation_deg`` (4), ``shift_x_mm`` (12.5), ``shift_y_mm`` (-7.5), ``scale`` (1),
``fiducial_noise_mm`` (0.05), ``seed`` (0), ``servo``, ``gain``. A bad option is a one-line
:class:`~crs_study.errors.MeasurementError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from crs_study._files import make_dirs, write_atomically
from crs_study.display import get_model
from crs_study.errors import MeasurementError
from crs_study.geometry.layout import Layout
from crs_study.quality.dic_import import write_table
from crs_study.rendering.feed_cap import FeedCap

#: The DIC's z offset (mm) and tilt (dz/dx, dz/dy) in the display's frame.
Z_OFFSET_MM = 3.0
TILT = (0.01, -0.005)
#: Pixels per millimetre of the image coordinates written beside the metric ones.
IMAGE_PX_PER_MM = 8.0


@dataclass(frozen=True)
class SyntheticDic:
    """The stand-in's rig (module docstring)."""

    spacing_mm: float | None = None  # None: 1 mm, 0.5 mm on a line of pixels
    noise_mm: float = 0.01
    holes: float = 0.01
    rotation_deg: float = 4.0
    shift_x_mm: float = 12.5
    shift_y_mm: float = -7.5
    scale: float = 1.0
    fiducial_noise_mm: float = 0.05
    seed: int = 0
    servo: tuple[tuple[str, float], ...] = ()
    gain: tuple[tuple[str, float], ...] = ()

    @classmethod
    def parse(cls, text: str) -> SyntheticDic:
        """``synthetic`` or ``synthetic?key=value&...`` (module docstring)."""
        parts = urlsplit(text)
        if parts.path != "synthetic" or parts.scheme or parts.netloc:
            raise MeasurementError(f"--capture {text!r}: expected synthetic[?key=value&...]")
        numbers = {f.name: f for f in fields(cls) if f.name not in ("servo", "gain")}
        values: dict[str, object] = {}
        servo: list[tuple[str, float]] = []
        gain: list[tuple[str, float]] = []
        for key, raw in parse_qsl(parts.query, keep_blank_values=True):
            if key in ("servo", "gain"):
                channel, _, number = raw.rpartition(":")
                value = _float(text, key, number)
                (servo if key == "servo" else gain).append((channel, value))
            elif key in numbers:
                values[key] = int(_float(text, key, raw)) if key == "seed" else \
                    _float(text, key, raw)
            else:
                raise MeasurementError(f"--capture {text!r}: unknown option {key!r}; valid: "
                                       f"{', '.join([*numbers, 'servo', 'gain'])}")
        rig = replace(cls(), servo=tuple(servo), gain=tuple(gain), **values)
        for name, low, high in (("noise_mm", 0.0, 5.0), ("holes", 0.0, 0.5),
                                ("scale", 0.5, 2.0), ("fiducial_noise_mm", 0.0, 10.0)):
            if not low <= getattr(rig, name) <= high:
                raise MeasurementError(f"--capture {text!r}: {name} must lie in "
                                       f"[{low:g}, {high:g}], got {getattr(rig, name)!r}")
        if rig.spacing_mm is not None and not 0.05 <= rig.spacing_mm <= 20.0:
            raise MeasurementError(f"--capture {text!r}: spacing_mm must lie in [0.05, 20]")
        return rig

    # --- frames ----------------------------------------------------------------------------

    @property
    def _rotation(self) -> np.ndarray:
        a = math.radians(self.rotation_deg)
        return np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])

    def to_dic(self, xy: np.ndarray) -> np.ndarray:
        """Display frame -> the DIC's (the inverse of the registration to be found)."""
        shift = np.array([self.shift_x_mm, self.shift_y_mm])
        return (np.asarray(xy, dtype=float) @ self._rotation + shift) * self.scale

    def to_display(self, xy: np.ndarray) -> np.ndarray:
        shift = np.array([self.shift_x_mm, self.shift_y_mm])
        return (np.asarray(xy, dtype=float) / self.scale - shift) @ self._rotation.T

    def grid(self, layout: Layout) -> np.ndarray:
        """The DIC's points: a regular grid in its own frame over the display (mm, display
        frame): the pixels' hull and a pitch around it; on a line, the beam's strip."""
        if layout.lattice == "line":
            spacing = self.spacing_mm or 0.5
            x0 = min(min(b.start[0], b.end[0]) for b in layout.beams)
            x1 = max(max(b.start[0], b.end[0]) for b in layout.beams)
            half = 0.5 * layout.beam_section.width_mm
            xs = np.arange(x0, x1 + 1e-9, spacing)
            ys = np.arange(-half, half + 1e-9, spacing) + layout.pixel_xy[0, 1]
            return np.array([(x, y) for y in ys for x in xs])
        spacing = self.spacing_mm or 1.0
        from scipy.spatial import Delaunay

        corners = self.to_dic(layout.pixel_xy)
        lo, hi = corners.min(axis=0) - layout.pitch_mm, corners.max(axis=0) + layout.pitch_mm
        u, v = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
        points = self.to_display(np.column_stack([u.ravel(), v.ravel()]))
        centre = layout.pixel_xy.mean(axis=0)
        scaled = centre + (layout.pixel_xy - centre) * (1 + layout.pitch_mm / np.max(
            np.hypot(*(layout.pixel_xy - centre).T)))
        return points[Delaunay(scaled).find_simplex(points) >= 0]

    # --- what the display shows -------------------------------------------------------------

    def true_setpoints(self, layout: Layout, shown: np.ndarray) -> np.ndarray:
        """The servos' real positions for ``shown`` (mm): each faulty pixel's offset and gain
        applied, each beam held to its longest stable shape through the real pixels."""
        channels = {f"{a.controller}:{a.channel}": a for a in layout.pixel_actuators}
        real = np.array(shown, dtype=float)
        for label, pairs in (("servo", self.servo), ("gain", self.gain)):
            for channel, value in pairs:
                if channel not in channels:
                    raise MeasurementError(f"--capture: {label}={channel}:{value:g}: "
                                           f"{channel!r} is no pixel channel of {layout.name} "
                                           f"({', '.join(channels)})")
                k = channels[channel].index
                real[k] = real[k] + value if label == "servo" else real[k] * value
        if layout.beams:
            starts = [float(real[b.start_servo]) for b in layout.beams]
            ends = [float(real[b.end_servo]) for b in layout.beams]
            capped_starts, capped_ends, _ = FeedCap(layout, None).apply(
                real[: layout.n_pixels], starts, ends)
            for b, beam in enumerate(layout.beams):
                real[beam.start_servo], real[beam.end_servo] = capped_starts[b], capped_ends[b]
        return real

    def export(self, layout: Layout, model: str, shown: np.ndarray, index: int
               ) -> dict[str, np.ndarray]:
        """The columns of the VIC-3D style export of one capture (``shown``: the servo
        positions the device reached; ``index``: the capture's, which seeds its noise)."""
        display = get_model(model, layout)
        points = self.grid(layout)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, index]))
        neutral = display.surface(self.true_setpoints(layout, layout.neutral_setpoints()),
                                  points)
        surface = display.surface(self.true_setpoints(layout, shown), points)
        base = Z_OFFSET_MM + TILT[0] * points[:, 0] + TILT[1] * points[:, 1]
        ref_noise = rng.normal(0.0, self.noise_mm, len(points))
        def_noise = rng.normal(0.0, self.noise_mm, len(points))
        z = (base + neutral + ref_noise) * self.scale
        w = (surface - neutral + def_noise - ref_noise) * self.scale
        dic = self.to_dic(points)
        sigma = np.full(len(points), 0.004)
        missing = rng.random(len(points)) < self.holes
        columns = {"X": dic[:, 0], "Y": dic[:, 1], "Z": z, "U": np.zeros(len(points)),
                   "V": np.zeros(len(points)), "W": w}
        for values in columns.values():
            values[missing] = 0.0
        sigma[missing] = -1.0
        columns["sigma"] = sigma
        columns["x"] = np.round(512 + IMAGE_PX_PER_MM * dic[:, 0], 1)
        columns["y"] = np.round(512 - IMAGE_PX_PER_MM * dic[:, 1], 1)
        return columns

    def fiducials(self, layout: Layout) -> dict[str, np.ndarray]:
        """The pixels as a person marks them on the reference capture (DIC frame, mm)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 2**31]))
        dic = self.to_dic(layout.pixel_xy) + rng.normal(0.0, self.fiducial_noise_mm,
                                                        layout.pixel_xy.shape)
        return {"pixel": np.arange(layout.n_pixels), "x": dic[:, 0], "y": dic[:, 1]}

    def write_capture(self, folder: Path, name: str, layout: Layout, model: str,
                      shown: np.ndarray, index: int) -> Path:
        """Write one capture's export as ``folder/name.csv`` (atomically)."""
        make_dirs(folder)
        path = folder / f"{name}.csv"
        columns = self.export(layout, model, shown, index)
        header = '"' + '","'.join(columns) + '"\n'
        body = write_table(columns).split("\n", 1)[1]
        write_atomically(path, header + body, durable=False)
        return path

    def write_fiducials(self, folder: Path, layout: Layout) -> Path:
        make_dirs(folder)
        path = folder / "fiducials.csv"
        write_atomically(path, write_table(self.fiducials(layout)), durable=False)
        return path


def _float(text: str, key: str, raw: str) -> float:
    try:
        value = float(raw)
    except ValueError:
        raise MeasurementError(f"--capture {text!r}: {key}: expected a number, got "
                               f"{raw!r}") from None
    if not math.isfinite(value):
        raise MeasurementError(f"--capture {text!r}: {key}: expected a finite number")
    return value
