"""Synthetic surface measurements for the tests: what a DIC would export of the display model.

Independent of the library's own stand-in (crs_study/quality/dic_standin.py), so the tests
check the import, registration and criteria against a generator they do not share:

* the true surface: the display model (``nearest``, ``linear``, ``beam``...) for the recorded
  setpoints, with faulty servos' pixels moved (``offset`` mm at every stroke, ``gain`` per
  commanded mm);
* a known misregistration: points and fiducials written in a DIC frame turned by
  ``rotation_deg``, shifted by ``shift`` and scaled by ``scale`` against the display's, the
  DIC's z axis offset and tilted;
* Gaussian noise of ``noise_mm`` on every measured height, a ``holes`` fraction of points
  without data and optionally a disc without data (``blob``: centre and radius, display
  frame);
* the exports of the tools the reader knows: VIC-3D (``vic3d``), GOM Correlate (``gom``:
  metadata lines, ``;`` and decimal commas, units in brackets), DICe (``dice``), a plain
  tab-separated table of coordinates in metres (``plain-m``: z only, so the reference capture
  is subtracted) and MATLAB (``mat``, scipy.io.savemat).

:func:`fill_measurement` writes a capture for every row of a measurement's manifest (and the
fiducials), the way a lab saves its DIC exports beside a measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crs_study.display import get_model
from crs_study.geometry.layout import Layout

FORMATS = ("vic3d", "gom", "dice", "plain-m", "mat")


@dataclass(frozen=True)
class Rig:
    """A DIC rig's known imperfections (module docstring)."""

    rotation_deg: float = -7.0
    shift: tuple[float, float] = (31.0, -12.0)
    scale: float = 1.0
    noise_mm: float = 0.01
    holes: float = 0.02
    blob: tuple[float, float, float] | None = None  # (x, y, radius) mm, display frame
    spacing_mm: float = 1.0
    fiducial_noise_mm: float = 0.03
    z_offset_mm: float = 412.0
    tilt: tuple[float, float] = (0.02, 0.01)
    faults: dict[int, tuple[float, float]] = field(default_factory=dict)  # pixel: (a, g)

    def rotation(self) -> np.ndarray:
        a = math.radians(self.rotation_deg)
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    def to_dic(self, xy: np.ndarray) -> np.ndarray:
        """display -> DIC (column vectors: p_dic = scale (R p + shift))."""
        return self.scale * (xy @ self.rotation().T + np.asarray(self.shift))


def grid(layout: Layout, spacing: float) -> np.ndarray:
    """Points over the display (display frame): the pixels' hull and a pitch around it; on a
    line, the beam's strip (its width)."""
    xy = layout.pixel_xy
    if layout.lattice == "line":
        x0, x1 = xy[:, 0].min() - layout.pitch_mm, xy[:, 0].max() + layout.pitch_mm
        half = 0.5 * layout.beam_section.width_mm
        xs = np.arange(x0, x1 + 1e-9, spacing)
        ys = np.arange(-half, half + 1e-9, spacing)
        return np.array([(x, y) for y in ys for x in xs])
    lo, hi = xy.min(axis=0) - layout.pitch_mm, xy.max(axis=0) + layout.pitch_mm
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
    points = np.column_stack([gx.ravel(), gy.ravel()])
    reach = np.max(np.hypot(*(xy - xy.mean(axis=0)).T)) + layout.pitch_mm
    return points[np.hypot(*(points - xy.mean(axis=0)).T) <= reach]


def true_setpoints(layout: Layout, setpoints: np.ndarray, faults: dict) -> np.ndarray:
    real = np.array(setpoints, dtype=float)
    for pixel, (offset, gain) in faults.items():
        real[pixel] = offset + gain * real[pixel]
    return real


