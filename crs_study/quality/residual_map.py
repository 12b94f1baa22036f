"""The per-pixel residual map: which servo does not put its pixel where its calibration says.

Each pixel's servo maps a commanded stroke c (mm) to a pulse width by the device file's
calibration (``pulse = zero_us + (full_us - zero_us) c / travel``). A servo whose real
stroke is ``a + g c`` instead of c is mis-calibrated: ``a`` (mm) is its offset at the neutral
pose, ``g`` its gain. Two parts of a measurement see them:

* the **reference captures** (the display neutral, every pixel commanded to 0): the surface
  there is flat but for the offsets, so a pixel's height above the plane fitted robustly to
  the whole reference (:func:`scipy.optimize.least_squares`, soft-L1 loss) is its ``a``; an
  export without the surface's z coordinate (displacements only) leaves ``a`` unknown;
* the **shapes** (heights above the reference, where offsets cancel): at each pixel the
  measured height minus the model's (the mean of the points within a small radius of the
  pixel, of the measurement and of the model at the same points, so the averaging's own
  bias cancels) against the commanded stroke gives ``g - 1`` by least squares through the
  origin, with its standard error.

A pixel is named when ``|a|`` exceeds the protocol's ``offset_limit_mm`` or ``|g - 1|``
exceeds ``gain_limit`` by more than three standard errors. Its corrected endpoints make the
real stroke equal the command: ``c' = (c - a) / g``, so
``zero_us' = zero_us - span a / (g travel)`` and
``full_us' = zero_us + span (travel - a) / (g travel)`` (``span = full_us - zero_us``); they
are what ``crs-study quality analyze --write-calibration`` writes into a copy of the device
file for ``crs-study device calibrate`` to start from and review.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from crs_study.geometry.layout import PULSE_MAX_US, PULSE_MIN_US, Layout

#: Shapes whose commanded stroke at a pixel is below this fraction of the protocol's height
#: carry no information on the pixel's gain and are left out of its fit.
MIN_STROKE_FRACTION = 0.05


@dataclass(frozen=True)
class PixelResidual:
    """One pixel of the map."""

    pixel: int
    channel: str  # "A:3"
    x_mm: float
    y_mm: float
    offset_mm: float  # a: height above the reference's plane at neutral (nan: unknown)
    gain: float  # g: real stroke per commanded mm (nan: no shape moved the pixel)
    gain_se: float
    shapes: int  # shapes in the gain's fit
    rms_mm: float  # RMS of measured - model heights at the pixel over the shapes
    flagged: bool
    why: str  # "" or what is beyond the limits

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}


@dataclass(frozen=True)
class ResidualMap:
    """Every pixel's residual (module docstring) and the limits it was judged by."""

    pixels: tuple[PixelResidual, ...]
    offset_limit_mm: float
    gain_limit: float

    @property
    def flagged(self) -> tuple[PixelResidual, ...]:
        return tuple(p for p in self.pixels if p.flagged)

    def to_frame(self):
        """One row per pixel, the fields of :class:`PixelResidual`."""
        import pandas as pd

        return pd.DataFrame([asdict(p) for p in self.pixels],
                            columns=list(PixelResidual.__dataclass_fields__))

    def to_dict(self) -> dict:
        return {"offset_limit_mm": self.offset_limit_mm, "gain_limit": self.gain_limit,
                "pixels": [p.to_dict() for p in self.pixels],
                "flagged": [p.channel for p in self.flagged]}

    def corrected_endpoints(self, layout: Layout) -> dict[str, tuple[float, float]]:
        """New ``(zero_us, full_us)`` of each flagged pixel's channel (module docstring),
        rounded to whole microseconds and kept inside the boards' 500..2500 us."""
        out = {}
        for residual in self.flagged:
            actuator = layout.pixel_actuators[residual.pixel]
            cal = actuator.calibration
            offset = residual.offset_mm if math.isfinite(residual.offset_mm) else 0.0
            gain = residual.gain if math.isfinite(residual.gain) and residual.gain > 0 else 1.0
            span = cal.full_us - cal.zero_us
            zero = cal.zero_us - span * offset / (gain * cal.travel_mm)
            full = cal.zero_us + span * (cal.travel_mm - offset) / (gain * cal.travel_mm)
            out[residual.channel] = tuple(float(np.clip(round(v), PULSE_MIN_US, PULSE_MAX_US))
                                          for v in (zero, full))
        return out


