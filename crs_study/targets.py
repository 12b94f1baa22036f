"""Target surfaces: what the display should show.

The stimulus of the paper is a raised-cosine bump (crs-paper.md, Eq. 7)::

    z(x, y) = z_f / 2 * [1 + cos(2 pi rho / l)],   rho = |(x, y) - (x_f, y_f)| <= l / 2
    z(x, y) = 0                                     otherwise

with diameter l (90 mm in the paper), height z_f and centre (x_f, y_f) anywhere. The 1D
counterpart is the same profile in x alone (rho = |x - x_f|). All lengths in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crs_study.errors import RenderError


@dataclass(frozen=True)
class Bump:
    """The raised-cosine bump of Eq. 7.

    Parameters
    ----------
    centre_mm : (x_f, y_f); y_f is ignored on a 1D (line) device.
    diameter_mm : l, the bump's diameter (support), > 0.
    height_mm : z_f, the height at the centre, >= 0.
    """

    centre_mm: tuple[float, float]
    diameter_mm: float
    height_mm: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.diameter_mm) and self.diameter_mm > 0):
            raise RenderError(f"bump diameter must be > 0 mm, got {self.diameter_mm!r}")
        if not (np.isfinite(self.height_mm) and self.height_mm >= 0):
            raise RenderError(f"bump height must be >= 0 mm, got {self.height_mm!r}")
        if not all(np.isfinite(self.centre_mm)):
            raise RenderError(f"bump centre must be finite, got {self.centre_mm!r}")

    def radius(self, xy_mm: np.ndarray) -> np.ndarray:
        """Distance rho from the centre for points (..., 2)."""
        xy = np.asarray(xy_mm, dtype=float)
        return np.hypot(xy[..., 0] - self.centre_mm[0], xy[..., 1] - self.centre_mm[1])

    def height(self, xy_mm: np.ndarray) -> np.ndarray:
        """z at points (..., 2), Eq. 7."""
        rho = self.radius(xy_mm)
        z = 0.5 * self.height_mm * (1.0 + np.cos(2.0 * np.pi * rho / self.diameter_mm))
        return np.where(rho <= 0.5 * self.diameter_mm, z, 0.0)

    def slope_along(self, xy_mm: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Directional derivative dz/ds at points (..., 2) along a unit ``direction``.

        dz/drho = -(pi z_f / l) sin(2 pi rho / l) inside the support, 0 outside;
        dz/ds = dz/drho * (p - c) . u / rho (0 at the centre, where the gradient vanishes).
        """
        xy = np.asarray(xy_mm, dtype=float)
        rho = self.radius(xy)
        l = self.diameter_mm
        dz_drho = np.where(rho <= 0.5 * l,
                           -np.pi * self.height_mm / l * np.sin(2.0 * np.pi * rho / l), 0.0)
        dx = xy[..., 0] - self.centre_mm[0]
        dy = xy[..., 1] - self.centre_mm[1]
        along = dx * direction[0] + dy * direction[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_angle = np.where(rho > 0, along / np.where(rho > 0, rho, 1.0), 0.0)
        return dz_drho * cos_angle

    def curvature_max(self) -> float:
        """Largest |z''| of the profile, at the centre: 2 pi^2 z_f / l^2 (1/mm)."""
        return 2.0 * np.pi**2 * self.height_mm / self.diameter_mm**2

    def moved_to(self, centre_mm: tuple[float, float]) -> Bump:
        return Bump((float(centre_mm[0]), float(centre_mm[1])), self.diameter_mm, self.height_mm)


#: Gauss-Legendre nodes per segment for arc-length integrals (exact to ~1e-9 of the length
#: for the bump at any d/l the devices use; see tests/test_targets.py).
_ARC_NODES, _ARC_WEIGHTS = np.polynomial.legendre.leggauss(24)


def arc_length(target: Bump, start_mm: tuple[float, float], end_mm: tuple[float, float],
               breakpoints: int = 16) -> float:
    """Arc length of the target's section along the straight segment start->end.

    L = integral_0^S sqrt(1 + (dz/ds)^2) ds, by composite Gauss-Legendre quadrature on
    ``breakpoints`` equal panels (the integrand is smooth except where the segment meets the
    bump's rim, where only the second derivative jumps).
    """
    start = np.asarray(start_mm, dtype=float)
    end = np.asarray(end_mm, dtype=float)
    span = float(np.linalg.norm(end - start))
    if span == 0.0:
        return 0.0
    unit = (end - start) / span
    edges = np.linspace(0.0, span, breakpoints + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    s = (mid[:, None] + half[:, None] * _ARC_NODES[None, :]).ravel()
    weights = (half[:, None] * _ARC_WEIGHTS[None, :]).ravel()
    points = start[None, :] + s[:, None] * unit[None, :]
    slope = target.slope_along(points, unit)
    return float(np.sum(weights * np.sqrt(1.0 + slope**2)))
