"""The distortions of one measured shape, as the paper defines them.

For a bump of diameter l at X_i (Eq. 7) and the measured surface psi (heights above the
reference capture, registered to the display's frame)::

    |x_r - X_i| / l                                                (the term of Eqs. 1, 5)
    sqrt( int_S (phi - psi)^2 / int_S phi^2 ),  S = {|x - X_i| <= l/2}   (Eqs. 2, 6)

(Wang, Meng & Chen, "Continuity reinforcement skeleton for pixel-based haptic display",
Nature Communications.) The integrals use the quadrature of the model criteria
(:func:`~crs_study.quality.criteria.support_rule`), psi taken at its nodes by linear
interpolation of the measured points (:class:`scipy.interpolate.LinearNDInterpolator` on their
Delaunay triangulation; in 1D :func:`numpy.interp` along the beam's strip). A node farther
than :data:`GAP_SPACINGS` point spacings from every measured point is a hole: beyond the
protocol's ``max_hole_fraction`` of the support (by quadrature weight) the shape is refused in
one line; below it holes take the nearest point's height.

The peak x_r is found to a fraction of the point spacing by a local fit: the highest measured
point within l/2 + d/2 of X_i, then the vertex of a least-squares quadratic over the points
within :func:`window_radius` of it (refitted once about the vertex), when the quadratic fits
them to the noise. A top it does not fit has no vertex to find: a plateau (the pixel-only
display's, over the highest pixel's cell: Eq. 1's "pixel display"), a kink (the linear
connection's top at a pixel) or a ridge (a tent of fabric along a beam). There x_r is the
centroid of the summit, the points within three noise levels (and :data:`TOP_FRACTION` of
the height) of the top, as the pixel-only theory takes the plateau's centre. The noise level
is a robust estimate from the points themselves (the median absolute difference between each
point and the quadratic through its nearest neighbours).

A summit is found against the highest point, which noise lifts, so a noisy summit is not the
noise-free one; the model is therefore read with the measurement's noise added
(:meth:`SampledSurface.with_heights`), and the two are compared estimator for estimator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from crs_study.errors import MeasurementError
from crs_study.geometry.layout import Layout
from crs_study.quality.criteria import support_rule
from crs_study.stimuli.targets import Bump

#: A quadrature node farther than this many point spacings from every point is a hole.
GAP_SPACINGS = 2.5
#: Neighbours of each point in the noise estimate (along a profile, over a surface).
NOISE_NEIGHBOURS = {True: 6, False: 12}
#: Fewest measured points the support of a shape may hold.
MIN_SUPPORT_POINTS = 10
#: Points are triangulated moved by up to this many spacings, from a fixed seed, so that a
#: regular grid is in general position (see :meth:`SampledSurface.at`).
JITTER_SPACINGS = 1e-6
JITTER_SEED = 20140527
#: A top fits a quadratic when the fit misses by less than twice the noise plus this
#: fraction of the top's height; the summit of a top that does not (a plateau, a kink, a
#: ridge) is the set of points within three noise levels plus this fraction of the top.
TOP_FRACTION = 1e-3


def window_radius(spacing: float, diameter: float) -> float:
    """Half-width of the local peak fit: a twentieth of the bump, at least four spacings."""
    return max(4.0 * spacing, diameter / 20.0)


@dataclass(frozen=True)
class ShapeMeasure:
    """The distortion terms of one shape and how they were found."""

    D_P: float  # |x_r - X_i| / l
    D_S: float  # Eq. 2 (1D) or Eq. 6 (2D)
    peak_mm: tuple[float, float]  # x_r (y_r)
    peak_fit: str  # "quadratic" or "summit"
    holes: float  # fraction of the support (by quadrature weight) without data
    points: int  # measured points in the support


class SampledSurface:
    """Heights at measured points of the display's frame, ready for the criteria.

    On a line of pixels only the points of the strip ``|y - y_line| <= strip_mm`` along the
    beam are kept and heights at one x are averaged: the surface is then a profile in x.
    :meth:`with_heights` gives another surface at the same points (the model as the DIC sampled
    it) sharing the neighbour search and the triangulation.
    """

    def __init__(self, xy: np.ndarray, heights: np.ndarray, *, line_y: float | None = None,
                 strip_mm: float | None = None) -> None:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        heights = np.asarray(heights, dtype=float).reshape(-1)
        keep = np.isfinite(xy).all(axis=1) & np.isfinite(heights)
        self.line = line_y is not None
        if self.line:
            keep &= np.abs(xy[:, 1] - line_y) <= strip_mm
            if keep.sum() < 2:
                raise MeasurementError(f"{int(keep.sum())} measured point(s) in the strip "
                                       f"along the beam; expected at least "
                                       f"{MIN_SUPPORT_POINTS}")
            # the strip's points in bins of one point spacing along x: the profile
            strip = xy[keep]
            step = float(np.median(cKDTree(strip).query(strip, k=2)[0][:, 1]))
            bins = np.round((strip[:, 0] - strip[:, 0].min()) / max(step, 1e-9)).astype(int)
            _, inverse = np.unique(bins, return_inverse=True)
            counts = np.bincount(inverse)
            xs = np.bincount(inverse, weights=strip[:, 0]) / counts
            self.xy = np.column_stack([xs, np.full(len(xs), float(line_y))])
            self.heights = np.bincount(inverse, weights=heights[keep]) / counts
            self._coords = xs[:, None]
        else:
            self.xy, self.heights = xy[keep], heights[keep]
            self._coords = self.xy
        if len(self.heights) < MIN_SUPPORT_POINTS:
            where = " in the strip along the beam" if self.line else ""
            raise MeasurementError(f"{len(self.heights)} measured point(s){where}; expected at "
                                   f"least {MIN_SUPPORT_POINTS}")
        self.tree = cKDTree(self._coords)
        distances = self.tree.query(self._coords, k=2)[0][:, 1]
        self.spacing = float(np.median(distances))
        self.noise_mm = self._noise()
        self._interpolator = None
        self._subset: np.ndarray | None = None

    def with_heights(self, heights: np.ndarray, rng: np.random.Generator | None = None
                     ) -> SampledSurface:
        """The same points (as kept here) with other heights, read with this surface's noise
        level; with ``rng``, that noise is added to them (Gaussian, of :attr:`noise_mm`).

        The model as the DIC would measure it: sampled at the same points, as noisy, and read
        by the very fit the measurement went through (the same tolerances). A top's summit
        is found against the highest point, which noise lifts; given the same noise the
        model's summit is lifted alike, so the two differ by their surfaces, not by the
        estimator."""
        other = object.__new__(SampledSurface)
        other.__dict__.update(self.__dict__)
        other.heights = np.asarray(heights, dtype=float).reshape(-1)
        if rng is not None:
            other.heights = other.heights + rng.normal(0.0, self.noise_mm, len(other.heights))
        if self._interpolator is not None:
            from scipy.interpolate import LinearNDInterpolator

            other._interpolator = LinearNDInterpolator(self._interpolator.tri,
                                                       other.heights[self._subset])
        return other

    def _noise(self) -> float:
        """The measurement's noise: each point's height minus the quadratic fitted by least
        squares to its nearest neighbours (a parabola along a profile), scaled by the fit's own
        error at the point (sqrt(1 + h), h the variance factor of the fit's value there); the
        median absolute deviation of those residuals, times 1.4826, a standard deviation. A
        smooth surface's slope and curvature leave no residual, so the bump's top does not
        pass for noise."""
        k = min(NOISE_NEIGHBOURS[self.line], len(self.heights) - 1)
        index = self.tree.query(self._coords, k=k + 1)[1][:, 1:]
        d = self._coords[index] - self._coords[:, None, :]
        terms = [np.ones(index.shape)]
        terms += [d[..., 0], d[..., 0] ** 2] if self.line else \
            [d[..., 0], d[..., 1], d[..., 0] ** 2, d[..., 0] * d[..., 1], d[..., 1] ** 2]
        basis = np.stack(terms, axis=2)
        normal = np.einsum("nki,nkj->nij", basis, basis)
        rhs = np.einsum("nki,nk->ni", basis, self.heights[index])
        usable = np.abs(np.linalg.det(normal)) > 1e-12 * np.abs(normal).max(axis=(1, 2)) ** \
            basis.shape[2]
        if not usable.any():
            return 0.0
        inverse = np.linalg.inv(normal[usable])
        fitted = np.einsum("nj,nj->n", inverse[:, 0, :], rhs[usable])
        residual = (self.heights[usable] - fitted) / np.sqrt(1.0 + inverse[:, 0, 0])
        return 1.4826 * float(np.median(np.abs(residual - np.median(residual))))

    def at(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Heights at ``points`` (n, 2) and which of them are holes (no point near)."""
        coords = points[:, :1] if self.line else points
        distance, nearest = self.tree.query(coords)
        holes = distance > GAP_SPACINGS * self.spacing
        if self.line:
            values = np.interp(points[:, 0], self._coords[:, 0], self.heights)
        else:
            if self._interpolator is None:
                # triangulate the points about the nodes only (the support, not the field).
                # A DIC's regular grid has four points on every circle and straight rows on
                # its edge: degenerate for Delaunay (ten times slower to evaluate, and Qhull's
                # own joggle is seeded by the clock and leaves slivers that are flat in the
                # stored coordinates, whose barycentric weights overflow). The points are
                # moved by a fixed, seeded millionth of a spacing and triangulated and
                # interpolated at those very coordinates: reproducible, and every value a
                # convex combination of measured heights.
                from scipy.interpolate import LinearNDInterpolator
                from scipy.spatial import Delaunay

                centre = points.mean(axis=0)
                reach = float(np.max(np.hypot(*(points - centre).T)))
                self._subset = self.near(centre, reach + GAP_SPACINGS * 2 * self.spacing)
                coords = self._coords[self._subset]
                jitter = np.random.default_rng(JITTER_SEED).uniform(-1.0, 1.0, coords.shape)
                triangulation = Delaunay(coords + JITTER_SPACINGS * self.spacing * jitter)
                self._interpolator = LinearNDInterpolator(triangulation,
                                                          self.heights[self._subset])
            values = self._interpolator(points)
        values = np.where(np.isfinite(values), values, self.heights[nearest])
        return values, holes

    def near(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """Indices of the points within ``radius`` of ``centre``."""
        coords = centre[:1] if self.line else centre
        return np.asarray(self.tree.query_ball_point(coords, radius), dtype=int)

    def local_mean(self, points: np.ndarray, radius: float) -> np.ndarray:
        """Mean height of the points within ``radius`` of each of ``points`` (NaN: none)."""
        out = np.full(len(points), np.nan)
        for k, point in enumerate(points):
            index = self.near(np.asarray(point, dtype=float), radius)
            if len(index):
                out[k] = float(self.heights[index].mean())
        return out


def find_peak(surface: SampledSurface, centre: np.ndarray, diameter: float, pitch: float
              ) -> tuple[np.ndarray, str]:
    """x_r (as a 2-vector) and how it was found (module docstring)."""
    candidates = surface.near(centre, 0.5 * diameter + 0.5 * pitch)
    if not len(candidates):
        raise MeasurementError(f"no measured point within {0.5 * diameter + 0.5 * pitch:.3g} "
                               f"mm of the bump centre ({centre[0]:.2f}, {centre[1]:.2f}) mm")
    heights = surface.heights[candidates]
    top = float(heights.max())
    start = surface.xy[candidates[int(np.argmax(heights))]]
    radius = window_radius(surface.spacing, diameter)
    vertex = _smooth_vertex(surface, start, radius, top)
    if vertex is not None:
        refit = _smooth_vertex(surface, vertex, radius, top)
        return (vertex if refit is None else refit), "quadratic"
    tolerance = 3.0 * surface.noise_mm + TOP_FRACTION * abs(top)
    summit = candidates[heights >= top - tolerance]
    return surface.xy[summit].mean(axis=0), "summit"


def _smooth_vertex(surface: SampledSurface, about: np.ndarray, radius: float, top: float
                   ) -> np.ndarray | None:
    """The vertex of a least-squares quadratic over the points within ``radius`` of
    ``about``, when the quadratic fits them to the noise (a smooth top, not a plateau's edge,
    a tent's kink or a ridge), is a maximum standing out of the noise and lies in the window;
    else None."""
    index = surface.near(about, radius)
    z = surface.heights[index]
    noise = surface.noise_mm
    if surface.line:
        if len(index) < 4:
            return None
        u = surface.xy[index, 0] - about[0]
        c2, c1, c0 = np.polyfit(u, z, 2)
        fitted = c0 + u * (c1 + u * c2)
        if not c2 < 0:
            return None
        shift = np.array([-c1 / (2.0 * c2), 0.0])
        drop = -c2 * radius**2
    else:
        if len(index) < 7:
            return None
        u, v = (surface.xy[index] - about).T
        basis = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
        c = np.linalg.lstsq(basis, z, rcond=None)[0]
        fitted = basis @ c
        hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        eigen = np.linalg.eigvalsh(hessian)
        if not eigen[-1] < 0:
            return None
        shift = np.linalg.solve(hessian, -c[1:3])
        drop = -0.5 * eigen[-1] * radius**2
    misfit = float(np.sqrt(np.mean((z - fitted) ** 2)))
    if misfit > 2.0 * noise + TOP_FRACTION * abs(top):
        return None  # not a smooth top: a plateau's edge, a kink or a ridge
    if not drop > 6.0 * noise + TOP_FRACTION * abs(top):
        return None  # flat to the noise: a plateau
    if not np.hypot(*shift) <= radius:
        return None
    return about + shift


def measure_shape(surface: SampledSurface, bump: Bump, layout: Layout, *,
                  max_hole_fraction: float, resolution: int = 12) -> ShapeMeasure:
    """The terms of Eqs. 1-2 (1D) or 5-6 (2D) for ``bump`` shown as ``surface``."""
    centre = np.asarray(bump.centre_mm, dtype=float)
    nodes, weights = support_rule(layout, bump, resolution)
    if surface.line:
        nodes = np.column_stack([nodes[:, 0], np.full(len(nodes), surface.xy[0, 1])])
    psi, holes = surface.at(nodes)
    hole_fraction = float(weights[holes].sum() / weights.sum())
    if hole_fraction > max_hole_fraction:
        raise MeasurementError(
            f"{hole_fraction:.1%} of the bump's support (l = {bump.diameter_mm:g} mm at "
            f"({centre[0]:.2f}, {centre[1]:.2f}) mm) has no measured point within "
            f"{GAP_SPACINGS * surface.spacing:.3g} mm, beyond the protocol's "
            f"max_hole_fraction of {max_hole_fraction:g}")
    in_support = surface.near(centre, 0.5 * bump.diameter_mm)
    if len(in_support) < MIN_SUPPORT_POINTS:
        raise MeasurementError(f"{len(in_support)} measured point(s) in the bump's support at "
                               f"({centre[0]:.2f}, {centre[1]:.2f}) mm; expected at least "
                               f"{MIN_SUPPORT_POINTS}")
    phi = bump.height(nodes)
    shape = math.sqrt(float(weights @ (phi - psi) ** 2) / float(weights @ phi**2))
    peak, fit = find_peak(surface, centre, bump.diameter_mm, layout.pitch_mm)
    offset = peak - centre
    lead = abs(offset[0]) if surface.line else math.hypot(*offset)
    return ShapeMeasure(lead / bump.diameter_mm, shape, (float(peak[0]), float(peak[1])), fit,
                        hole_fraction, len(in_support))
