"""``beam``: the compressed beam of the CRS, solved in closed form per segment.

Each beam runs from its start clamp (s = 0) through its pixels to its end clamp (s = S).
Between consecutive constraint points it obeys (Wang, Meng & Chen 2025, the ODE behind Eq. 3;
docs/physics.md, "The compressed beam")::

    EI y'''' + N y'' + beta y = 0,

N the compressive axial load, beta the Winkler foundation of a skin pressed onto the skeleton
(``foundation=True``: ``layout.foundation_stiffness``; the default ``False``: beta = 0, the
display as shown without a finger pressing on it, and the trigonometric closed form).
Conditions: y = y' = 0 at both clamps; at a pixel y equals the commanded height on both
sides and y, y', y'' (slope, moment) are continuous, the shear jumping by the pixel's
reaction (the beam is pressed through a point support). N is found so that the beam's
arc length between the clamps equals the commanded length, less the elastic shortening of
the steel under N (paper: Delta l = N L / EA)::

    L(N) = integral_0^S sqrt(1 + y'^2) ds = L_c (1 - N / EA),   L_c = S + feed_start + feed_end.

The EA term is tiny (N_cr S / EA is a few micrometres on the published devices) but it matters
for one case: a beam whose pixels are all at base height, given a small feed (a 2D bump
crossing its line between pixels), keeps its straight shape under N = EA (1 - S / L_c) instead
of being reported as collapsed; a feed beyond N_cr S / EA does collapse it (it would buckle
between its pixels, uncontrolled by them).

Solution per segment
    The closed forms and the linear system of a segment chain are
    :mod:`crs_study.display.beam_equations`: unknowns are the states (y, y', y'', y''') at
    each segment start; arc length by 8-point Gauss-Legendre per segment.
Root finding
    For each distinct beam geometry (its segment lengths, shared by most beams of a patch),
    the critical load and the linear maps from pixel heights to the slopes at the quadrature
    nodes on a grid of 48 loads in [0, margin N_cr] are computed once and cached on the class.
    A frame evaluates L on the whole grid with one batched product; the first grid interval
    reaching the commanded length brackets N. Every beam is then refined at once by
    safeguarded inverse interpolation: the Lagrange polynomial a(f) through the 8 grid points
    around the bracket, evaluated at f = 0; each step is an exact batched solve that replaces
    the point of largest |f| (regula falsi when a step leaves the bracket). The first exact
    solve almost always meets |L - L_c (1 - N/EA)| <= ``LENGTH_TOLERANCE_MM`` (1 nm, four
    orders below the servos' step) and its states are the frame's shapes: ~0.3 ms a frame for
    the 9 beams of the 2D device (``crs-study bench display``).

Failure modes (never returned as a shape)
    * Critical load: the system's determinant vanishes first at N_cr (a buckling mode with zero
      displacement at every pixel: the shape stops being unique). N is searched in
      [0, margin N_cr] (margin 0.98); a commanded length not reached there (the beam would need
      N >= margin N_cr, or no N gives it at all) raises :class:`CollapseError`.
    * Eq. 4: with beta > 0 and Delta = 16 pi^4 EI / (27 beta d^4) < 1 the beam collapses as soon
      as it is compressed: :class:`CollapseError` when any beam needs N > 0.
    * Yield: curvature beyond 2 sigma_y / (E t) (at quadrature nodes and supports) raises
      :class:`DisplayModelError` (plastic deformation).
    * Tension fallback: a commanded length at or below the length of the N = 0 shape (zero feed
      with raised pixels, say) would need tension. The boundary servos can only push length in,
      and a steel beam does not stretch measurably, so we clamp N at 0 and return the N = 0 shape
      (the clamped spline when beta = 0); ``length_mm`` then exceeds ``commanded_length_mm``,
      which says so.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from crs_study.display.base import register
from crs_study.display.beam_equations import (
    GL_NODES,
    TINY_LOAD,
    BeamSet,
    fundamental_matrix,
    no_collapse_number,
    theta_minus_sin_over_cube,
)
from crs_study.display.network import (
    BeamProfiles,
    NetworkModel,
    beam_support_positions,
    check_setpoints,
    check_yield,
)
from crs_study.errors import CollapseError, DisplayModelError
from crs_study.geometry.layout import Layout

#: |L - L_c (1 - N/EA)| at which N is accepted: 1 nm, four orders below the servos' step;
#: the height error it leaves is a few nm
LENGTH_TOLERANCE_MM = 1e-6
_SCAN_POINTS = 400  # grid for the first determinant sign change (critical load)
_GRID_POINTS = 48  # N grid for bracketing the length root
_WINDOW = 8  # points of the inverse interpolation
_EYE = np.eye(_WINDOW)[:, :, None]
_OFF_EYE = 1.0 - _EYE


class CompressedBeams:
    """Per-layout solver for every beam at once (see the module docstring). Build once."""

    _cache: dict[tuple, CompressedBeams] = {}
    #: (segment lengths in pitch units, b, margin) -> (a_critical, grid slope operator (K,nq,p))
    _geometry_cache: dict[tuple, tuple[float, np.ndarray]] = {}

    @classmethod
    def for_layout(cls, layout: Layout, foundation: bool = False,
                   critical_margin: float = 0.98) -> CompressedBeams:
        key = (layout.pitch_mm, layout.pixel_xy.tobytes(), layout.beams, layout.beam_section,
               layout.foundation_stiffness, bool(foundation), float(critical_margin))
        if key not in cls._cache:
            if len(cls._cache) > 32:
                cls._cache.clear()
            cls._cache[key] = cls(layout, foundation, critical_margin)
        return cls._cache[key]

    def __init__(self, layout: Layout, foundation: bool = False,
                 critical_margin: float = 0.98) -> None:
        if not 0.0 < critical_margin < 1.0:
            raise DisplayModelError(
                f"beam: critical_margin must be in (0, 1), got {critical_margin!r}")
        self.layout = layout
        self.margin = critical_margin
        self.d = d = layout.pitch_mm
        self.ei = layout.beam_section.bending_stiffness
        self.beta = layout.foundation_stiffness if foundation else 0.0
        self.b = self.beta * d**4 / self.ei
        self.delta = no_collapse_number(self.ei, self.beta, d)
        section = layout.beam_section
        # N = a EI / d^2; axial strain N / (E A) = a * axial_compliance
        self.axial_compliance = self.ei / (d**2 * section.youngs_modulus_mpa * section.area_mm2)
        supports = [beam_support_positions(layout, beam) / d for beam in layout.beams]
        p = max(len(s) - 1 for s in supports)
        self.beams = BeamSet(supports, p)
        self.n_beams = self.beams.n_beams
        self.n_segments = self.beams.n_segments
        self.n_seg_max = p
        self.seg_start = self.beams.seg_start
        self.spans = np.array([beam.straight_length for beam in layout.beams])
        self.pixel_map = np.full((self.n_beams, self.beams.n_pixels), -1)
        for bi, beam in enumerate(layout.beams):
            self.pixel_map[bi, : len(beam.pixels)] = beam.pixels
        self.start_servo = np.array([b.start_servo for b in layout.beams], dtype=int)
        self.end_servo = np.array([b.end_servo for b in layout.beams], dtype=int)
        self._pixel_index = np.maximum(self.pixel_map, 0)
        self._pixel_real = (self.pixel_map >= 0).astype(float)
        self._cols = np.arange(self.n_beams)
        self._precompute_geometries(supports)
        self.critical_load_n = self.a_critical * self.ei / d**2

    # --- per-geometry precomputation (cached across layouts) -------------------------------
    def _precompute_geometries(self, supports: list[np.ndarray]) -> None:
        """Critical load and grid slope operators, once per distinct beam geometry.

        Beams with the same segment lengths (most beams of a periodic patch, and the same
        beam in the patches of a d/l sweep) share both; they are computed for one beam of each
        geometry and cached on the class.
        """
        keys = [(tuple(np.round(np.diff(s), 12)), self.b, self.margin) for s in supports]
        missing = sorted({k for k in keys if k not in self._geometry_cache})
        if missing:
            if len(self._geometry_cache) > 512:
                type(self)._geometry_cache.clear()
            reps = [supports[keys.index(k)] for k in missing]
            unique = BeamSet(reps, max(len(s) - 1 for s in reps))
            a_critical = self._critical_a(unique)
            grid_slopes = self._grid_operators(unique, a_critical)
            for i, k in enumerate(missing):
                n_pix = int(unique.n_segments[i]) - 1
                q = len(GL_NODES) * int(unique.n_segments[i])
                self._geometry_cache[k] = (float(a_critical[i]), grid_slopes[i, :, :q, :n_pix])
        entries = [self._geometry_cache[k] for k in keys]
        self.a_critical = np.array([e[0] for e in entries])
        u = np.linspace(0.0, 1.0, _GRID_POINTS)[:, None]
        self.a_grid = self.margin * self.a_critical[None, :] * (1.0 - (1.0 - u) ** 2)  # (K, B)
        self._shortening = 1.0 - self.a_grid * self.axial_compliance
        self._windows = np.arange(_GRID_POINTS - _WINDOW + 1)[:, None] + np.arange(_WINDOW)
        self._window_start = np.clip(np.arange(_GRID_POINTS) - _WINDOW // 2, 0,
                                     _GRID_POINTS - _WINDOW)  # by the bracket's upper index
        self._grid_windows = self.a_grid.T[:, self._windows].transpose(1, 0, 2)  # (start, B, W)
        nq = self.beams.t_nodes.shape[1]
        ops = np.zeros((self.n_beams, _GRID_POINTS, nq, self.beams.n_pixels))
        for bi, (_, op) in enumerate(entries):
            ops[bi, :, : op.shape[1], : op.shape[2]] = op
        # slopes dy/ds (dimensionless) at every grid load: (B, K * nq, n_pix) @ heights
        self._grid_slopes = ops.reshape(self.n_beams, _GRID_POINTS * nq, -1) / self.d
        self._grid_weights = self.beams.w_nodes * self.d  # mm per node
        self._top_slopes = np.ascontiguousarray(  # slopes at margin N_cr: (B, nq, n_pix)
            self._grid_slopes.reshape(self.n_beams, _GRID_POINTS, nq, -1)[:, -1])
        self._top_stretch = 1.0 / self._shortening[-1]
        self._top_offset = self.spans + LENGTH_TOLERANCE_MM

    def _critical_a(self, beams: BeamSet) -> np.ndarray:
        """First zero of det(A(a)) per beam: the critical load in units EI/d^2."""
        longest = beams.lengths.max(axis=1)
        upper = 1.05 * ((2 * np.pi / longest) ** 2 + 3 * self.b * longest**2 / (4 * np.pi**2))
        grid = np.linspace(0.0, 1.0, _SCAN_POINTS)[:, None] * upper[None, :]
        sign, _ = np.linalg.slogdet(beams.system(grid, self.b))
        out = upper.copy()
        for bi in range(beams.n_beams):
            change = np.flatnonzero(sign[1:, bi] * sign[0, bi] <= 0)
            if change.size == 0:
                continue  # no sign change below the Rayleigh bound: keep the bound
            k = int(change[0]) + 1
            _, ref = np.linalg.slogdet(beams.system(grid[k - 1], self.b)[bi])

            def det(x: float, bi: int = bi, ref: float = ref) -> float:
                a = np.zeros(beams.n_beams)
                a[bi] = x
                s, logdet = np.linalg.slogdet(beams.system(a, self.b)[bi])
                return float(s * np.exp(logdet - ref))

            out[bi] = brentq(det, grid[k - 1, bi], grid[k, bi], xtol=1e-13, rtol=1e-13)
        return out

    def _grid_operators(self, beams: BeamSet, a_critical: np.ndarray) -> np.ndarray:
        """Slope operators (B, K, P*Q, n_pix) (pitch units) on a grid of a in [0, margin a_cr].

        The grid clusters towards the margin (u -> 1 - (1 - u)^2), where L(a) steepens.
        """
        u = np.linspace(0.0, 1.0, _GRID_POINTS)[:, None]
        a_grid = self.margin * a_critical[None, :] * (1.0 - (1.0 - u) ** 2)
        n_pix = beams.n_pixels
        basis = np.linalg.solve(beams.system(a_grid, self.b), beams.rhs[None])
        basis = basis.reshape(_GRID_POINTS, beams.n_beams, beams.n_seg_max, 4, n_pix)
        phi = fundamental_matrix(np.broadcast_to(beams.t_nodes, a_grid.shape
                                                 + beams.t_nodes.shape[1:]), a_grid, self.b)
        slopes = np.einsum("kbnj,kbnjp->kbnp", phi[..., 1, :], basis[:, :, beams.node_seg])
        return np.ascontiguousarray(slopes.transpose(1, 0, 2, 3))

    # --- per frame ------------------------------------------------------------------------
    def heights(self, setpoints: np.ndarray) -> np.ndarray:
        return setpoints[self._pixel_index] * self._pixel_real

    def _commanded(self, setpoints: np.ndarray) -> np.ndarray:
        return self.spans + setpoints[self.start_servo] + setpoints[self.end_servo]

    def _state(self, a: np.ndarray, heights: np.ndarray) -> _State:
        """Exact shapes at loads a: segment states, y' and y'' at the nodes, arc lengths."""
        coef = self.beams.coefficients(a, self.b, heights)
        slope, second = self.beams.node_derivatives(a, self.b, coef)
        length = np.sum(self._grid_weights * np.sqrt(1.0 + (slope / self.d) ** 2), axis=-1)
        return _State(coef, slope, second, length)

    def longest_feeds(self, pixel_heights_mm: np.ndarray) -> np.ndarray:
        """Largest total feed (mm) per beam that :meth:`solve` can show for these pixel heights.

        The longest stable shape is the one at N = margin N_cr (the length grows with N);
        after the steel's shortening the commanded length may be at most
        L(margin N_cr) / (1 - margin N_cr / EA), so the feed at most that less the span S,
        less ``LENGTH_TOLERANCE_MM`` (so the root is bracketed strictly). With every pixel at
        base this is ~margin N_cr S / EA (the straight beam's elastic shortening). One
        (nq x n_pix) product per beam: the renderer's feed cap (:mod:`crs_study.rendering.render`).
        """
        heights = np.asarray(pixel_heights_mm, dtype=float)[self._pixel_index] * self._pixel_real
        top = np.matmul(self._top_slopes, heights[:, :, None])[..., 0]
        length = np.einsum("bq,bq->b", self._grid_weights, np.sqrt(1.0 + top * top))
        return length * self._top_stretch - self._top_offset

    def longest_operator(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`longest_feeds` as arrays over the layout's pixels: ``(slopes, weights,
        offset)``, with longest = ``weights @ sqrt(1 + (slopes @ h)^2) - offset`` per beam.

        ``slopes`` (B, nq, n_pixels): dy/ds at each node of the shape at margin N_cr per mm
        of each pixel's height (0 for the pixels off the beam); ``weights`` (B, nq): the
        quadrature weights (mm) times the steel's stretch; ``offset`` (B,): S + tolerance.
        """
        slopes = np.zeros(self._top_slopes.shape[:2] + (self.layout.n_pixels,))
        for b, j in zip(*np.nonzero(self.pixel_map >= 0), strict=True):
            slopes[b, :, self.pixel_map[b, j]] += self._top_slopes[b, :, j]
        return slopes, self._grid_weights * self._top_stretch[:, None], self._top_offset.copy()

    def solve(self, setpoints_mm: np.ndarray, check_yield_curvature: bool = True,
              model: str = "beam") -> BeamProfiles:
        """Shapes with N solved so each beam's arc length equals its commanded length."""
        setpoints = check_setpoints(self.layout, setpoints_mm, model)
        heights = self.heights(setpoints)
        target = self._commanded(setpoints)
        slopes = np.matmul(self._grid_slopes, heights[:, :, None])[..., 0]
        grid_lengths = np.sum((self._grid_weights[:, None, :] * np.sqrt(
            1.0 + slopes.reshape(self.n_beams, _GRID_POINTS, -1) ** 2)), axis=-1).T  # (K, B)
        # the steel shortens by N L / (E A) under the load: shape length = L_c (1 - N / EA)
        excess = grid_lengths - target * self._shortening
        need = excess[0] < -LENGTH_TOLERANCE_MM
        if not need.any():
            a = np.zeros(self.n_beams)
            return self._profiles(a, self._state(a, heights), target, check_yield_curvature,
                                  model)
        if self.delta < 1.0:
            bi = int(np.flatnonzero(need)[0])
            raise CollapseError(
                f"{model}: beam {bi}: Delta = {self.delta:.3g} < 1 (Eq. 4, beta = "
                f"{self.beta:.3g} N/mm^2): the compressed beam collapses into the skin; use "
                f"a stiffer beam, a softer skin or a smaller pitch")
        reached = excess >= 0.0
        unreachable = need & ~reached[-1]
        if unreachable.any():
            bi = int(np.flatnonzero(unreachable)[0])
            raise CollapseError(
                f"{model}: beam {bi}: commanded length {target[bi]:.4f} mm needs N >= "
                f"{self.margin:g} N_cr = {self.margin * self.critical_load_n[bi]:.4g} N "
                f"(longest stable shape {grid_lengths[-1, bi]:.4f} mm): the beam collapses; "
                f"reduce the boundary feed or the stimulus height")
        a, state = self._root(need, np.argmax(reached, axis=0), excess, target, heights)
        return self._profiles(a, state, target, check_yield_curvature, model)

    def _root(self, need, first, excess, target, heights) -> tuple[np.ndarray, _State]:
        """N per beam by safeguarded inverse interpolation (module docstring, Root finding).

        Starts from the ``_WINDOW`` grid loads around the bracket [a_{k-1}, a_k] (their
        lengths are exact: the grid operators are exact solves); each step evaluates f exactly
        at the interpolated root and replaces the point of largest |f|; a step outside the
        current bracket falls back to regula falsi. Beams that need no load keep a = 0.
        """
        cols = self._cols
        hi_index = np.maximum(first, 1)
        start = self._window_start[hi_index]
        pa = self._grid_windows[start, cols].T  # (W, B): the grid loads around the bracket
        pf = excess[self._windows[start].T, cols]
        bracket = hi_index - start
        lo, hi = pa[bracket - 1, cols], pa[bracket, cols]
        f_lo, f_hi = pf[bracket - 1, cols], pf[bracket, cols]
        a = np.zeros(self.n_beams)
        state = None
        active = need
        for _ in range(60):
            # Lagrange form of the inverse interpolant a(f) at f = 0: sum_i a_i prod_{j != i}
            # f_j / (f_j - f_i); the identity on the diagonal makes its factors 1
            denominator = pf[None, :, :] - pf[:, None, :] + _EYE
            ratio = np.divide(pf[None, :, :] * _OFF_EYE + _EYE, denominator,
                              out=np.full(denominator.shape, np.nan), where=denominator != 0)
            guess = np.sum(pa * np.prod(ratio, axis=1), axis=0)
            inside = (guess > lo) & (guess < hi)  # False for nan
            if not inside[active].all():  # regula falsi (f_hi > 0 >= f_lo: no division by 0)
                guess = np.where(inside, guess, (lo * f_hi - hi * f_lo) / (f_hi - f_lo))
            trial = np.where(active, guess, a)
            trial_state = self._state(trial, heights)
            f = trial_state.length - target * (1.0 - trial * self.axial_compliance)
            state = trial_state if state is None else state.where(active, trial_state)
            a = trial
            done = np.abs(f) <= LENGTH_TOLERANCE_MM
            if done[active].all():
                break
            upper = active & (f > 0)
            lower = active & (f <= 0)
            hi, f_hi = np.where(upper, trial, hi), np.where(upper, f, f_hi)
            lo, f_lo = np.where(lower, trial, lo), np.where(lower, f, f_lo)
            worst = np.argmax(np.abs(pf), axis=0)
            replace = active & ~done
            pa[worst[replace], cols[replace]] = trial[replace]
            pf[worst[replace], cols[replace]] = f[replace]
            active = active & ~done & (hi - lo > 1e-14 * self.a_critical)
            if not active.any():
                break
        return a, state

    def _profiles(self, a, state: _State, target, check_yield_curvature, model
                  ) -> BeamProfiles:
        coef, slope = state.coef, state.slope
        if check_yield_curvature:
            curvature = np.abs(state.second) / self.d**2 / (1.0 + (slope / self.d) ** 2) ** 1.5
            at_supports = np.abs(coef[:, :, 2]) / self.d**2  # y'' at segment starts (y' = 0
            # at clamps; at pixels the slope factor only lowers it, so this bounds from above)
            worst = np.maximum(curvature.max(axis=1), at_supports.max(axis=1))
            bi = int(np.argmax(worst))
            check_yield(model, bi, float(worst[bi]), self.layout)
        shape = _ShapeEvaluator(self, a, coef)
        return BeamProfiles(
            spans_mm=self.spans, evaluate=shape,
            axial_load_n=a * self.ei / self.d**2, critical_load_n=self.critical_load_n,
            commanded_length_mm=target, length_mm=state.length,
            prepare=shape.prepare, evaluate_prepared=shape.prepared, geometry=self,
        )

    def solve_with_load(self, setpoints_mm: np.ndarray, axial_load_n: np.ndarray | float
                        ) -> BeamProfiles:
        """Shapes for a given axial load N (no length condition): for checks against Eq. 3."""
        setpoints = check_setpoints(self.layout, setpoints_mm, "beam")
        a = np.broadcast_to(np.asarray(axial_load_n, dtype=float) * self.d**2 / self.ei,
                            (self.n_beams,)).copy()
        return self._profiles(a, self._state(a, self.heights(setpoints)),
                              self._commanded(setpoints), False, "beam")


