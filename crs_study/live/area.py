"""The recognition area, and a finger packet's position turned into the bump of Eq. 7.

The paper's scene sends the fingertip "relative to the center of the CRS recognition area"
(Wang, Meng & Chen 2025, Methods): a packet's (x_f, y_f) are millimetres from the
display's centre (:func:`crs_study.stimuli.stimulus.display_centre`, the centroid of the pixels, the
centre pixel on crs2d), in the device file's axes. The area is where a finger makes a bump:

* a 2D display: the convex hull of the pixel centres, grown by ``margin_mm`` (each edge moved
  out by the margin, corners kept sharp);
* a line of pixels (1D): x between the end pixels, grown by ``margin_mm``; y_f is ignored, as
  the renderer ignores it.

A finger outside flattens the display, as leaving the paper's recognition area does. The bump
is Eq. 7 centred under the finger, diameter ``diameter_mm`` (90 mm in the paper), height the
press depth z_f capped at ``max_height_mm`` (the pixels' travel unless told); z_f <= 0 is a
finger that does not press, a flat display.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crs_study.geometry.layout import Layout
from crs_study.live.errors import LiveError
from crs_study.stimuli.stimulus import display_centre
from crs_study.stimuli.targets import Bump

#: The paper's bump diameter (Eq. 7).
PAPER_DIAMETER_MM = 90.0


@dataclass(frozen=True, eq=False)
class RecognitionArea:
    """Where a finger makes a bump on ``layout`` (module docstring). Build with
    :meth:`for_layout`."""

    layout: Layout
    centre_mm: tuple[float, float]
    margin_mm: float
    diameter_mm: float
    max_height_mm: float
    #: 2D: hull edge lines (a, b, c), a x + b y + c <= 0 inside, (a, b) unit; 1D: None
    edges: np.ndarray | None
    x_range: tuple[float, float]  # 1D: x limits (layout frame, margin included)
    edge_rows: tuple[tuple[float, float, float], ...] = ()  # ``edges`` as plain floats

    @classmethod
    def for_layout(cls, layout: Layout, margin_mm: float = 0.0,
                   diameter_mm: float = PAPER_DIAMETER_MM,
                   max_height_mm: float | None = None) -> RecognitionArea:
        for name, value, low in (("area margin", margin_mm, 0.0),
                                 ("bump diameter", diameter_mm, None)):
            if not _finite(value) or (value < low if low is not None else value <= 0):
                bound = ">= 0" if low is not None else "> 0"
                raise LiveError(f"{name}: expected a number of mm {bound}, got {value!r}")
        height = layout.travel_mm if max_height_mm is None else max_height_mm
        if not _finite(height) or not 0 < height <= layout.travel_mm:
            raise LiveError(f"largest bump height: expected mm in (0, {layout.travel_mm:g}] "
                            f"(the pixels' travel), got {max_height_mm!r}")
        xy = layout.pixel_xy
        edges = None
        if layout.lattice != "line":
            from scipy.spatial import ConvexHull

            edges = ConvexHull(xy).equations.copy()
            edges.setflags(write=False)
        x_range = (float(xy[:, 0].min()) - margin_mm, float(xy[:, 0].max()) + margin_mm)
        rows = () if edges is None else tuple(map(tuple, edges.tolist()))
        return cls(layout, display_centre(layout), float(margin_mm), float(diameter_mm),
                   float(height), edges, x_range, rows)

    def to_layout(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """A packet's (x_f, y_f) in the device file's frame."""
        return self.centre_mm[0] + x_mm, self.centre_mm[1] + y_mm

    def contains(self, x_mm: float, y_mm: float) -> bool:
        """Whether a finger at packet coordinates (x_f, y_f) is inside the area."""
        x, y = self.to_layout(x_mm, y_mm)
        if self.edges is None:
            return self.x_range[0] <= x <= self.x_range[1]
        limit = self.margin_mm + 1e-9
        # plain floats: for a handful of edges, numpy's per-call cost is most of the work
        return all(a * x + b * y + c <= limit for a, b, c in self.edge_rows)

    def bump(self, x_mm: float, y_mm: float, z_mm: float) -> Bump | None:
        """The bump under a finger at (x_f, y_f, z_f); None when the finger is outside the
        area (a flat display). Height: z_f within [0, max_height_mm]."""
        placed = self.place(x_mm, y_mm, z_mm)
        return None if placed is None else Bump(placed[:2], self.diameter_mm, placed[2])

    def place(self, x_mm: float, y_mm: float, z_mm: float
              ) -> tuple[float, float, float] | None:
        """:meth:`bump`'s centre (layout frame) and height as plain floats, without building
        the Bump (the live loop's path to :meth:`Renderer.render_bump`); None outside."""
        if not self.contains(x_mm, y_mm):
            return None
        x, y = self.to_layout(x_mm, y_mm)
        return x, y, min(max(float(z_mm), 0.0), self.max_height_mm)

    def describe(self) -> str:
        if self.edges is None:
            lo, hi = (x - self.centre_mm[0] for x in self.x_range)
            return f"x_f in [{lo:g}, {hi:g}] mm"
        reach = float(np.max(np.hypot(*(self.layout.pixel_xy - self.centre_mm).T)))
        return (f"the pixels' hull (corners {reach:g} mm from the centre) grown by "
                f"{self.margin_mm:g} mm")


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) \
        and math.isfinite(value)
