"""Beam networks and the fabric between them: the shared 1D/2D machinery of the beam models.

A beam model (``spline``, ``beam``, ``reference``) solves each beam of the layout in its own
vertical plane along its lattice line, as a 1D problem in the coordinate ``s`` (mm from the
start clamp, ``0 <= s <= S``). Crossing beams share the pixel supports, so they agree at the
pixels. :class:`NetworkModel` turns the beam shapes into a surface:

1D (``lattice == "line"``)
    the surface is the beam: z(x, y) = y_beam(s), s = (p - start) . u, and 0 beyond the clamps.
2D (``lattice == "hex"``)
    the beams are sampled at fine-lattice nodes along their lines and the fabric between them
    is a taut membrane (:class:`Fabric`).

The fabric model
----------------
The published 2D device covers the beams with spandex fabric, sewn to each pixel and stretched
over the frame (Wang, Meng & Chen 2025, Methods). Spandex has no bending stiffness worth
speaking of; pre-stretched, it carries an (assumed uniform, isotropic) tension T. With no load
between the supports, small-slope membrane equilibrium is Laplace's equation::

    T (z_xx + z_yy) = 0   between the beams,
    z = y_beam(s)         on every beam line (the fabric rests on the beams),
    z = 0                 on the display border (the convex hull of the clamps).

Why a membrane and not, e.g., a thin-plate spline through the beam samples: the fabric cannot
resist bending, so a plate's curvature-minimising overshoot between beams is not physical; and
a membrane obeys the maximum principle, so it never shows a peak the beams do not carry (the
paper: the CRS "expands the haptic feedback area from dots to a network woven by skeletons").
Known limits: the fabric is assumed bilaterally attached to the beams (it does not lift off a
beam that curves downwards), and its tension is assumed uniform.

Discretisation: linear finite elements on the triangular lattice refined ``m`` times
(``fabric_subdivisions``, spacing h = d/m), which contains every beam line, so beam samples are
nodes. On equilateral triangles the FE Laplacian is the 6-neighbour stencil
``6 z_i - sum(z_j) = 0``. The map from beam samples to free-node heights is linear and fixed
per layout, so the membrane matrix is factorised once (sparse LU); a frame costs one sparse
solve plus a barycentric lookup per query point. Everything that depends on the query points
alone (barycentric weights, which beam corrects which point, each beam abscissa's segment) is
planned once per point set and kept (LRU of 16 sets): the observer and the quality criteria
ask for the same points frame after frame. The correction weights are computed from the few
(beam, point) pairs within one fine spacing of a beam, not densely over all beams and points.
No BLAS call is made per frame on n x 2 arrays (threaded OpenBLAS gemv is ~80x slower on a
busy two-core machine). On the beam lines the surface equals the beam profile exactly (a
correction term confined to the triangles touching the beam replaces the piecewise-linear
sampling there, see ``Fabric._correction_terms``).
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.linalg import splu
from scipy.spatial import ConvexHull

from crs_study.display.base import DisplayModel
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import Beam, Layout, fabric_mesh_for_margin

#: fine-lattice subdivisions of one pitch for the fabric (h = d / 8 = 3.75 mm at d = 30 mm);
#: finer when the beam clamps need it (:func:`crs_study.geometry.layout.fabric_mesh_for_margin`)
DEFAULT_FABRIC_SUBDIVISIONS = 8
#: point sets whose surface plan a fabric keeps (LRU)
_PLANS_KEPT = 16

_SQRT3_2 = math.sqrt(3.0) / 2.0


def beam_support_positions(layout: Layout, beam: Beam) -> np.ndarray:
    """Positions s (mm from the start clamp) of the clamp, the beam's pixels, and the end clamp."""
    start = np.asarray(beam.start, dtype=float)
    s_pixels = (layout.pixel_xy[list(beam.pixels)] - start) @ beam.direction
    return np.concatenate([[0.0], s_pixels, [beam.straight_length]])


def commanded_lengths(layout: Layout, setpoints_mm: np.ndarray) -> np.ndarray:
    """Length each beam has in the display (mm): straight length + start feed + end feed."""
    return np.array([b.straight_length + setpoints_mm[b.start_servo] + setpoints_mm[b.end_servo]
                     for b in layout.beams])


