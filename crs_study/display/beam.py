"""``beam``: the compressed beam of the CRS, solved in closed form per segment.

Each beam runs from its start clamp (s = 0) through its pixels to its end clamp (s = S).
Between consecutive constraint points it obeys (crs-paper.md, Mechanical model; Eq. 3's ODE)::

    EI y'''' + N y'' + beta y = 0,

N the compressive axial load, beta the Winkler foundation of a skin pressed onto the skeleton
(``foundation=True``: ``layout.foundation_stiffness``; the default ``False`` is the issue's
"optionally": beta = 0, the display as shown, and the trigonometric closed form).
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
    With k = sqrt(N/EI) and beta = 0 the segment solution is a combination of
    {1, x, cos kx, sin kx}; we use the normalised fundamental system
    {1, x, (1 - cos kx)/k^2, (kx - sin kx)/k^3} (the state-transition matrix expm(M x)), written
    as t^2/2 sinc^2 and a short series so that k -> 0 tends stably to the cubic (the spline).
    With beta > 0 the same matrix comes from its Taylor series (recurrence
    c_{n+4} = -a c_{n+2} - b c_n). Unknowns are the states (y, y', y'', y''') at each segment
    start; a 4(m+1) linear system per beam, all beams batched, lengths in pitch units.
Root finding
    L(N) is evaluated on a per-layout grid of N (the map from pixel heights to slopes is linear
    and precomputed for each grid N), the first grid interval reaching the commanded length
    brackets N, and a vectorised Illinois (regula falsi) iteration on exact solves refines all
    beams at once (one batched solve per step instead of a scalar brentq per beam).
    |L - L_c (1 - N/EA)| <= 1e-9 S.

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

import numpy as np
from scipy.optimize import brentq

from crs_study.display.base import register
from crs_study.display.network import (
    BeamProfiles,
    NetworkModel,
    beam_support_positions,
    check_setpoints,
    check_yield,
    commanded_lengths,
)
from crs_study.errors import CollapseError, DisplayModelError
from crs_study.layout import Layout

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(12)
_SERIES_TERMS = 64
_SERIES_LIMIT = 12.0  # largest rho * t for which 64 Taylor terms stay accurate (~1e-12)
_SCAN_POINTS = 400  # grid for the first determinant sign change (critical load)
_GRID_POINTS = 48  # N grid for bracketing the length root
_FACTORIALS = np.array([math.factorial(n) for n in range(_SERIES_TERMS)], dtype=float)


def no_collapse_number(bending_stiffness: float, beta: float, pitch_mm: float) -> float:
    """Delta = 16 pi^4 EI / (27 beta d^4) (crs-paper.md, Eq. 4); inf when beta = 0."""
    if beta <= 0.0:
        return math.inf
    return 16.0 * math.pi**4 * bending_stiffness / (27.0 * beta * pitch_mm**4)


def fundamental_matrix(t: np.ndarray, a: np.ndarray, b: float = 0.0) -> np.ndarray:
    """State-transition matrix of y'''' + a y'' + b y = 0: ``Phi[..., T, r, i] = phi_i^(r)(t)``.

    ``a`` has shape (...), ``t`` shape (..., T); phi_i is the solution with
    phi_i^(r)(0) = delta_ir. a = N d^2/EI and b = beta d^4/EI in pitch units, a >= 0.
    """
    t = np.asarray(t, dtype=float)
    a = np.maximum(np.asarray(a, dtype=float), 0.0)
    if b == 0.0:
        return _trig_fundamental(t, np.broadcast_to(a[..., None], t.shape))
    return _series_fundamental(t, a, float(b))


def _theta_minus_sin_over_cube(theta: np.ndarray) -> np.ndarray:
    """(theta - sin theta) / theta^3, by its series below 0.5 (no cancellation)."""
    small = theta < 0.5
    th2 = theta * theta
    series = 1 / 6 - th2 * (1 / 120 - th2 * (1 / 5040 - th2 * (1 / 362880 - th2 * (
        1 / 39916800 - th2 / 6227020800))))
    safe = np.where(small, 1.0, theta)
    return np.where(small, series, (safe - np.sin(safe)) / safe**3)


def _trig_fundamental(t: np.ndarray, a: np.ndarray) -> np.ndarray:
    k = np.sqrt(a)
    theta = k * t
    sin_over_k = t * np.sinc(theta / np.pi)  # sin(kt)/k
    one_minus_cos = 0.5 * t * t * np.sinc(theta / (2 * np.pi)) ** 2  # (1 - cos kt)/k^2
    cos = np.cos(theta)
    out = np.zeros(t.shape + (4, 4))
    out[..., 0, 0] = 1.0
    out[..., 0, 1] = t
    out[..., 1, 1] = 1.0
    out[..., 0, 2] = one_minus_cos
    out[..., 1, 2] = sin_over_k
    out[..., 2, 2] = cos
    out[..., 3, 2] = -a * sin_over_k
    out[..., 0, 3] = t**3 * _theta_minus_sin_over_cube(theta)
    out[..., 1, 3] = one_minus_cos
    out[..., 2, 3] = sin_over_k
    out[..., 3, 3] = cos
    return out


def _series_fundamental(t: np.ndarray, a: np.ndarray, b: float) -> np.ndarray:
    """Taylor series of the impulse response g (g = g' = g'' = 0 and g''' = 1 at t = 0).

    g^(n+4)(0) = -a g^(n+2)(0) - b g^(n)(0); the normalised system is phi_3 = g, phi_2 = g',
    phi_1 = g'' + a g, phi_0 = g''' + a g' (the standard construction for p(D) = D^4 + aD^2 + b).
    """
    rho = max(float(np.sqrt(np.max(a, initial=0.0))), b**0.25)
    if rho * float(np.max(np.abs(t), initial=0.0)) > _SERIES_LIMIT:
        raise DisplayModelError(
            f"beam: segment too long for the foundation series (rho t = "
            f"{rho * np.max(np.abs(t)):.3g} > {_SERIES_LIMIT}); reduce end_margin_pitch or "
            f"the foundation stiffness")
    m = _SERIES_TERMS
    odd = np.zeros(a.shape + ((m + 8) // 2,))  # g^(2j+1)(0)
    odd[..., 1] = 1.0
    for j in range(odd.shape[-1] - 2):
        odd[..., j + 2] = -a * odd[..., j + 1] - b * odd[..., j]
    seq = np.zeros(a.shape + (2 * odd.shape[-1],))
    seq[..., 1::2] = odd
    windows = np.lib.stride_tricks.sliding_window_view(seq, m, axis=-1)[..., :7, :]
    powers = t[..., None] ** np.arange(m) / _FACTORIALS
    g = np.einsum("...tj,...rj->...tr", powers, windows)  # g^(r)(t), r = 0..6
    aa = a[..., None, None]
    out = np.empty(t.shape + (4, 4))
    out[..., 3] = g[..., 0:4]
    out[..., 2] = g[..., 1:5]
    out[..., 1] = g[..., 2:6] + aa * g[..., 0:4]
    out[..., 0] = g[..., 3:7] + aa * g[..., 1:5]
    return out


class CompressedBeams:
    """Per-layout solver for every beam at once (see the module docstring). Build once."""

    _cache: dict[tuple, CompressedBeams] = {}

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
        self.n_beams = n_beams = len(supports)
        self.n_segments = np.array([len(s) - 1 for s in supports])
        self.n_seg_max = p = int(self.n_segments.max())
        self.spans = np.array([beam.straight_length for beam in layout.beams])
        self.seg_start = np.zeros((n_beams, p))
        self.lengths = np.zeros((n_beams, p))
        self.pixel_map = np.full((n_beams, max(p - 1, 1)), -1)
        for bi, (s, beam) in enumerate(zip(supports, layout.beams, strict=True)):
            n = len(s) - 1
            self.seg_start[bi, :n] = s[:-1]
            self.seg_start[bi, n:] = s[-1]
            self.lengths[bi, :n] = np.diff(s)
            self.pixel_map[bi, : n - 1] = beam.pixels
        self.supports = supports
        self._build_templates()
        q = len(_GL_NODES)
        self.t_nodes = ((_GL_NODES[None, None, :] + 1.0) / 2.0
                        * self.lengths[:, :, None]).reshape(n_beams, p * q)
        self.w_nodes = (_GL_WEIGHTS[None, None, :] / 2.0
                        * self.lengths[:, :, None]).reshape(n_beams, p * q)
        self.node_seg = np.repeat(np.arange(p), q)
        self.a_critical = self._critical_a()
        self.critical_load_n = self.a_critical * self.ei / d**2
        self._build_grid()

    # --- assembly -------------------------------------------------------------------------
    def _build_templates(self) -> None:
        n_beams, p = self.n_beams, self.n_seg_max
        size = 4 * p
        template = np.zeros((n_beams, size, size))
        rhs = np.zeros((n_beams, size, self.pixel_map.shape[1]))
        pb, prow, pcol, pseg, pr, pi = [], [], [], [], [], []

        def phi_row(bi: int, row: int, seg: int, r: int) -> None:
            for i in range(4):
                pb.append(bi)
                prow.append(row)
                pcol.append(4 * seg + i)
                pseg.append(seg)
                pr.append(r)
                pi.append(i)

        for bi in range(n_beams):
            n = int(self.n_segments[bi])
            template[bi, 0, 0] = template[bi, 1, 1] = 1.0
            for j in range(n - 1):  # junction j: pixel j between segments j and j + 1
                row = 2 + 4 * j
                phi_row(bi, row, j, 0)
                rhs[bi, row, j] = 1.0
                template[bi, row + 1, 4 * (j + 1)] = 1.0
                rhs[bi, row + 1, j] = 1.0
                phi_row(bi, row + 2, j, 1)
                template[bi, row + 2, 4 * (j + 1) + 1] = -1.0
                phi_row(bi, row + 3, j, 2)
                template[bi, row + 3, 4 * (j + 1) + 2] = -1.0
            phi_row(bi, 4 * n - 2, n - 1, 0)
            phi_row(bi, 4 * n - 1, n - 1, 1)
            for row in range(4 * n, size):  # padding segments: c = 0
                template[bi, row, row] = 1.0
        self._template = template
        self._rhs = rhs
        self._index = tuple(np.array(v) for v in (pb, prow, pcol, pseg, pr, pi))

    def _system(self, a: np.ndarray) -> np.ndarray:
        """Matrices (..., B, 4P, 4P) for dimensionless loads a of shape (..., B)."""
        pb, prow, pcol, pseg, pr, pi = self._index
        phi = fundamental_matrix(np.broadcast_to(self.lengths, a.shape + (self.n_seg_max,)),
                                 a, self.b)
        system = np.broadcast_to(self._template, a.shape[:-1] + self._template.shape).copy()
        system[..., pb, prow, pcol] = phi[..., pb, pseg, pr, pi]
        return system

    def _coefficients(self, a: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """Segment start states (B, P, 4) for loads a (B,) and pixel heights (B, n_pix)."""
        rhs = np.einsum("bkp,bp->bk", self._rhs, heights)
        coef = np.linalg.solve(self._system(a), rhs[..., None])[..., 0]
        return coef.reshape(self.n_beams, self.n_seg_max, 4)

    def _node_derivatives(self, a: np.ndarray, coef: np.ndarray) -> np.ndarray:
        """(y', y'') at the quadrature nodes, pitch units: shape (2, B, P*Q)."""
        phi = fundamental_matrix(self.t_nodes, a, self.b)[..., 1:3, :]
        states = coef[:, self.node_seg, :]
        return np.einsum("bnrj,bnj->rbn", phi, states)

    def _arc_length(self, slopes: np.ndarray) -> np.ndarray:
        """Arc length (mm) from slopes dy/ds_hat (mm per pitch) at the nodes, (..., B, P*Q)."""
        return self.d * np.sum(self.w_nodes * np.sqrt(1.0 + (slopes / self.d) ** 2), axis=-1)

    # --- per-layout precomputation --------------------------------------------------------
    def _critical_a(self) -> np.ndarray:
        """First zero of det(A(a)) per beam: the critical load in units EI/d^2."""
        longest = self.lengths.max(axis=1)
        upper = 1.05 * ((2 * np.pi / longest) ** 2 + 3 * self.b * longest**2 / (4 * np.pi**2))
        grid = np.linspace(0.0, 1.0, _SCAN_POINTS)[:, None] * upper[None, :]
        sign, _ = np.linalg.slogdet(self._system(grid))
        out = upper.copy()
        for bi in range(self.n_beams):
            change = np.flatnonzero(sign[1:, bi] * sign[0, bi] <= 0)
            if change.size == 0:
                continue  # no sign change below the Rayleigh bound: keep the bound
            k = int(change[0]) + 1

            _, ref = np.linalg.slogdet(self._system(grid[k - 1])[bi])

            def det(x: float, bi: int = bi, ref: float = ref) -> float:
                a = np.zeros(self.n_beams)
                a[bi] = x
                s, logdet = np.linalg.slogdet(self._system(a)[bi])
                return float(s * np.exp(logdet - ref))

            out[bi] = brentq(det, grid[k - 1, bi], grid[k, bi], xtol=1e-13, rtol=1e-13)
        return out

    def _build_grid(self) -> None:
        """Slope operators (K, B, P*Q, n_pix) on a grid of a in [0, margin a_cr]."""
        u = np.linspace(0.0, 1.0, _GRID_POINTS)[:, None]
        self.a_grid = self.margin * self.a_critical[None, :] * (1.0 - (1.0 - u) ** 2)
        n_pix = self.pixel_map.shape[1]
        basis = np.linalg.solve(self._system(self.a_grid), self._rhs[None])  # (K, B, 4P, n_pix)
        basis = basis.reshape(_GRID_POINTS, self.n_beams, self.n_seg_max, 4, n_pix)
        phi = fundamental_matrix(np.broadcast_to(self.t_nodes, self.a_grid.shape
                                                 + self.t_nodes.shape[1:]), self.a_grid, self.b)
        self._grid_slopes = np.einsum("kbnj,kbnjp->kbnp", phi[..., 1, :],
                                      basis[:, :, self.node_seg])

    # --- per frame ------------------------------------------------------------------------
    def heights(self, setpoints: np.ndarray) -> np.ndarray:
        return np.where(self.pixel_map >= 0, setpoints[np.maximum(self.pixel_map, 0)], 0.0)

    def solve(self, setpoints_mm: np.ndarray, check_yield_curvature: bool = True,
              model: str = "beam") -> BeamProfiles:
        """Shapes with N solved so each beam's arc length equals its commanded length."""
        setpoints = check_setpoints(self.layout, setpoints_mm, model)
        heights = self.heights(setpoints)
        target = commanded_lengths(self.layout, setpoints)
        grid_lengths = self._arc_length(np.einsum("kbnp,bp->kbn", self._grid_slopes, heights))
        # the steel shortens by N L / (E A) under the load: shape length = L_c (1 - N / EA)
        grid_target = target[None, :] * (1.0 - self.a_grid * self.axial_compliance)
        excess = grid_lengths - grid_target
        tolerance = 1e-9 * self.spans
        need = excess[0] < -tolerance
        a = np.zeros(self.n_beams)
        if np.any(need):
            if self.delta < 1.0:
                bi = int(np.flatnonzero(need)[0])
                raise CollapseError(
                    f"{model}: beam {bi}: Delta = {self.delta:.3g} < 1 (Eq. 4, beta = "
                    f"{self.beta:.3g} N/mm^2): the compressed beam collapses into the skin; use "
                    f"a stiffer beam, a softer skin or a smaller pitch")
            reached = excess >= 0.0
            unreachable = need & ~reached.any(axis=0)
            if np.any(unreachable):
                bi = int(np.flatnonzero(unreachable)[0])
                raise CollapseError(
                    f"{model}: beam {bi}: commanded length {target[bi]:.4f} mm needs N >= "
                    f"{self.margin:g} N_cr = {self.margin * self.critical_load_n[bi]:.4g} N "
                    f"(longest stable shape {grid_lengths[-1, bi]:.4f} mm): the beam collapses; "
                    f"reduce the boundary feed or the stimulus height")
            a = self._refine(need, np.argmax(reached, axis=0), excess, target, heights,
                             tolerance)
        return self._profiles(a, heights, target, check_yield_curvature, model)

    def _refine(self, need, first, excess, target, heights, tolerance) -> np.ndarray:
        """Illinois iteration on f(a) = L(a) - L_c (1 - N/EA) inside each grid bracket."""
        cols = np.arange(self.n_beams)
        hi_index = np.maximum(first, 1)
        lo = self.a_grid[hi_index - 1, cols]
        hi = self.a_grid[hi_index, cols]
        f_lo = excess[hi_index - 1, cols]
        f_hi = excess[hi_index, cols]
        a = np.where(need, lo, 0.0)
        active = need.copy()
        side = np.zeros(self.n_beams, dtype=int)
        for _ in range(60):
            if not np.any(active):
                break
            trial = np.where(active, (lo * f_hi - hi * f_lo) / np.where(
                f_hi != f_lo, f_hi - f_lo, 1.0), a)
            coef = self._coefficients(trial, heights)
            f = (self._arc_length(self._node_derivatives(trial, coef)[0])
                 - target * (1.0 - trial * self.axial_compliance))
            a = np.where(active, trial, a)
            done = np.abs(f) <= tolerance
            upper = active & (f > 0)
            lower = active & (f <= 0)
            f_lo = np.where(upper & (side == 1), f_lo / 2.0, f_lo)
            f_hi = np.where(lower & (side == -1), f_hi / 2.0, f_hi)
            hi, f_hi = np.where(upper, trial, hi), np.where(upper, f, f_hi)
            lo, f_lo = np.where(lower, trial, lo), np.where(lower, f, f_lo)
            side = np.where(upper, 1, np.where(lower, -1, side))
            active &= ~done & (hi - lo > 1e-14 * self.a_critical)
        return a

    def _profiles(self, a, heights, target, check_yield_curvature, model) -> BeamProfiles:
        coef = self._coefficients(a, heights)
        slope, second = self._node_derivatives(a, coef)
        lengths = self._arc_length(slope)
        if check_yield_curvature:
            curvature = np.abs(second) / self.d**2 / (1.0 + (slope / self.d) ** 2) ** 1.5
            at_supports = np.abs(coef[:, :, 2]) / self.d**2  # y'' at segment starts (y' = 0
            # at clamps; at pixels the slope factor only lowers it, so this bounds from above)
            worst = np.maximum(curvature.max(axis=1), at_supports.max(axis=1))
            for bi in np.argsort(-worst)[:1]:
                check_yield(model, int(bi), float(worst[bi]), self.layout)
        seg_start = self.seg_start
        n_segments = self.n_segments
        d, b = self.d, self.b

        def evaluate(beam: np.ndarray, s: np.ndarray) -> np.ndarray:
            s_hat = s / d
            seg = np.sum(s_hat[:, None] >= seg_start[beam], axis=1) - 1
            seg = np.clip(seg, 0, n_segments[beam] - 1)
            t = s_hat - seg_start[beam, seg]
            phi = fundamental_matrix(t[:, None], a[beam], b)[:, 0, 0, :]
            return np.einsum("nj,nj->n", phi, coef[beam, seg])

        return BeamProfiles(
            spans_mm=self.spans, evaluate=evaluate,
            axial_load_n=a * self.ei / self.d**2, critical_load_n=self.critical_load_n,
            commanded_length_mm=target, length_mm=lengths,
        )

    def solve_with_load(self, setpoints_mm: np.ndarray, axial_load_n: np.ndarray | float
                        ) -> BeamProfiles:
        """Shapes for a given axial load N (no length condition): for checks against Eq. 3."""
        setpoints = check_setpoints(self.layout, setpoints_mm, "beam")
        a = np.broadcast_to(np.asarray(axial_load_n, dtype=float) * self.d**2 / self.ei,
                            (self.n_beams,)).copy()
        return self._profiles(a, self.heights(setpoints),
                              commanded_lengths(self.layout, setpoints), False, "beam")


@register
class BeamModel(NetworkModel):
    """The CRS: compressed beams (length = commanded length) joined by the fabric in 2D.

    Options: ``foundation`` (use the layout's Winkler beta for a skin pressed onto the
    skeleton, Fig. 3; default False: the display as shown, and the closed form is ~3x faster),
    ``critical_margin`` (0.98), ``check_yield_curvature`` (True), ``fabric_subdivisions``.
    """

    name = "beam"
    description = "compressed beam (CRS): EI y'''' + N y'' + beta y = 0, arc length = command"

    def __init__(self, layout: Layout, foundation: bool = False, critical_margin: float = 0.98,
                 check_yield_curvature: bool = True, **options) -> None:
        super().__init__(layout, **options)
        self.solver = CompressedBeams.for_layout(layout, foundation, critical_margin)
        self.check_yield_curvature = check_yield_curvature
        self._last: tuple[bytes, BeamProfiles] | None = None

    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        key = np.asarray(setpoints_mm, dtype=float).tobytes()
        if self._last is None or self._last[0] != key:  # a held frame is solved once
            self._last = (key, self.solver.solve(setpoints_mm, self.check_yield_curvature,
                                                 self.name))
        return self._last[1]