@dataclass(frozen=True)
class _State:
    """Exact shapes of all beams at some loads (see :meth:`CompressedBeams._state`)."""

    coef: np.ndarray  # (B, P, 4) segment start states
    slope: np.ndarray  # (B, P*Q) y' at the nodes, pitch units
    second: np.ndarray  # (B, P*Q) y''
    length: np.ndarray  # (B,) arc length, mm

    def where(self, mask: np.ndarray, other: _State) -> _State:
        """``other`` for the beams in ``mask``, self elsewhere."""
        column = mask[:, None]
        return _State(np.where(mask[:, None, None], other.coef, self.coef),
                      np.where(column, other.slope, self.slope),
                      np.where(column, other.second, self.second),
                      np.where(mask, other.length, self.length))


class _ShapeEvaluator:
    """y(beam, s) of solved beams: the segment's state times row 0 of its fundamental matrix.

    ``prepare(beam, s)`` does the frame-independent part (segment, offset) once for points
    asked again and again (a fabric plan); ``prepared(query)`` evaluates it for this frame.
    """

    def __init__(self, solver: CompressedBeams, a: np.ndarray, coef: np.ndarray) -> None:
        self.d, self.b = solver.d, solver.b
        self.seg_start, self.n_segments = solver.seg_start, solver.n_segments
        self.a, self.coef = a, coef

    def prepare(self, beam: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
        s_hat = s / self.d
        seg = np.sum(s_hat[:, None] >= self.seg_start[beam], axis=1) - 1
        seg = np.clip(seg, 0, self.n_segments[beam] - 1)
        t = s_hat - self.seg_start[beam, seg]
        return beam, seg, t, t * t, t**3

    def __call__(self, beam: np.ndarray, s: np.ndarray) -> np.ndarray:
        return self.prepared(self.prepare(beam, s))

    def prepared(self, query: tuple[np.ndarray, ...]) -> np.ndarray:
        beam, seg, t, t2, t3 = query
        c = self.coef[beam, seg]
        a = self.a[beam]
        if self.b == 0.0:
            a = np.maximum(a, TINY_LOAD)
            k = np.sqrt(a)
            theta = k * t
            half_sin = np.sin(0.5 * theta)
            one_minus_cos = 2.0 * half_sin * half_sin / a
            cubic = t3 * theta_minus_sin_over_cube(theta)  # (kt - sin kt)/k^3
            return c[:, 0] + c[:, 1] * t + c[:, 2] * one_minus_cos + c[:, 3] * cubic
        phi = fundamental_matrix(t[:, None], a, self.b)[:, 0, 0, :]
        return np.einsum("nj,nj->n", phi, c)


@register
class BeamModel(NetworkModel):
    """The CRS: compressed beams (length = commanded length) joined by the fabric in 2D.

    Options: ``foundation`` (use the layout's Winkler beta for a skin pressed onto the
    skeleton, Fig. 3; default False: the display as shown, and the closed form is ~3x faster),
    ``critical_margin`` (0.98), ``check_yield_curvature`` (True), ``fabric_subdivisions``,
    ``memo_frames`` (256: the last frames' solutions, and failures, are kept in an LRU keyed by
    the setpoints' bytes, since a session shows the same stimuli again and again) and
    ``quantum_mm`` (0: off; > 0 rounds the setpoints to this step before solving and keying,
    so near-repeats hit the memo too; 1e-4 mm is far below the servos' ~0.01 mm step).
    """

    name = "beam"
    description = "compressed beam (CRS): EI y'''' + N y'' + beta y = 0, arc length = command"

    def __init__(self, layout: Layout, foundation: bool = False, critical_margin: float = 0.98,
                 check_yield_curvature: bool = True, memo_frames: int = 256,
                 quantum_mm: float = 0.0, **options) -> None:
        super().__init__(layout, **options)
        if not (isinstance(memo_frames, int) and memo_frames >= 0):
            raise DisplayModelError(f"beam: memo_frames must be a whole number >= 0, "
                                    f"got {memo_frames!r}")
        if not (isinstance(quantum_mm, int | float) and math.isfinite(quantum_mm)
                and quantum_mm >= 0.0):
            raise DisplayModelError(f"beam: quantum_mm must be >= 0 (mm), got {quantum_mm!r}")
        self.solver = CompressedBeams.for_layout(layout, foundation, critical_margin)
        self.check_yield_curvature = check_yield_curvature
        self.memo_frames = memo_frames
        self.quantum_mm = float(quantum_mm)
        self._memo: OrderedDict[bytes, BeamProfiles | DisplayModelError] = OrderedDict()

    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        setpoints = np.asarray(setpoints_mm, dtype=float)
        if self.quantum_mm > 0.0 and setpoints.ndim == 1:
            setpoints = np.round(setpoints / self.quantum_mm) * self.quantum_mm
        key = setpoints.tobytes()
        found = self._memo.get(key)
        if found is None:
            try:
                found = self.solver.solve(setpoints, self.check_yield_curvature, self.name)
            except DisplayModelError as exc:  # collapse and yield: as repeatable as a shape
                if setpoints.shape != (self.layout.n_actuators,):
                    raise  # a malformed call is not a frame
                found = exc
            if self.memo_frames:
                self._memo[key] = found
                if len(self._memo) > self.memo_frames:
                    self._memo.popitem(last=False)
        else:
            self._memo.move_to_end(key)
        if isinstance(found, DisplayModelError):
            raise found.with_traceback(None)
        return found
