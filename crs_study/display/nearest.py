"""The ``nearest`` display model: pixel-only theory, the skin meets the nearest pixel's height.

The paper's pixel-only display (Wang, Meng & Chen 2025, Fig. 2d, Eqs. 1, 2, 5, 6): with no
connection between pixels the displayed surface over each pixel's Voronoi cell is that pixel's
height, so

    psi(x) = h_k,   k = argmin_j |x - p_j|

1D (``lattice = "line"``): a staircase in x with steps half-way between pixels (y ignored).
2D: constant on the Voronoi cells (hexagons on the hex lattice, squares on a square one).
Beyond the pixels (farther from every pixel than the circumradius of a lattice cell: d/2 on a
line, d/sqrt(3) hexagonal, d/sqrt(2) square) the surface is the base, 0.

The surface peaks on the whole cell of the highest pixel; :meth:`NearestPixel.peak_xy` gives
the cell's centroid, the pixel itself, as the paper's theory does (D_P = 0.25 d/l in 1D).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from crs_study.display.base import DisplayModel, register
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import Layout

#: Circumradius of a lattice cell in pitches: the farthest a point of the display can be from
#: its nearest pixel.
CELL_CIRCUMRADIUS = {"line": 0.5, "hex": 1.0 / math.sqrt(3.0), "square": 1.0 / math.sqrt(2.0)}


def pixel_heights(layout: Layout, setpoints_mm: np.ndarray) -> np.ndarray:
    """The pixel part of a setpoint vector (mm), checked for length."""
    setpoints = np.asarray(setpoints_mm, dtype=float)
    if setpoints.shape != (layout.n_actuators,) and setpoints.shape != (layout.n_pixels,):
        raise DisplayModelError(
            f"{layout.name}: expected {layout.n_actuators} setpoints (or {layout.n_pixels} "
            f"pixel heights), got shape {setpoints.shape!r}"
        )
    return setpoints[: layout.n_pixels]


def highest_pixel_xy(layout: Layout, heights: np.ndarray) -> np.ndarray:
    """Position of the highest pixel; the mean position when several tie (within 1e-12)."""
    top = heights.max()
    tied = heights >= top - 1e-12 * max(abs(top), 1.0)
    return layout.pixel_xy[tied].mean(axis=0)


@register
class NearestPixel(DisplayModel):
    """Each point shows the height of its nearest pixel (pixel-only display)."""

    name = "nearest"
    description = "pixel-only theory: the skin meets the nearest pixel's height (Voronoi cells)"

    def __init__(self, layout: Layout) -> None:
        super().__init__(layout)
        self._line = layout.lattice == "line"
        self._reach = CELL_CIRCUMRADIUS.get(layout.lattice, 1.0) * layout.pitch_mm * (1 + 1e-9)
        if self._line:
            self._order = np.argsort(layout.pixel_xy[:, 0], kind="stable")
            x = layout.pixel_xy[self._order, 0]
            self._x = x
            self._midpoints = 0.5 * (x[1:] + x[:-1])
        else:
            self._tree = cKDTree(layout.pixel_xy)

    def surface(self, setpoints_mm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        heights = pixel_heights(self.layout, setpoints_mm)
        xy = np.asarray(xy_mm, dtype=float).reshape(-1, 2)
        if self._line:
            slot = np.searchsorted(self._midpoints, xy[:, 0])
            distance = np.abs(xy[:, 0] - self._x[slot])
            index = self._order[slot]
        else:
            distance, index = self._tree.query(xy)
        return np.where(distance <= self._reach, heights[index], 0.0)

    def peak_xy(self, setpoints_mm: np.ndarray) -> np.ndarray:
        """Where the surface peaks: the centroid of the highest cell, i.e. the highest pixel."""
        return highest_pixel_xy(self.layout, pixel_heights(self.layout, setpoints_mm))
