"""The ``linear`` display model: straight connections between the pixel tips.

The paper's "linear connection" (origami-like displays; Wang, Meng & Chen 2025, Fig. 2d;
docs/physics.md, "Display models"): in 1D the surface is the piecewise-linear interpolant of
the pixel heights, in 2D the piecewise-linear interpolant on the Delaunay triangulation of the
pixel positions (barycentric weights within each triangle). Outside the pixels' convex hull the
surface is the base, 0. On the hexagonal lattice the Delaunay triangulation is unique
(equilateral triangles); on a square lattice four points are co-circular and Qhull picks one
diagonal per square, so the model is not symmetric there. A 2D layout whose pixels all lie on
one line is interpolated along that line.

Its maximum lies at a pixel (a linear function peaks at a vertex), so the peak position
distortion equals the pixel-only one (paper: D_P = 0.25 d/l in 1D for both).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from crs_study.display.base import DisplayModel, register
from crs_study.display.nearest import highest_pixel_xy, pixel_heights
from crs_study.geometry.layout import Layout


@register
class LinearConnection(DisplayModel):
    """Piecewise-linear surface through the pixel tips, zero outside their hull."""

    name = "linear"
    description = "linear connection between pixel tips (1D interpolant, 2D Delaunay triangles)"

    def __init__(self, layout: Layout) -> None:
        super().__init__(layout)
        xy = layout.pixel_xy
        centred = xy - xy.mean(axis=0)
        self._tol = 1e-9 * layout.pitch_mm
        flat = len(xy) < 3 or np.linalg.matrix_rank(centred, tol=self._tol) < 2
        self._line = layout.lattice == "line" or flat
        if self._line:
            self._check_offset = layout.lattice != "line" and len(xy) >= 2
            self._origin, self._axis = np.zeros(2), np.array([1.0, 0.0])
            if self._check_offset:
                self._origin, self._axis = xy.mean(axis=0), np.linalg.svd(centred)[2][0]
            t = (xy - self._origin) @ self._axis
            self._order = np.argsort(t, kind="stable")
            self._t = t[self._order]
        else:
            self._tri = Delaunay(xy)

    def surface(self, setpoints_mm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        heights = pixel_heights(self.layout, setpoints_mm)
        xy = np.asarray(xy_mm, dtype=float).reshape(-1, 2)
        if self._line:
            rel = xy - self._origin
            t = rel[:, 0] * self._axis[0] + rel[:, 1] * self._axis[1]  # no BLAS gemv
            z = np.interp(t, self._t, heights[self._order], left=0.0, right=0.0)
            if self._check_offset:
                off = np.abs(rel[:, 0] * self._axis[1] - rel[:, 1] * self._axis[0])
                z = np.where(off <= self._tol, z, 0.0)
            return z
        tri = self._tri
        simplex = tri.find_simplex(xy, tol=self._tol)
        inside = simplex >= 0
        s = simplex[inside]
        transform = tri.transform[s]
        b = np.einsum("ijk,ik->ij", transform[:, :2], xy[inside] - transform[:, 2])
        weights = np.column_stack([b, 1.0 - b.sum(axis=1)])
        z = np.zeros(len(xy))
        z[inside] = np.sum(weights * heights[tri.simplices[s]], axis=1)
        return z

    def peak_xy(self, setpoints_mm: np.ndarray) -> np.ndarray:
        """Where the surface peaks: the highest pixel (the mean position of tied ones)."""
        return highest_pixel_xy(self.layout, pixel_heights(self.layout, setpoints_mm))
