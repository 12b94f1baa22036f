"""The equations of the compressed beam: EI y'''' + N y'' + beta y = 0 on each segment.

The solver (:mod:`crs_study.display.beam`) finds the axial load N of every beam; this module
gives, for a load, the shape through the pixel heights (Wang, Meng & Chen 2025, the ODE
behind Eq. 3) and the no-collapse number of Eq. 4 (docs/physics.md, "The compressed beam").

Solution per segment
    With k = sqrt(N/EI) and beta = 0 the segment solution is a combination of
    {1, x, cos kx, sin kx}; we use the normalised fundamental system
    {1, x, (1 - cos kx)/k^2, (kx - sin kx)/k^3} (the state-transition matrix expm(M x)), written
    as t^2/2 sinc^2 and a short series so that k -> 0 tends stably to the cubic (the spline).
    With beta > 0 the same matrix comes from its Taylor series (recurrence
    c_{n+4} = -a c_{n+2} - b c_n). Unknowns are the states (y, y', y'', y''') at each segment
    start: a 4(m+1) linear system per beam, all beams batched, lengths in pitch units. With
    beta = 0 (the default) the same states come from the slopes at the pixels alone
    (slope-deflection: an m x m tridiagonal system per beam, ``BeamSet._slope_deflection``).
    Arc length: 8-point Gauss-Legendre per segment (the integrand is analytic, k l <= 2 pi
    below the critical load: error ~1e-11 of the length).
"""

from __future__ import annotations

import math

import numpy as np

from crs_study.errors import DisplayModelError

GL_NODES, GL_WEIGHTS = np.polynomial.legendre.leggauss(8)
_SERIES_TERMS = 64
_SERIES_LIMIT = 12.0  # largest rho * t for which 64 Taylor terms stay accurate (~1e-12)
#: smallest dimensionless load used in the closed forms (their a -> 0 limits are exact there)
TINY_LOAD = 1e-100
_FACTORIALS = np.array([math.factorial(n) for n in range(_SERIES_TERMS)], dtype=float)


def no_collapse_number(bending_stiffness: float, beta: float, pitch_mm: float) -> float:
    """Delta = 16 pi^4 EI / (27 beta d^4) (Wang, Meng & Chen 2025, Eq. 4); inf when beta = 0."""
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


def theta_minus_sin_over_cube(theta: np.ndarray) -> np.ndarray:
    """(theta - sin theta) / theta^3, by its series below 0.5 (no cancellation)."""
    if theta.size and theta.min() >= 0.5:  # the common case of a loaded segment
        return (theta - np.sin(theta)) / (theta * theta * theta)
    small = theta < 0.5
    th2 = theta * theta
    series = 1 / 6 - th2 * (1 / 120 - th2 * (1 / 5040 - th2 * (1 / 362880 - th2 * (
        1 / 39916800 - th2 / 6227020800))))
    safe = np.where(small, 1.0, theta)
    return np.where(small, series, (safe - np.sin(safe)) / safe**3)


def _trig_fundamental(t: np.ndarray, a: np.ndarray) -> np.ndarray:
    sin_over_k, one_minus_cos, cos = _trig_terms(t, a)
    out = np.zeros(t.shape + (4, 4))
    out[..., 0, 0] = 1.0
    out[..., 0, 1] = t
    out[..., 1, 1] = 1.0
    out[..., 0, 2] = one_minus_cos
    out[..., 1, 2] = sin_over_k
    out[..., 2, 2] = cos
    out[..., 3, 2] = -a * sin_over_k
    out[..., 0, 3] = t**3 * theta_minus_sin_over_cube(np.sqrt(a) * t)
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