def pixel_heights(xy: np.ndarray, *heights: np.ndarray, layout: Layout, radius_mm: float
                  ) -> tuple[np.ndarray, ...]:
    """The height of each of ``heights`` (surfaces at the points ``xy`` of the display's
    frame) at each pixel: the median of the points within ``radius_mm`` of the pixel and
    inside the pixels' hull (NaN where there is none). Inside the hull: the models end at it
    (the linear connection drops to the base there), and a point a registration's residual
    away from it is then read on one side by the model, on the other by the measurement; the
    median shrugs off the few points so read, where a mean would not."""
    from scipy.spatial import cKDTree

    tolerance = 1e-6 * layout.pitch_mm
    if layout.lattice == "line":
        lo, hi = layout.pixel_xy[:, 0].min(), layout.pixel_xy[:, 0].max()
        inside = (xy[:, 0] >= lo - tolerance) & (xy[:, 0] <= hi + tolerance)
    else:
        from scipy.spatial import Delaunay

        inside = Delaunay(layout.pixel_xy).find_simplex(xy, tol=tolerance) >= 0
    index = np.flatnonzero(inside)
    tree = cKDTree(xy[index])
    out = tuple(np.full(layout.n_pixels, np.nan) for _ in heights)
    for k, pixel in enumerate(layout.pixel_xy):
        near = index[tree.query_ball_point(pixel, radius_mm)]
        if len(near):
            for values, surface in zip(out, heights, strict=True):
                values[k] = float(np.median(surface[near]))
    return out


def reference_offsets(xy: np.ndarray, z: np.ndarray, layout: Layout, radius_mm: float,
                      noise_mm: float) -> np.ndarray:
    """Each pixel's height above the plane fitted robustly to a neutral capture (mm; NaN
    where no point lies near the pixel, :func:`pixel_heights`). ``xy`` in the display's
    frame."""
    from scipy.optimize import least_squares

    keep = np.isfinite(xy).all(axis=1) & np.isfinite(z)
    xy, z = xy[keep], z[keep]
    design = np.column_stack([np.ones(len(z)), xy])
    start = np.linalg.lstsq(design, z, rcond=None)[0]
    plane = least_squares(lambda c: design @ c - z, start, loss="soft_l1",
                          f_scale=max(noise_mm, 1e-6)).x
    (offsets,) = pixel_heights(xy, z - design @ plane, layout=layout, radius_mm=radius_mm)
    return offsets


def residual_map(layout: Layout, commanded: np.ndarray, residuals: np.ndarray,
                 offsets: Sequence[np.ndarray], *, height_mm: float, offset_limit_mm: float,
                 gain_limit: float) -> ResidualMap:
    """The map from the shapes' ``commanded`` pixel strokes and their ``residuals``
    (measured minus model height at each pixel), both (shapes, pixels) with NaN where the
    pixel was not seen, and the reference captures' ``offsets`` (one array per reference)."""
    commanded = np.asarray(commanded, dtype=float).reshape(-1, layout.n_pixels)
    residuals = np.asarray(residuals, dtype=float).reshape(-1, layout.n_pixels)
    known = [o for o in offsets if np.isfinite(o).any()]
    offset = np.nanmean(np.vstack(known), axis=0) if known else np.full(layout.n_pixels,
                                                                          np.nan)
    pixels = []
    for k, actuator in enumerate(layout.pixel_actuators):
        c, r = commanded[:, k], residuals[:, k]
        use = np.isfinite(r) & (c >= MIN_STROKE_FRACTION * height_mm)
        n = int(use.sum())
        gain = se = rms = math.nan
        if n >= 2:
            cc, rr = c[use], r[use]
            slope = float(cc @ rr / (cc @ cc))
            gain = 1.0 + slope
            dof = n - 1
            se = math.sqrt(float(np.sum((rr - slope * cc) ** 2)) / dof / float(cc @ cc))
            rms = float(np.sqrt(np.mean(rr**2)))
        elif n == 1:
            gain = 1.0 + float(r[use][0] / c[use][0])
        why = []
        a = float(offset[k])
        if math.isfinite(a) and abs(a) > offset_limit_mm:
            why.append(f"offset {a:+.2f} mm at neutral (limit {offset_limit_mm:g})")
        if math.isfinite(gain) and abs(gain - 1.0) > gain_limit and \
                math.isfinite(se) and abs(gain - 1.0) > 3.0 * se:
            why.append(f"gain {gain:.3f} +- {se:.3f} (limit 1 +- {gain_limit:g})")
        pixels.append(PixelResidual(
            k, f"{actuator.controller}:{actuator.channel}", float(layout.pixel_xy[k, 0]),
            float(layout.pixel_xy[k, 1]), a, gain, se, n, rms, bool(why), "; ".join(why)))
    return ResidualMap(tuple(pixels), offset_limit_mm, gain_limit)