def check_setpoints(layout: Layout, setpoints_mm: np.ndarray, model: str) -> np.ndarray:
    """Setpoints as a finite float vector of the layout's actuator count, or DisplayModelError."""
    values = np.asarray(setpoints_mm, dtype=float)
    if values.shape != (layout.n_actuators,):
        raise DisplayModelError(
            f"{model}: expected {layout.n_actuators} setpoints for {layout.name!r}, "
            f"got shape {values.shape!r}")
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise DisplayModelError(
            f"{model}: setpoint of {layout.actuators[bad].name} is {float(values[bad])!r}, "
            f"expected a finite number (mm)")
    return values


def check_yield(model: str, beam: int, curvature_per_mm: float, layout: Layout) -> None:
    """Raise DisplayModelError when a beam bends beyond its yield curvature 2 sigma_y / (E t)."""
    limit = layout.beam_section.yield_curvature_per_mm
    if curvature_per_mm > limit:
        raise DisplayModelError(
            f"{model}: beam {beam} bends to curvature {curvature_per_mm:.4g} /mm (radius "
            f"{1 / curvature_per_mm:.3g} mm), beyond the yield curvature {limit:.4g} /mm of "
            f"{layout.beam_section.material}: plastic deformation; lower the stimulus height "
            f"or widen it")


@dataclass(frozen=True)
class BeamProfiles:
    """The shapes of all beams of a layout for one frame.

    ``heights(beam, s_mm)`` evaluates beam ``beam[i]`` at ``s_mm[i]`` (vectorised; 0 beyond
    the clamps). ``axial_load_n`` is the compressive load N of each beam (0 for the spline),
    ``critical_load_n`` its first critical load (inf where not computed).
    """

    spans_mm: np.ndarray  # (n_beams,) clamp-to-clamp straight length S
    evaluate: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (beam, s) -> heights, s in [0,S]
    axial_load_n: np.ndarray
    critical_load_n: np.ndarray
    commanded_length_mm: np.ndarray
    length_mm: np.ndarray  # arc length of the shape
    #: optional fast path for points asked every frame (inside the clamps): ``prepare(beam,
    #: s)`` gives a query valid for every profile of the same ``geometry`` (a hashable key),
    #: ``evaluate_prepared(query)`` the heights; equal to ``evaluate(beam, s)``
    prepare: Callable[[np.ndarray, np.ndarray], object] | None = None
    evaluate_prepared: Callable[[object], np.ndarray] | None = None
    geometry: object = None

    def heights(self, beam: np.ndarray, s_mm: np.ndarray) -> np.ndarray:
        beam = np.asarray(beam, dtype=int)
        s = np.asarray(s_mm, dtype=float)
        beam, s = np.broadcast_arrays(beam, s)
        span = self.spans_mm[beam]
        inside = (s >= 0.0) & (s <= span)
        out = np.zeros(s.shape)
        if np.any(inside):
            out[inside] = self.evaluate(beam[inside], s[inside])
        return out

    def profile(self, beam: int) -> Callable[[np.ndarray], np.ndarray]:
        """One beam's shape as a function of s (mm)."""
        return lambda s: self.heights(np.full(np.shape(s), beam), s)


class NetworkModel(DisplayModel):
    """A display model made of beams solved one by one, joined by the fabric in 2D."""

    def __init__(self, layout: Layout, fabric_subdivisions: int = DEFAULT_FABRIC_SUBDIVISIONS
                 ) -> None:
        super().__init__(layout)
        if layout.lattice not in ("line", "hex"):
            raise DisplayModelError(
                f"{self.name}: lattice {layout.lattice!r} not supported; expected line or hex")
        if not layout.beams:
            raise DisplayModelError(f"{self.name}: layout {layout.name!r} has no beams")
        self.starts = np.array([b.start for b in layout.beams], dtype=float)
        self.units = np.array([b.direction for b in layout.beams])
        self.spans = np.array([b.straight_length for b in layout.beams])
        # the finest of the asked mesh and the one the clamps need (layout checked it exists)
        mesh = fabric_mesh_for_margin(layout.end_margin_pitch, fabric_subdivisions)
        self.fabric = (Fabric.for_layout(layout, mesh or fabric_subdivisions)
                       if layout.lattice == "hex" else None)

    @abstractmethod
    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        """Each beam's shape for the setpoints (cheap to sample many times)."""

    def surface(self, setpoints_mm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy_mm, dtype=float)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise DisplayModelError(f"{self.name}: expected points of shape (n, 2), "
                                    f"got {xy.shape!r}")
        profiles = self.beam_profiles(setpoints_mm)
        if self.fabric is None:
            rel = xy - self.starts[0]
            s = rel[:, 0] * self.units[0, 0] + rel[:, 1] * self.units[0, 1]  # no BLAS gemv
            return profiles.heights(np.zeros(len(s), dtype=int), s)
        return self.fabric.surface(profiles, xy)