def _trig_terms(t: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sin(kt)/k, (1 - cos kt)/k^2 and cos kt for k = sqrt(a) >= 0 (exact limits at a = 0).

    The fast path of :func:`_trig_fundamental` for the rows the solver needs. 2 sin^2(kt/2)/a
    has no cancellation, so a is merely kept above ``TINY_LOAD`` (where both forms equal
    their a = 0 limits t and t^2/2 to the last bit).
    """
    a = np.maximum(a, TINY_LOAD)
    k = np.sqrt(a)
    theta = k * t
    half_sin = np.sin(0.5 * theta)
    one_minus_cos = 2.0 * half_sin * half_sin / a
    return np.sin(theta) / k, one_minus_cos, 1.0 - a * one_minus_cos


class BeamSet:
    """Padded per-segment arrays and the linear system of a list of beams (pitch units).

    Beam i has supports ``supports[i]`` (clamp, pixels, clamp); all beams are padded to
    ``n_seg_max`` segments (padding segments have zero length and state c = 0).
    """

    def __init__(self, supports: list[np.ndarray], n_seg_max: int) -> None:
        self.n_beams = n_beams = len(supports)
        self.n_segments = np.array([len(s) - 1 for s in supports])
        self.n_seg_max = p = n_seg_max
        self.n_pixels = max(p - 1, 1)
        self.seg_start = np.zeros((n_beams, p))
        self.lengths = np.zeros((n_beams, p))
        for bi, s in enumerate(supports):
            n = len(s) - 1
            self.seg_start[bi, :n] = s[:-1]
            self.seg_start[bi, n:] = s[-1]
            self.lengths[bi, :n] = np.diff(s)
        self._build_templates()
        q = len(GL_NODES)
        self.t_nodes = ((GL_NODES[None, None, :] + 1.0) / 2.0
                        * self.lengths[:, :, None]).reshape(n_beams, p * q)
        self.w_nodes = (GL_WEIGHTS[None, None, :] / 2.0
                        * self.lengths[:, :, None]).reshape(n_beams, p * q)
        self.node_seg = np.repeat(np.arange(p), q)
        # slope-deflection masks: padding segments, real pixels, pixel pairs
        self._padding = self.lengths <= 0.0
        real = np.arange(self.n_pixels)[None, :] < (self.n_segments - 1)[:, None]
        self._pixel_valid = real.astype(float)
        self._pixel_pair = (real[:, :, None] & real[:, None, :]).astype(float)
        self._pixel_padding = np.eye(self.n_pixels)[None] * (~real)[:, :, None]
        self._diag = np.arange(self.n_pixels)
        self._has_padding = bool(self._padding.any())
        supports = np.arange(p + 1)[None, :] <= self.n_segments[:, None]
        self._support_is_pixel_or_clamp = supports.astype(float)

    def _build_templates(self) -> None:
        n_beams, p = self.n_beams, self.n_seg_max
        size = 4 * p
        template = np.zeros((n_beams, size, size))
        rhs = np.zeros((n_beams, size, self.n_pixels))
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
        self.template = template
        self.rhs = rhs
        self.index = tuple(np.array(v, dtype=int) for v in (pb, prow, pcol, pseg, pr, pi))

    def system(self, a: np.ndarray, b: float) -> np.ndarray:
        """Matrices (..., B, 4P, 4P) for dimensionless loads a of shape (..., B)."""
        pb, prow, pcol, pseg, pr, pi = self.index
        phi = fundamental_matrix(np.broadcast_to(self.lengths, a.shape + (self.n_seg_max,)),
                                 a, b)
        system = np.broadcast_to(self.template, a.shape[:-1] + self.template.shape).copy()
        system[..., pb, prow, pcol] = phi[..., pb, pseg, pr, pi]
        return system

    def coefficients(self, a: np.ndarray, b: float, heights: np.ndarray) -> np.ndarray:
        """Segment start states (B, P, 4) for loads a (B,) and pixel heights (B, n_pix)."""
        if b == 0.0:
            return self._slope_deflection(a, heights)
        rhs = np.matmul(self.rhs, heights[:, :, None])
        coef = np.linalg.solve(self.system(a, b), rhs)[..., 0]
        return coef.reshape(self.n_beams, self.n_seg_max, 4)

    def _slope_deflection(self, a: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """The same states for beta = 0 from the slopes at the pixels alone (beam-column
        slope-deflection method, e.g. Timoshenko & Gere, Theory of Elastic Stability, 1.11).

        On a segment of length l with end heights Y_i, Y_j and end slopes theta_i, theta_j,
        y = Y_i + theta_i t + c2 (1 - cos kt)/k^2 + c3 (kt - sin kt)/k^3 with
        [C D; s C] [c2; c3] = [Y_j - Y_i - theta_i l; theta_j - theta_i] (C, D, s: the
        functions at t = l). Moment continuity y''(l-) = y''(0+) at each pixel gives a
        tridiagonal system in the pixel slopes (clamps: theta = 0), n_pix unknowns a beam
        instead of 4(n_pix + 1). det = C^2 - D s vanishes only at a segment's own
        clamped-clamped buckling load, above the beam's critical load.
        """
        ell = self.lengths
        a = np.maximum(a, TINY_LOAD)[:, None]  # a -> 0 is the spline: no special case needed
        k = np.sqrt(a)
        theta = k * ell
        half_sin = np.sin(0.5 * theta)
        big_c = 2.0 * half_sin * half_sin / a  # (1 - cos kl)/k^2
        small_s = np.sin(theta) / k  # sin(kl)/k
        cos = 1.0 - a * big_c
        big_d = ell**3 * theta_minus_sin_over_cube(theta)  # (kl - sin kl)/k^3
        if self._has_padding:
            big_c = np.where(self._padding, 1.0, big_c)
        det = big_c * big_c - big_d * small_s
        # rows: c2 = [alpha, beta, gamma] . (th_i, th_j, dY), c3 likewise (alpha2 ...)
        terms = np.stack([big_d - big_c * ell, -big_d, big_c,
                          small_s * ell - big_c, big_c, -small_s]) / det
        # curvature at the segment's right end: c2 cos + c3 s
        right = terms[:3] * cos + terms[3:] * small_s
        y = np.zeros((self.n_beams, self.n_seg_max + 1))
        y[:, 1:-1] = heights
        if self._has_padding:
            y *= self._support_is_pixel_or_clamp
        dy = y[:, 1:] - y[:, :-1]
        q = self.n_pixels
        matrix = np.zeros((self.n_beams, q, q))
        d = self._diag
        matrix[:, d, d] = right[1, :, :q] - terms[0, :, 1:]
        matrix[:, d[1:], d[:-1]] = right[0, :, 1:q]
        matrix[:, d[:-1], d[1:]] = -terms[1, :, 1:q]
        rhs = terms[2, :, 1:] * dy[:, 1:] - right[2, :, :q] * dy[:, :q]
        if self._has_padding:
            matrix = matrix * self._pixel_pair + self._pixel_padding
            rhs = rhs * self._pixel_valid
        slopes = np.zeros((self.n_beams, self.n_seg_max + 1))
        slopes[:, 1:-1] = np.linalg.solve(matrix, rhs[:, :, None])[..., 0]
        if self._has_padding:
            slopes[:, 1:-1] *= self._pixel_valid
        coef = np.empty((self.n_beams, self.n_seg_max, 4))
        coef[..., 0] = y[:, :-1]
        coef[..., 1] = slopes[:, :-1]
        coef[..., 2:] = np.moveaxis(terms[0::3] * slopes[:, :-1] + terms[1::3] * slopes[:, 1:]
                                    + terms[2::3] * dy, 0, -1)
        return coef

    def node_derivatives(self, a: np.ndarray, b: float, coef: np.ndarray,
                         second: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """(y', y'') at the quadrature nodes, pitch units, each (B, P*Q); y'' only if asked."""
        states = coef[:, self.node_seg, :]
        if b == 0.0:
            sin_over_k, one_minus_cos, cos = _trig_terms(self.t_nodes, a[:, None])
            slope = (states[..., 1] + states[..., 2] * sin_over_k
                     + states[..., 3] * one_minus_cos)
            if not second:
                return slope, None
            return slope, states[..., 2] * cos + states[..., 3] * sin_over_k
        phi = fundamental_matrix(self.t_nodes, a, b)[..., 1:3, :]
        both = np.einsum("bnrj,bnj->rbn", phi, states)
        return both[0], both[1]
