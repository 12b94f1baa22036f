"""``reference``: a high-fidelity, independent model of the length-constrained beam.

Each beam is discretised by cubic Hermite finite elements (nodal y and y', ``elements`` per
segment between constraint points) and its shape is the minimiser of the bending (+ Winkler)
energy under the pixel constraints, clamped ends and the length constraint::

    minimise  U(y) = integral EI y''^2 / 2 + beta y^2 / 2 ds
    subject to y = h at the pixels, y = y' = 0 at the clamps,
               g(y) = integral sqrt(1 + y'^2) ds = L_c (1 - N / EA).

The Lagrange multiplier of the length constraint is the axial load N: for a given N the
equilibrium K y - N grad g(y) = 0 is solved by Newton's method (exact arc length, so the axial
term is (y' / sqrt(1 + y'^2))' rather than the ``beam`` model's linearised y''), and N is found
by brentq on g(y(N)) - L_c (1 - N/EA) in [0, margin N_cr]. N_cr is the first load at which the
tangent stiffness K - N G_0 stops being positive definite (banded Cholesky, bisection), found
here independently of the ``beam`` model's determinant search. Gauss-Legendre (6 points per
element) for every integral. The same failure rules as ``beam``: collapse (N would reach
margin N_cr, or Delta < 1 under compression) raises CollapseError; the tension case returns
the N = 0 shape. It costs tens of milliseconds a beam: a yardstick, not a runtime model. In 2D
its fabric is four times finer than the runtime models' (:data:`REFERENCE_FABRIC_SUBDIVISIONS`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicHermiteSpline
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded
from scipy.optimize import brentq

from crs_study.display.base import register
from crs_study.display.beam_equations import no_collapse_number
from crs_study.display.network import (
    BeamProfiles,
    NetworkModel,
    beam_support_positions,
    check_setpoints,
    check_yield,
    commanded_lengths,
)
from crs_study.errors import CollapseError, DisplayModelError
from crs_study.geometry.layout import Layout

_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(6)
_XI = (_GAUSS_X + 1.0) / 2.0
_WQ = _GAUSS_W / 2.0


def _hermite(xi: np.ndarray, length: np.ndarray):
    """Shape functions and x-derivatives at xi for elements of ``length``: (n_el, Q, 4)."""
    ell = length[:, None]
    x = xi[None, :]
    h = np.stack([1 - 3 * x**2 + 2 * x**3 + 0 * ell, ell * (x - 2 * x**2 + x**3),
                  3 * x**2 - 2 * x**3 + 0 * ell, ell * (-(x**2) + x**3)], axis=-1)
    d1 = np.stack([(-6 * x + 6 * x**2) / ell, 1 - 4 * x + 3 * x**2 + 0 * ell,
                   (6 * x - 6 * x**2) / ell, -2 * x + 3 * x**2 + 0 * ell], axis=-1)
    d2 = np.stack([(-6 + 12 * x) / ell**2, (-4 + 6 * x) / ell, (6 - 12 * x) / ell**2,
                   (-2 + 6 * x) / ell], axis=-1)
    return h, d1, d2


class _FiniteElementBeam:
    """One beam: Hermite elements, constraints, energy, and the length-constrained solve."""

    def __init__(self, supports_mm: np.ndarray, elements: int, ei: float, beta: float,
                 ea: float) -> None:
        self.supports = supports_mm
        x = np.concatenate([np.linspace(a, b, elements + 1)[:-1]
                            for a, b in zip(supports_mm[:-1], supports_mm[1:], strict=True)]
                           + [supports_mm[-1:]])
        self.x = x
        n = len(x)
        length = np.diff(x)
        self.h, self.d1, self.d2 = _hermite(_XI, length)
        self.w = _WQ[None, :] * length[:, None]
        self.dofs = np.stack([2 * np.arange(n - 1), 2 * np.arange(n - 1) + 1,
                              2 * np.arange(1, n), 2 * np.arange(1, n) + 1], axis=1)
        size = 2 * n
        stiffness = np.zeros((size, size))
        ke = (ei * np.einsum("eq,eqi,eqj->eij", self.w, self.d2, self.d2)
              + beta * np.einsum("eq,eqi,eqj->eij", self.w, self.h, self.h))
        np.add.at(stiffness, (self.dofs[:, :, None], self.dofs[:, None, :]), ke)
        self.stiffness = stiffness
        pixel_nodes = [int(np.argmin(np.abs(x - s))) for s in supports_mm[1:-1]]
        self.pixel_dofs = np.array([2 * i for i in pixel_nodes], dtype=int)
        fixed = np.concatenate([[0, 1, size - 2, size - 1], self.pixel_dofs])
        self.fixed = fixed
        self.free = np.setdiff1d(np.arange(size), fixed)
        self.ea = ea
        self.g0 = self._geometric(np.zeros(size))

    def _slopes(self, y: np.ndarray) -> np.ndarray:
        return np.einsum("eqi,ei->eq", self.d1, y[self.dofs])

    def arc_length(self, y: np.ndarray) -> float:
        return float(np.sum(self.w * np.sqrt(1.0 + self._slopes(y) ** 2)))

    def _geometric(self, y: np.ndarray) -> np.ndarray:
        """Hessian of the arc length: sum w B'^T B' (1 + y'^2)^(-3/2)."""
        factor = self.w * (1.0 + self._slopes(y) ** 2) ** -1.5
        ge = np.einsum("eq,eqi,eqj->eij", factor, self.d1, self.d1)
        out = np.zeros_like(self.stiffness)
        np.add.at(out, (self.dofs[:, :, None], self.dofs[:, None, :]), ge)
        return out

    def _gradient(self, y: np.ndarray) -> np.ndarray:
        slope = self._slopes(y)
        ge = np.einsum("eq,eqi->ei", self.w * slope / np.sqrt(1.0 + slope**2), self.d1)
        out = np.zeros(len(y))
        np.add.at(out, self.dofs, ge)
        return out

    def _banded(self, matrix: np.ndarray) -> np.ndarray:
        sub = matrix[np.ix_(self.free, self.free)]
        bands = 4
        out = np.zeros((bands, len(sub)))
        for k in range(bands):
            out[bands - 1 - k, k:] = np.diagonal(sub, k)
        return out

    def positive_definite(self, n_load: float) -> bool:
        try:
            cholesky_banded(self._banded(self.stiffness - n_load * self.g0))
        except LinAlgError:
            return False
        return True

    def critical_load(self, upper: float) -> float:
        """First N at which K - N G_0 is no longer positive definite (bisection)."""
        lo, hi = 0.0, upper
        while self.positive_definite(hi):
            hi *= 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.positive_definite(mid) else (lo, mid)
        return lo

    def equilibrium(self, heights: np.ndarray, n_load: float, start: np.ndarray) -> np.ndarray:
        """Newton solve of K y - N grad g(y) = 0 with the constraints."""
        y = start.copy()
        y[self.fixed] = 0.0
        y[self.pixel_dofs] = heights
        for _ in range(50):
            residual = self.stiffness @ y - n_load * self._gradient(y)
            tangent = self.stiffness - n_load * self._geometric(y)
            try:
                factor = cholesky_banded(self._banded(tangent))
            except LinAlgError as exc:
                raise CollapseError(f"reference: tangent stiffness lost at N = {n_load:.4g} N"
                                    ) from exc
            step = cho_solve_banded((factor, False), residual[self.free])
            y[self.free] -= step
            if np.max(np.abs(step)) < 1e-9 * (1.0 + np.max(np.abs(y))):  # rounding ~1e-11
                return y
        raise DisplayModelError(f"reference: Newton did not converge at N = {n_load:.4g} N")


#: The reference's fabric mesh (subdivisions of a pitch), four times the runtime models' 8, so
#: that their fabric discretisation is part of the error measured against it. Measured on a
#: 41 x 41 crs2d surface (z_f = 4 mm): max change 0.017 mm from 8 to 16, 0.0038 from 16 to 32,
#: 0.0006 from 32 to 64 subdivisions; the build takes 0.3 s, a surface the same as with 8.
REFERENCE_FABRIC_SUBDIVISIONS = 32


@register
class ReferenceModel(NetworkModel):
    """Finely discretised length-constrained energy minimisation per beam (module docstring)."""

    name = "reference"
    description = "high-fidelity FE energy minimisation with the exact arc-length constraint"

    def __init__(self, layout: Layout, elements: int = 32, foundation: bool = False,
                 critical_margin: float = 0.98, check_yield_curvature: bool = True,
                 fabric_subdivisions: int = REFERENCE_FABRIC_SUBDIVISIONS, **options) -> None:
        super().__init__(layout, fabric_subdivisions=fabric_subdivisions, **options)
        section = layout.beam_section
        self.ei = section.bending_stiffness
        self.beta = layout.foundation_stiffness if foundation else 0.0
        self.delta = no_collapse_number(self.ei, self.beta, layout.pitch_mm)
        self.margin = critical_margin
        self.check_yield_curvature = check_yield_curvature
        ea = section.youngs_modulus_mpa * section.area_mm2
        self.beams = []
        self.critical = []
        for beam in layout.beams:
            supports = beam_support_positions(layout, beam)
            fe = _FiniteElementBeam(supports, elements, self.ei, self.beta, ea)
            longest = float(np.max(np.diff(supports)))
            upper = (self.ei * (2 * math.pi / longest) ** 2
                     + 3 * self.beta * longest**2 / (4 * math.pi**2))
            self.beams.append(fe)
            self.critical.append(fe.critical_load(upper))

    def beam_profiles(self, setpoints_mm: np.ndarray) -> BeamProfiles:
        setpoints = check_setpoints(self.layout, setpoints_mm, self.name)
        target = commanded_lengths(self.layout, setpoints)
        shapes, loads, lengths = [], [], []
        for bi, (beam, fe) in enumerate(zip(self.layout.beams, self.beams, strict=True)):
            heights = setpoints[list(beam.pixels)]
            y, n_load = self._solve_beam(bi, fe, heights, target[bi])
            dydx = y[1::2]
            shapes.append(CubicHermiteSpline(fe.x, y[0::2], dydx))
            loads.append(n_load)
            lengths.append(fe.arc_length(y))
            if self.check_yield_curvature:
                curvature = np.abs(np.einsum("eqi,ei->eq", fe.d2, y[fe.dofs]))
                check_yield(self.name, bi, float(curvature.max()), self.layout)

        def evaluate(beam: np.ndarray, s: np.ndarray) -> np.ndarray:
            out = np.empty(s.shape)
            for b in np.unique(beam):
                mask = beam == b
                out[mask] = shapes[b](s[mask])
            return out

        return BeamProfiles(spans_mm=self.spans, evaluate=evaluate,
                            axial_load_n=np.array(loads), critical_load_n=np.array(self.critical),
                            commanded_length_mm=target, length_mm=np.array(lengths))

    def _solve_beam(self, bi: int, fe: _FiniteElementBeam, heights: np.ndarray,
                    target: float) -> tuple[np.ndarray, float]:
        state = {"y": np.zeros(len(fe.x) * 2)}

        def excess(n_load: float) -> float:
            state["y"] = fe.equilibrium(heights, n_load, state["y"])
            return fe.arc_length(state["y"]) - target * (1.0 - n_load / fe.ea)

        if excess(0.0) >= -1e-9 * fe.supports[-1]:
            return state["y"], 0.0  # tension case: the N = 0 shape (module docstring)
        if self.delta < 1.0:
            raise CollapseError(
                f"reference: beam {bi}: Delta = {self.delta:.3g} < 1 (Eq. 4): the compressed "
                f"beam collapses into the skin; use a stiffer beam, a softer skin or a smaller "
                f"pitch")
        n_max = self.margin * self.critical[bi]
        if excess(n_max) < 0.0:
            raise CollapseError(
                f"reference: beam {bi}: commanded length {target:.4f} mm needs N >= "
                f"{self.margin:g} N_cr = {n_max:.4g} N: the beam collapses; reduce the "
                f"boundary feed or the stimulus height")
        n_load = brentq(excess, 0.0, n_max, xtol=1e-14, rtol=1e-12)
        excess(n_load)
        return state["y"], n_load