class Fabric:
    """Membrane between the beams of a hexagonal layout (module docstring). Build once."""

    _cache: dict[tuple, Fabric] = {}

    @classmethod
    def for_layout(cls, layout: Layout, subdivisions: int) -> Fabric:
        key = (layout.pitch_mm, layout.pixel_xy.tobytes(), layout.beams, subdivisions)
        if key not in cls._cache:
            if len(cls._cache) > 16:
                cls._cache.clear()
            cls._cache[key] = cls(layout, subdivisions)
        return cls._cache[key]

    def __init__(self, layout: Layout, subdivisions: int) -> None:
        if not (isinstance(subdivisions, int) and subdivisions >= 1):
            raise DisplayModelError(
                f"fabric_subdivisions: expected a whole number >= 1, got {subdivisions!r}")
        m = subdivisions
        self.h = h = layout.pitch_mm / m
        # fine axial coordinates of the pixels and the clamps; every beam node must be a node
        points = [layout.pixel_xy] + [np.array([b.start, b.end]) for b in layout.beams]
        fine = self._to_axial(np.vstack(points))
        rounded = np.rint(fine)
        if np.max(np.abs(fine - rounded)) > 1e-6:
            raise DisplayModelError(
                f"fabric: clamps of {layout.name!r} (end_margin_pitch "
                f"{layout.end_margin_pitch!r}) do not fall on the fabric lattice with "
                f"fabric_subdivisions={m}; choose subdivisions so that margin * subdivisions "
                f"is whole")
        hull = ConvexHull(self._to_xy(rounded))
        lo = rounded.min(axis=0).astype(int) - 1
        hi = rounded.max(axis=0).astype(int) + 1
        qq, rr = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1),
                             indexing="ij")
        xy_nodes = self._to_xy(np.column_stack([qq.ravel(), rr.ravel()]))
        slack = hull.equations[:, :2] @ xy_nodes.T + hull.equations[:, 2:3]
        inside = np.all(slack <= 1e-6 * h, axis=0).reshape(qq.shape)
        self.origin = lo
        self.shape = qq.shape
        index = np.full(qq.shape, -1)
        index[inside] = np.arange(int(inside.sum()))
        self.index = index
        n_nodes = int(inside.sum())
        steps = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, -1), (-1, 1))
        padded = np.pad(inside, 1)
        border = np.zeros_like(inside)
        for dq, dr in steps:
            border |= inside & ~padded[1 + dq: 1 + dq + inside.shape[0],
                                      1 + dr: 1 + dr + inside.shape[1]]
        # beam nodes: s = j h along each beam; a node shared by beams (a pixel) is taken once
        role = np.zeros(n_nodes, dtype=int)  # 0 free, 1 border (z = 0), 2 beam sample
        role[index[border]] = 1
        sample_node, sample_beam, sample_s = [], [], []
        for b, beam in enumerate(layout.beams):
            start = np.rint(self._to_axial(np.array([beam.start]))[0]).astype(int)
            end = np.rint(self._to_axial(np.array([beam.end]))[0]).astype(int)
            count = int(np.max(np.abs(end - start)))
            step = (end - start) // count
            step_mm = float(np.linalg.norm(self._to_xy(step[None, :])[0]))
            for j in range(count + 1):
                q, r = start + j * step - lo
                node = index[q, r]
                if role[node] == 0:
                    role[node] = 2
                    sample_node.append(node)
                    sample_beam.append(b)
                    sample_s.append(j * step_mm)
        self.sample_node = np.array(sample_node, dtype=int)
        self.sample_beam = np.array(sample_beam, dtype=int)
        self.sample_s = np.array(sample_s)
        free = np.flatnonzero(role == 0)
        self.free = free
        # Laplacian rows of the free nodes: 6 z_i - sum of the 6 neighbours
        position = np.full(n_nodes, -1)
        position[free] = np.arange(len(free))
        sample_col = np.full(n_nodes, -1)
        sample_col[self.sample_node] = np.arange(len(self.sample_node))
        node_q, node_r = np.nonzero(inside)
        node_q, node_r = node_q[index[inside].argsort()], node_r[index[inside].argsort()]
        rows_ff, cols_ff, vals_ff = [np.arange(len(free))], [np.arange(len(free))], [
            np.full(len(free), 6.0)]
        rows_fb, cols_fb = [], []
        for dq, dr in steps:
            nb = index[node_q[free] + dq, node_r[free] + dr]
            is_free = position[nb] >= 0
            rows_ff.append(np.flatnonzero(is_free))
            cols_ff.append(position[nb[is_free]])
            vals_ff.append(np.full(int(is_free.sum()), -1.0))
            is_sample = sample_col[nb] >= 0
            rows_fb.append(np.flatnonzero(is_sample))
            cols_fb.append(sample_col[nb[is_sample]])
        l_ff = coo_matrix((np.concatenate(vals_ff), (np.concatenate(rows_ff),
                           np.concatenate(cols_ff))), shape=(len(free), len(free))).tocsc()
        rows, cols = np.concatenate(rows_fb), np.concatenate(cols_fb)
        # L_ff z_f = l_fb z_b  (l_fb holds +1 for each beam neighbour). A sparse LU solve per
        # frame (~0.2 ms) rather than a dense precomputed inverse: no BLAS threads in the hot
        # path (threaded OpenBLAS gemv is 80x slower on a busy two-core machine).
        self._l_fb = coo_matrix((np.ones(len(rows)), (rows, cols)),
                                shape=(len(free), len(self.sample_node))).tocsr()
        self._lu = splu(l_ff) if len(free) else None
        self.n_nodes = n_nodes
        self.beam_starts = np.array([b.start for b in layout.beams], dtype=float)
        self.beam_units = np.array([b.direction for b in layout.beams])
        self.beam_spans = np.array([b.straight_length for b in layout.beams])
        self._plans: OrderedDict[bytes, _SurfacePlan] = OrderedDict()

    def _to_axial(self, xy: np.ndarray) -> np.ndarray:
        r = xy[:, 1] / (self.h * _SQRT3_2)
        return np.column_stack([xy[:, 0] / self.h - r / 2.0, r])

    def _to_xy(self, qr: np.ndarray) -> np.ndarray:
        qr = np.asarray(qr, dtype=float)
        return np.column_stack([self.h * (qr[:, 0] + qr[:, 1] / 2.0),
                                self.h * _SQRT3_2 * qr[:, 1]])

    def node_heights(self, profiles: BeamProfiles) -> np.ndarray:
        """Heights of every fabric node (border 0, beams sampled, free nodes by the membrane)."""
        return self._node_heights(profiles.heights(self.sample_beam, self.sample_s))

    def _node_heights(self, samples: np.ndarray) -> np.ndarray:
        z = np.zeros(self.n_nodes)
        z[self.sample_node] = samples
        if self._lu is not None:
            z[self.free] = self._lu.solve(self._l_fb @ samples)
        return z

    def surface(self, profiles: BeamProfiles, xy_mm: np.ndarray) -> np.ndarray:
        """Fabric heights at points (n, 2): linear FE interpolation plus the beam correction.

        Everything that depends on the points alone (the barycentric weights as a sparse
        matrix, which beams correct which points, where) is planned once per point set and
        kept (the observer and the quality criteria ask for the same points frame after
        frame); a frame then costs one evaluation of the beams at the samples and correction
        abscissae, one sparse solve and two sparse products.
        """
        xy = np.asarray(xy_mm, dtype=float)
        plan = self._plan(xy)
        if profiles.prepare is None:
            values = profiles.heights(plan.beam, plan.s)
        else:  # every plan abscissa lies within its beam's clamps
            query = plan.prepared.get(profiles.geometry)
            if query is None:
                query = plan.prepared[profiles.geometry] = profiles.prepare(plan.beam, plan.s)
            values = profiles.evaluate_prepared(query)
        n_samples = len(self.sample_node)
        z_nodes = self._node_heights(values[:n_samples])
        return plan.interpolate @ z_nodes + plan.correct @ values[n_samples:]

    def _plan(self, xy: np.ndarray) -> _SurfacePlan:
        key = xy.tobytes()
        plan = self._plans.get(key)
        if plan is None:
            plan = self._make_plan(xy)
            self._plans[key] = plan
            if len(self._plans) > _PLANS_KEPT:
                self._plans.popitem(last=False)
        else:
            self._plans.move_to_end(key)
        return plan

    def _make_plan(self, xy: np.ndarray) -> _SurfacePlan:
        n = len(xy)
        axial = self._to_axial(xy) - self.origin
        base = np.floor(axial).astype(int)
        frac = axial - base
        upper = frac.sum(axis=1) > 1.0
        corner = base + upper[:, None]  # (q+1, r+1) for upper triangles
        w0 = np.where(upper, frac.sum(axis=1) - 1.0, 1.0 - frac.sum(axis=1))
        wq = np.where(upper, 1.0 - frac[:, 1], frac[:, 0])
        wr = np.where(upper, 1.0 - frac[:, 0], frac[:, 1])
        rows, cols, vals = [], [], []
        for weight, (q, r) in ((w0, corner.T), (wq, (base[:, 0] + 1, base[:, 1])),
                               (wr, (base[:, 0], base[:, 1] + 1))):
            node = self._node_index(q, r)
            keep = node >= 0  # off the fabric: height 0
            rows.append(np.flatnonzero(keep))
            cols.append(node[keep])
            vals.append(weight[keep])
        interpolate = csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                  np.concatenate(cols))), shape=(n, self.n_nodes))
        beam, point, s_near, left, right, frac_s, weight = self._correction_terms(xy)
        m = len(s_near)
        # correction = weight * (exact - (1 - frac) left - frac right), as one sparse map
        correct = csr_matrix((np.concatenate([weight, -weight * (1 - frac_s), -weight * frac_s]),
                              (np.tile(point, 3), np.arange(3 * m))), shape=(n, 3 * m))
        return _SurfacePlan(
            beam=np.concatenate([self.sample_beam, np.tile(beam, 3)]),
            s=np.concatenate([self.sample_s, s_near, left, right]),
            interpolate=interpolate, correct=correct)

    def _node_index(self, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        ok = (q >= 0) & (q < self.shape[0]) & (r >= 0) & (r < self.shape[1])
        node = np.full(q.shape, -1)
        node[ok] = self.index[q[ok], r[ok]]
        return node

    def _correction_terms(self, xy: np.ndarray) -> tuple[np.ndarray, ...]:
        """Beam shape minus its linear sampling, faded out over one fine spacing off the beam.

        Beam b's correction carries the weight c_b prod_{b' != b} (1 - c_b'), with closeness
        c_b = 1 - distance / (h sqrt(3)/2) (0 beyond the next lattice line): zero at every node,
        on other beams' lines and one lattice line away, so the surface stays continuous; on a
        beam line the surface equals the beam profile (except within h of a crossing, where
        the crossing beams share the linear sampling). Returns, per (beam, point) term: beam,
        point, s, the fine nodes left and right of s along the beam, the fraction between
        them, and the weight.
        """
        # distance off each beam's line, (B, n); the few close (beam, point) pairs go on
        normal = np.column_stack([-self.beam_units[:, 1], self.beam_units[:, 0]])
        offset = np.einsum("bk,bk->b", normal, self.beam_starts)[:, None]
        off = np.abs(normal[:, :1] * xy[:, 0] + normal[:, 1:] * xy[:, 1] - offset)  # no BLAS
        band = self.h * _SQRT3_2
        beam_idx, point = np.nonzero(off < band)
        s_all = np.einsum("nk,nk->n", xy[point] - self.beam_starts[beam_idx],
                          self.beam_units[beam_idx])
        close = np.where((s_all > 0.0) & (s_all < self.beam_spans[beam_idx]),
                         1.0 - off[beam_idx, point] / band, 0.0)
        keep = close > 0.0
        beam_idx, point, close, s_near = beam_idx[keep], point[keep], close[keep], s_all[keep]
        # prod_{b' != b} (1 - c_b') over the point's other close beams (at most a few)
        factor = 1.0 - close
        zero = factor <= 0.0
        n = len(xy)
        zeros = np.bincount(point, weights=zero, minlength=n)
        product = np.ones(n)
        np.multiply.at(product, point, np.where(zero, 1.0, factor))
        others = np.where(zero, product[point], product[point] / np.where(zero, 1.0, factor))
        others = np.where(zeros[point] - zero > 0, 0.0, others)
        weight = close * others
        take = weight > 0.0
        beam_idx, point, s_near, weight = beam_idx[take], point[take], s_near[take], weight[take]
        left = np.floor(s_near / self.h) * self.h
        right = np.minimum(left + self.h, self.beam_spans[beam_idx])
        frac = (s_near - left) / self.h
        return beam_idx, point, s_near, left, right, frac, weight


@dataclass(frozen=True)
class _SurfacePlan:
    """What a point set needs from each frame (see :meth:`Fabric.surface`)."""

    beam: np.ndarray  # beams to evaluate: the fabric samples, then 3 per correction term
    s: np.ndarray
    interpolate: csr_matrix  # (n_points, n_nodes) barycentric weights
    correct: csr_matrix  # (n_points, 3 * terms) weight * (exact - linear)
    #: BeamProfiles.geometry -> its prepared query of (beam, s)
    prepared: dict = field(default_factory=dict)
