"""Registration of a capture to the display's frame from pixel fiducials.

The DIC measures in its own frame (its calibration plate's axes); the criteria need the
display's (the device file's pixel positions, mm). Pixels marked in the DIC's frame (the
knots tying the fabric to each pixel, :func:`~crs_study.quality.dic_import.read_fiducials`)
and their positions in the device file give the map by least squares: the orthogonal
Procrustes problem (:func:`scipy.linalg.orthogonal_procrustes`) on the centred points, a
rotation (``rigid``) or a rotation and a scale (``similarity``, Umeyama's scale
trace(S) / |A|^2), then the translation between the centroids::

    p_display = s R p_dic + t

A fit that needs a mirror image is refused (the DIC's y axis flipped, or pixels numbered the
other way round); on a line of pixels, where a mirror across the line fits as well as the
rotation, the rotation is taken. The residual of each fiducial (its fitted position minus the
device file's, mm) is reported, their RMS is checked against the protocol's limit and the
worst pixel named. ``similarity`` scales the heights too: a scale other than 1 is a unit the
export did not state (or a calibration off by that factor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.linalg import orthogonal_procrustes

from crs_study.errors import MeasurementError
from crs_study.geometry.layout import Layout
from crs_study.quality.dic_import import Fiducials

#: Fewest fiducials: three leave a residual to check for either fit.
MIN_FIDUCIALS = 3


@dataclass(frozen=True)
class Registration:
    """The map from a capture's DIC frame to the display's (module docstring)."""

    mode: Literal["rigid", "similarity"]
    rotation: np.ndarray  # (2, 2), row vectors: p_display = scale * p_dic @ rotation + t
    scale: float
    translation: np.ndarray  # (2,) mm
    pixels: np.ndarray  # (n,) fiducial pixels
    residuals_mm: np.ndarray  # (n,) distance of each fitted fiducial from its pixel
    source: str = ""

    @property
    def rotation_deg(self) -> float:
        """The angle the DIC frame is turned by, counter-clockwise, degrees."""
        return math.degrees(math.atan2(self.rotation[0, 1], self.rotation[0, 0]))

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm**2)))

    @property
    def max_mm(self) -> float:
        return float(self.residuals_mm.max())

    @property
    def worst_pixel(self) -> int:
        return int(self.pixels[int(np.argmax(self.residuals_mm))])

    def to_display(self, xy: np.ndarray) -> np.ndarray:
        """Points (n, 2) of the DIC's frame in the display's (mm)."""
        return self.scale * (np.asarray(xy, dtype=float) @ self.rotation) + self.translation

    def check(self, limit_mm: float) -> None:
        """A :class:`MeasurementError` when the fiducials' RMS residual exceeds ``limit_mm``."""
        if self.rms_mm > limit_mm:
            raise MeasurementError(
                f"{self.source}: the {self.mode} fit of {len(self.pixels)} fiducials misses by "
                f"{self.rms_mm:.3g} mm RMS, beyond the protocol's {limit_mm:g} mm; the worst "
                f"is pixel {self.worst_pixel} ({self.max_mm:.3g} mm): is it marked on the "
                f"right pixel?")

    def to_dict(self) -> dict:
        return {"mode": self.mode, "rotation_deg": self.rotation_deg, "scale": self.scale,
                "translation_mm": [float(v) for v in self.translation],
                "fiducials": len(self.pixels), "rms_mm": self.rms_mm, "max_mm": self.max_mm,
                "worst_pixel": self.worst_pixel, "source": self.source,
                "residuals_mm": {int(p): float(r)
                                 for p, r in zip(self.pixels, self.residuals_mm, strict=True)}}


def fit_registration(fiducials: Fiducials, layout: Layout,
                     mode: Literal["rigid", "similarity"] = "rigid") -> Registration:
    """Least-squares rigid or similarity map of ``fiducials`` onto ``layout``'s pixels."""
    source = fiducials.source
    if mode not in ("rigid", "similarity"):
        raise MeasurementError(f"registration {mode!r}: expected rigid or similarity")
    if len(fiducials.pixels) < MIN_FIDUCIALS:
        raise MeasurementError(f"{source}: {len(fiducials.pixels)} fiducial(s); expected at "
                               f"least {MIN_FIDUCIALS} marked pixels")
    outside = fiducials.pixels[fiducials.pixels >= layout.n_pixels]
    if len(outside):
        raise MeasurementError(f"{source}: pixel {int(outside[0])} is not on {layout.name} "
                               f"(pixels 0..{layout.n_pixels - 1})")
    a = fiducials.xy
    b = layout.pixel_xy[fiducials.pixels]
    a_mean, b_mean = a.mean(axis=0), b.mean(axis=0)
    ac, bc = a - a_mean, b - b_mean
    spread = np.linalg.svd(ac, compute_uv=False)
    if not spread[0] > 0:
        raise MeasurementError(f"{source}: the fiducials all sit at one point")
    collinear = spread[1] <= 1e-9 * spread[0]
    rotation, _ = orthogonal_procrustes(ac, bc)
    if np.linalg.det(rotation) < 0:
        if not collinear:
            raise MeasurementError(
                f"{source}: the fiducials fit the pixels only as a mirror image; is the "
                "DIC's y axis flipped, or are the pixels numbered the other way round?")
        # on a line a mirror across it fits as well: take the rotation onto the same line
        u = np.linalg.svd(ac)[2][0]
        v = bc.T @ (ac @ u)
        angle = math.atan2(v[1], v[0]) - math.atan2(u[1], u[0])
        c, s = math.cos(angle), math.sin(angle)
        rotation = np.array([[c, s], [-s, c]])
    scale = 1.0
    if mode == "similarity":
        scale = float(np.sum(bc * (ac @ rotation)) / np.sum(ac * ac))
        if not scale > 0:
            raise MeasurementError(f"{source}: the similarity fit has no positive scale")
    translation = b_mean - scale * (a_mean @ rotation)
    fitted = scale * (a @ rotation) + translation
    residuals = np.hypot(*(fitted - b).T)
    return Registration(mode, rotation, scale, translation, fiducials.pixels.copy(), residuals,
                        source)