def surfaces(layout: Layout, model: str, setpoints: np.ndarray, rig: Rig, points: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(neutral, shown) true heights at ``points`` (display frame). A beam whose commanded
    length no longer fits the faulty pixels is taken as the spline through them (the test's
    truth need not be the beam's physics, only the measurement's)."""
    display = get_model(model, layout)
    neutral = true_setpoints(layout, layout.neutral_setpoints(), rig.faults)
    shown = true_setpoints(layout, setpoints, rig.faults)
    try:
        return display.surface(neutral, points), display.surface(shown, points)
    except Exception:  # noqa: BLE001 - a collapsing beam under faulty pixels: the spline
        spline = get_model("spline", layout)
        return spline.surface(neutral, points), spline.surface(shown, points)


def capture_columns(layout: Layout, model: str, setpoints: np.ndarray, rig: Rig,
                    rng: np.random.Generator) -> dict[str, np.ndarray]:
    """DIC frame positions (X, Y), the reference coordinate Z and the displacement W, with NaN
    where a point has no data (mm)."""
    points = grid(layout, rig.spacing_mm)
    neutral, shown = surfaces(layout, model, setpoints, rig, points)
    base = rig.z_offset_mm + rig.tilt[0] * points[:, 0] + rig.tilt[1] * points[:, 1]
    ref_noise = rng.normal(0.0, rig.noise_mm, len(points))
    def_noise = rng.normal(0.0, rig.noise_mm, len(points))
    dic = rig.to_dic(points)
    z = (base + neutral + ref_noise) * rig.scale
    w = (shown - neutral + def_noise - ref_noise) * rig.scale
    missing = rng.random(len(points)) < rig.holes
    if rig.blob is not None:
        bx, by, radius = rig.blob
        missing |= np.hypot(points[:, 0] - bx, points[:, 1] - by) <= radius
    columns = {"X": dic[:, 0], "Y": dic[:, 1], "Z": z, "W": w}
    for values in columns.values():
        values[missing] = np.nan
    return columns


def _number(value: float, comma: bool = False) -> str:
    text = "" if not math.isfinite(value) else f"{value:.6f}"
    return text.replace(".", ",") if comma else text


def write_capture(path: Path, fmt: str, columns: dict[str, np.ndarray]) -> Path:
    """Write ``columns`` as the export of tool ``fmt`` at ``path`` (its suffix set here)."""
    x, y, z, w = columns["X"], columns["Y"], columns["Z"], columns["W"]
    missing = ~np.isfinite(w)
    n = len(x)
    if fmt == "mat":
        from scipy.io import savemat

        path = path.with_suffix(".mat")
        savemat(path, {"x": x.reshape(1, -1), "y": y.reshape(1, -1), "z": z.reshape(1, -1),
                       "w": w.reshape(1, -1)})
        return path
    path = path.with_suffix(".csv" if fmt != "plain-m" else ".tsv")
    lines = []
    if fmt == "vic3d":
        lines.append('"X","Y","Z","U","V","W","sigma","x","y"')
        for k in range(n):
            if missing[k]:
                lines.append("0,0,0,0,0,0,-1,0,0")
            else:
                lines.append(f"{x[k]:.6f},{y[k]:.6f},{z[k]:.6f},0,0,{w[k]:.6f},0.004,"
                             f"{600 + 9 * x[k]:.1f},{400 - 9 * y[k]:.1f}")
    elif fmt == "gom":
        lines += ["Project: crs-study synthetic", "Stage: 1", "",
                  "Point id;x [mm];y [mm];z [mm];dX [mm];dY [mm];dZ [mm]"]
        for k in range(n):
            lines.append(";".join([f"P{k}", _number(x[k], True), _number(y[k], True),
                                   _number(z[k], True), "0,0", "0,0", _number(w[k], True)]))
    elif fmt == "dice":
        lines += ["***", "*** Digital Image Correlation Engine (DICe), synthetic", "***",
                  "SUBSET_ID,COORDINATE_X,COORDINATE_Y,DISPLACEMENT_X,DISPLACEMENT_Y,"
                  "MODEL_COORDINATES_X,MODEL_COORDINATES_Y,MODEL_COORDINATES_Z,"
                  "MODEL_DISPLACEMENT_X,MODEL_DISPLACEMENT_Y,MODEL_DISPLACEMENT_Z,SIGMA"]
        for k in range(n):
            sigma = "-1.0" if missing[k] else "4.0E-03"
            lines.append(f"{k},{500 + 7 * k % 300},{200 + k // 300},0,0,{_number(x[k])},"
                         f"{_number(y[k])},{_number(z[k])},0,0,{_number(w[k])},{sigma}")
    elif fmt == "plain-m":  # coordinates of the deformed surface only, in metres
        lines.append("x (m)\ty (m)\tz (m)")
        for k in range(n):
            deformed = z[k] + w[k]
            lines.append("\t".join(f"{v / 1000.0:.9f}" if math.isfinite(v) else "NaN"
                                   for v in (x[k], y[k], deformed)))
    else:
        raise ValueError(fmt)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def write_fiducials(path: Path, layout: Layout, rig: Rig, rng: np.random.Generator) -> Path:
    dic = rig.to_dic(layout.pixel_xy) + rng.normal(0.0, rig.fiducial_noise_mm,
                                                   layout.pixel_xy.shape)
    lines = ["pixel,x,y"] + [f"{k},{dic[k, 0]:.6f},{dic[k, 1]:.6f}"
                             for k in range(layout.n_pixels)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def fill_measurement(folder: Path, rig: Rig, fmt: str = "vic3d", seed: int = 0,
                     model_for: dict[str, str] | None = None) -> Path:
    """Write the DIC export of every capture of the measurement in ``folder`` (and the
    fiducials) into ``folder/captures``; ``model_for``: the true model of each condition
    (default the protocol's)."""
    from crs_study.quality.manifest import read_manifest
    from crs_study.quality.measured_analysis import load_measurement

    _, protocol, layout = load_measurement(folder)
    captures = folder / "captures"
    captures.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    write_fiducials(captures / "fiducials.csv", layout, rig, rng)
    for entry in read_manifest(folder / "manifest.tsv", layout.n_actuators):
        model = (model_for or protocol.models)[entry.condition]
        columns = capture_columns(layout, model, entry.setpoints_mm, rig, rng)
        write_capture(captures / entry.capture, fmt, columns)
    return captures
