"""The paper's display-quality criteria: peak position distortion D_P and shape distortion D_S.

For a bump of diameter (wavelength) l centred at X (Wang, Meng & Chen 2025; the ideal shape, its
Supplementary Equation 4 and Eq. 7, is the raised cosine phi = [1 + cos(2 pi |x - X| / l)] / 2
on |x - X| <= l/2)::

    D_P = E( |x_r - X| / l )                                             (Eqs. 1, 5)
    D_S = E( sqrt( int_S (phi - psi)^2 / int_S phi^2 ) ),  S = {|x - X| <= l/2}   (Eqs. 2, 6)

psi is the displayed surface (a display model fed the setpoints the renderer gives for the
bump), x_r its highest point. X is uniform over the display; on the (infinite) lattice every
term is periodic in X, so E is taken over one lattice cell (:mod:`crs_study.quality.lattices`).

Numerics, and their error
-------------------------
* E over X: Gauss-Legendre on the cell (1D: panels cut where the support's ends cross a pixel
  or a mid-point, and, for models without a closed-form peak, where the peak's lead x_r - X
  changes sign, found by brentq, since |x_r - X| has a kink there; 2D: the Voronoi cell cut
  into triangles at its centre, Duffy-mapped product rule).
* int_S: 1D Gauss-Legendre on panels cut at the pixels and mid-points (exact breaks for the
  nearest and linear models); 2D polar product rule about X (Gauss-Legendre in rho, the
  periodic trapezoid rule in theta), about ``resolution`` nodes per pitch each way.
* x_r: the model's own ``peak_xy(setpoints)`` where it has one (``nearest``, ``linear``: the
  highest pixel); otherwise the maximum on a grid of pitch/8 over the support widened by half
  a pitch, then on grids of pitch/80 (and, in 2D, pitch/800) around it, refined by the vertex
  of a least-squares quadratic (1D: parabola) through the neighbouring points. Two (2D: three)
  surface calls per position: beam models solve their beams once per call.

Measured change from the defaults (order 4, resolution 12) to order 8, resolution 24, at
d/l = 0.1, 0.2, 0.3 and 1/3; tests/test_quality.py checks every row (hex: the beam) at one or
two of these d/l, within the bound (D_P of 1D pixel-only within 1e-12):

==========================  =========  =========
models                       D_P        D_S
==========================  =========  =========
1D nearest, linear           < 1e-15    < 2e-6
1D spline, beam              < 1.5e-3   < 5e-4
2D nearest, linear           < 1e-6     < 5e-3
hex spline, beam             < 3e-2     < 1e-3
==========================  =========  =========

The 2D D_P of beam networks is the loose one: where the top of the surface passes from one
beam to another x_r jumps, the integrand is discontinuous, and a product rule converges only
as 1/order there (order 12 differs from order 8 as much as 8 from 4). The jumps belong to the
model, not the quadrature; a 3 % error is far below the differences the criteria are read for
(hex beam 0.033 against pixel-only 0.117 at d/l = 1/3). ``estimate_error=True`` records the
change at half the nodes for any model on :attr:`Distortion.error`.

Range: d/l must lie in [:data:`MIN_D_OVER_L`, the lattice's covering limit]: below, the bump
spans so many pixels that the 2D integrals grow as (l/d)^2 (use the paper's linear laws
there, :data:`THEORY`); above, a bump can sit wholly between pixels, the display is flat and
x_r has no meaning. Both are :class:`~crs_study.errors.DisplayModelError`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.optimize import brentq

from crs_study.display import get_model
from crs_study.display.base import DisplayModel
from crs_study.errors import DisplayModelError, RenderError
from crs_study.geometry.layout import Layout, load_layout
from crs_study.quality.lattices import (
    LATTICES,
    LatticeName,
    cell_rule,
    cell_vertices,
    lattice_of,
    panel_edges,
    periodic_layout,
)
from crs_study.rendering.render import Renderer
from crs_study.stimuli.targets import Bump

#: Smallest d/l computed (the bump then spans 50 pitches).
MIN_D_OVER_L = 0.02
#: Largest d/l per lattice: beyond, the support (radius l/2) can miss every pixel, since a
#: point can be the cell circumradius from its nearest pixel (d/2, d/sqrt 2, d/sqrt 3).
MAX_D_OVER_L = {"1d": 1.0, "square": 1.0 / math.sqrt(2.0), "hex": math.sqrt(3.0) / 2.0}

#: Default bump height (mm): well inside the 9 mm travel, slopes small enough that the
#: compressed beam stays far from its yield curvature for l >= 30 mm.
DEFAULT_HEIGHT_MM = 5.0

#: The paper's theory lines (docs/physics.md): (lattice, model) -> (quantity, coefficient, power).
#: D = coefficient * (d/l)^power. Pixel-only D_P is exact theory; the D_S lines are fits.
THEORY = {
    ("1d", "nearest"): {"D_P": (0.25, 1), "D_S": (0.994, 1)},
    ("square", "nearest"): {"D_P": (0.3826, 1), "D_S": (1.412, 1)},
    ("hex", "nearest"): {"D_P": (0.3510, 1), "D_S": (1.318, 1)},
    ("1d", "linear"): {"D_P": (0.25, 1), "D_S": (1.545, 2)},
}

#: Models whose surface, fed symmetric setpoints, has the lattice's point symmetry on any
#: patch: their expectation may use the fundamental part of the cell (1D: half the cell).
#: The Delaunay triangulation of a square lattice is not unique, so ``linear`` is symmetric
#: on the line and the hexagonal lattice only.
SYMMETRIC_MODELS = {"nearest": {"1d", "square", "hex"}, "linear": {"1d", "hex"}}

#: Beam networks have that symmetry on the periodic patch only (:func:`periodic_layout` lays a
#: beam on every lattice line, the renderer splits each feed evenly, the fabric is regular);
#: on a device it must be shown (tests/test_quality.py does so for the published crs2d).
PATCH_SYMMETRIC_MODELS = {"spline": {"1d", "hex"}, "beam": {"1d", "hex"},
                          "reference": {"1d", "hex"}}


def symmetric_by_default(model: str, lattice: str, periodic: bool = True) -> bool:
    """Whether the expectation may use the fundamental part of the cell (see above)."""
    if lattice in SYMMETRIC_MODELS.get(model, set()):
        return True
    return periodic and lattice in PATCH_SYMMETRIC_MODELS.get(model, set())


@dataclass(frozen=True)
class Distortion:
    """D_P and D_S of one display model on one lattice at one d/l (dimensionless)."""

    layout: str  # "1d" | "square" | "hex"
    model: str
    d_over_l: float
    D_P: float
    D_S: float
    positions: int  # peak positions X the expectation used
    error: dict = field(default_factory=dict)  # {"D_P": .., "D_S": ..}: change at half the nodes
    device: str = ""  # layout the surfaces were computed on

    def row(self) -> dict:
        """The JSON row of ``crs-study quality --json``."""
        return {"layout": self.layout, "model": self.model, "d_over_l": self.d_over_l,
                "D_P": self.D_P, "D_S": self.D_S}

    def to_dict(self) -> dict:
        return asdict(self)


def theory(lattice: str, model: str, quantity: str, d_over_l: float | np.ndarray) -> float | None:
    """The paper's line for (lattice, model, quantity) at d/l, or None when it gives none."""
    line = THEORY.get((lattice, model), {}).get(quantity)
    if line is None:
        return None
    coefficient, power = line
    return coefficient * np.asarray(d_over_l) ** power


def check_d_over_l(lattice: LatticeName, d_over_l: float) -> None:
    if lattice not in LATTICES:
        raise DisplayModelError(f"unknown lattice {lattice!r}; known: {', '.join(LATTICES)}")
    upper = MAX_D_OVER_L[lattice]
    if not (np.isfinite(d_over_l) and MIN_D_OVER_L <= d_over_l <= upper):
        raise DisplayModelError(
            f"d/l = {d_over_l!r} is outside [{MIN_D_OVER_L}, {upper:.4f}] for the {lattice} "
            f"lattice: below, the bump spans too many pixels to integrate (use the paper's "
            f"linear laws); above, a bump can fall between pixels and show nothing"
        )


class _Evaluator:
    """Per-(model, layout, l) machinery: renderer, quadrature templates, peak search."""

    def __init__(self, model: DisplayModel, layout: Layout, lattice: LatticeName, l: float,
                 height: float, condition: str | None, resolution: int) -> None:
        self.model, self.layout, self.lattice = model, layout, lattice
        self.l, self.height, self.d = l, height, layout.pitch_mm
        # None: surfaces come from given setpoints alone (:meth:`shown`), nothing is rendered
        self.renderer = (None if condition is None else
                         Renderer(layout, condition, policy="error", cap_feed=False))
        self.resolution = resolution
        self.peak_xy = getattr(model, "peak_xy", None)
        if lattice != "1d":
            radius = 0.5 * l
            n_rho = max(16, math.ceil(resolution * radius / self.d))
            n_theta = max(32, math.ceil(2 * math.pi * resolution * radius / self.d))
            x, w = np.polynomial.legendre.leggauss(n_rho)
            rho, w_rho = 0.5 * radius * (x + 1.0), 0.5 * radius * w
            theta = 2 * math.pi * np.arange(n_theta) / n_theta
            self.offsets = (rho[:, None, None] * np.stack([np.cos(theta), np.sin(theta)], -1)
                            ).reshape(-1, 2)
            self.weights = np.repeat(w_rho * rho * 2 * math.pi / n_theta, n_theta)
        self.coarse = max(self.d / 8.0, 1e-9)

    def _segment_rule(self, centre: float) -> tuple[np.ndarray, np.ndarray]:
        """1D: nodes and weights on [X - l/2, X + l/2] cut at pixels and mid-points."""
        lo, hi = centre - 0.5 * self.l, centre + 0.5 * self.l
        half_pitch = 0.5 * self.d
        k = np.arange(math.ceil(lo / half_pitch), math.floor(hi / half_pitch) + 1)
        edges = np.unique(np.concatenate([[lo, hi], k * half_pitch]))
        x, w = np.polynomial.legendre.leggauss(max(4, self.resolution // 2))
        mids, halves = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
        nodes = (mids[:, None] + halves[:, None] * x).ravel()
        return np.column_stack([nodes, np.zeros_like(nodes)]), (halves[:, None] * w).ravel()

    def support(self, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nodes and weights of int_S over the support |x - X| <= l/2 of a bump at ``centre``."""
        if self.lattice == "1d":
            return self._segment_rule(float(centre[0]))
        return centre + self.offsets, self.weights

    def __call__(self, origin: np.ndarray, x: np.ndarray) -> tuple[float, float]:
        """(|x_r - X| / l, shape distortion) for a bump at X = origin + x."""
        centre = origin + x
        bump = Bump((float(centre[0]), float(centre[1])), self.l, self.height)
        try:
            setpoints = self.renderer.render(bump).setpoints
        except RenderError as exc:
            raise DisplayModelError(f"quality at d/l = {self.d / self.l:.4g}: {exc}") from None
        return self.shown(bump, setpoints)

    def shown(self, bump: Bump, setpoints: np.ndarray) -> tuple[float, float]:
        """(|x_r - X| / l, shape distortion) of the surface ``setpoints`` give for ``bump``."""
        centre = np.asarray(bump.centre_mm, dtype=float)
        points, weights = self.support(centre)
        grid = None if self.peak_xy is not None else self._coarse_grid(centre)
        evaluate = points if grid is None else np.concatenate([points, grid])
        values = self.model.surface(setpoints, evaluate)
        psi = values[: len(points)]
        phi = bump.height(points)
        shape = math.sqrt(np.dot(weights, (phi - psi) ** 2) / np.dot(weights, phi**2))
        if self.peak_xy is not None:
            peak = np.asarray(self.peak_xy(setpoints), dtype=float)
            top = float(values.max()) if len(values) else 0.0
        else:
            peak, top = self._search_peak(setpoints, grid, values[len(points):])
        if not top > 1e-9 * self.height:
            raise DisplayModelError(
                f"{self.model.name}: the display is flat for a bump at {tuple(centre)!r} "
                f"(d/l = {self.d / self.l:.4g}): no peak; use a smaller d/l"
            )
        if self.lattice == "1d":
            return abs(peak[0] - centre[0]) / self.l, shape
        return math.hypot(peak[0] - centre[0], peak[1] - centre[1]) / self.l, shape

    def peak_shift(self, origin: np.ndarray, x: float) -> float:
        """1D: the signed (x_r - X) / l for a bump at X = origin + x (no shape integral)."""
        centre = origin + np.array([x, 0.0])
        bump = Bump((float(centre[0]), float(centre[1])), self.l, self.height)
        try:
            setpoints = self.renderer.render(bump).setpoints
        except RenderError as exc:
            raise DisplayModelError(f"quality at d/l = {self.d / self.l:.4g}: {exc}") from None
        grid = self._coarse_grid(centre)
        peak, _ = self._search_peak(setpoints, grid, self.model.surface(setpoints, grid))
        return float(peak[0] - centre[0]) / self.l

    def shift_roots(self, origin: np.ndarray, edges: np.ndarray, samples: int = 6) -> list[float]:
        """1D: where the peak shift x_r - X changes sign inside a panel of ``edges``.

        |x_r - X| has a kink there (a beam's peak leads the bump near a pixel and lags it near
        a mid-point), which costs Gauss-Legendre its order: without the cut the beam's D_P at
        d/l = 1/3 wandered by 7 % between orders 4 and 32. Each panel is sampled at
        ``samples`` interior points and each sign change bracketed by brentq to 1e-9 pitch.
        """
        roots = []
        for lo, hi in itertools.pairwise(edges):
            xs = lo + (hi - lo) * (np.arange(samples) + 0.5) / samples
            shifts = [self.peak_shift(origin, x) for x in xs]
            for (a, fa), (b, fb) in itertools.pairwise(zip(xs, shifts, strict=True)):
                if fa == 0.0:
                    roots.append(float(a))
                elif fa * fb < 0.0:
                    roots.append(brentq(lambda x: self.peak_shift(origin, x), a, b,
                                        xtol=1e-9 * self.d))
        return roots

    def _coarse_grid(self, centre: np.ndarray) -> np.ndarray:
        reach = 0.5 * self.l + 0.5 * self.d
        n = math.ceil(reach / self.coarse)
        ticks = np.arange(-n, n + 1) * self.coarse
        if self.lattice == "1d":
            return np.column_stack([centre[0] + ticks, np.zeros_like(ticks)])
        gx, gy = np.meshgrid(ticks, ticks, indexing="ij")
        keep = gx**2 + gy**2 <= reach**2
        return centre + np.column_stack([gx[keep], gy[keep]])

    def _search_peak(self, setpoints: np.ndarray, grid: np.ndarray, values: np.ndarray
                     ) -> tuple[np.ndarray, float]:
        """Grid maximum, one zoomed grid (spacing / 10) around it, then a quadratic fit."""
        top = float(values.max())
        tied = values >= top - 1e-12 * max(abs(top), 1.0)
        if np.count_nonzero(tied) > 1:  # a plateau: its centroid (as for the pixel-only cells)
            return grid[tied].mean(axis=0), top
        best, spacing = grid[int(np.argmax(values))], self.coarse / 10.0
        if self.lattice != "1d":  # a first zoom; ridges (peaks on a beam line) defeat the fit
            ticks = np.arange(-10, 11) * spacing
            gx, gy = np.meshgrid(ticks, ticks, indexing="ij")
            local = best + np.column_stack([gx.ravel(), gy.ravel()])
            z = self.model.surface(setpoints, local)
            k = int(np.argmax(z))
            if z[k] >= top:
                best, top = local[k], float(z[k])
            spacing /= 10.0
        ticks = np.arange(-10, 11) * spacing
        if self.lattice == "1d":
            local = np.column_stack([best[0] + ticks, np.zeros_like(ticks)])
            z = self.model.surface(setpoints, local)
            k = int(np.argmax(z))
            peak = local[k].copy()
            if 0 < k < len(z) - 1:  # vertex of the parabola through the three best points
                curvature = z[k - 1] - 2 * z[k] + z[k + 1]
                if curvature < 0:
                    peak[0] += 0.5 * spacing * (z[k - 1] - z[k + 1]) / curvature
            return peak, max(top, float(z[k]))
        gx, gy = np.meshgrid(ticks, ticks, indexing="ij")
        local = best + np.column_stack([gx.ravel(), gy.ravel()])
        z = self.model.surface(setpoints, local).reshape(gx.shape)
        i, j = np.unravel_index(int(np.argmax(z)), z.shape)
        peak = local.reshape(*gx.shape, 2)[i, j].copy()
        if 2 <= i <= z.shape[0] - 3 and 2 <= j <= z.shape[1] - 3:
            # least-squares quadratic on the 5 x 5 neighbourhood; its vertex if it is a maximum
            u, v = np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="ij")
            u, v = u.ravel().astype(float), v.ravel().astype(float)
            basis = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
            c = np.linalg.lstsq(basis, z[i - 2:i + 3, j - 2:j + 3].ravel(), rcond=None)[0]
            hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
            if np.all(np.linalg.eigvalsh(hessian) < 0):
                shift = np.linalg.solve(hessian, -c[1:3])
                if np.all(np.abs(shift) <= 1.0):
                    peak += spacing * shift
        return peak, max(top, float(z[i, j]))


def distortion(model: str | DisplayModel, lattice: LatticeName, d_over_l: float, *,
               layout: Layout | None = None, template: Layout | None = None,
               height_mm: float = DEFAULT_HEIGHT_MM,
               condition: str = "crs", order: int = 4, resolution: int = 12,
               symmetric: bool | None = None, estimate_error: bool = False) -> Distortion:
    """D_P and D_S (Eqs. 1, 2, 5, 6) of a display model on a lattice at one d/l.

    Parameters
    ----------
    model : a registered model name (``"nearest"``, ``"linear"``, ``"beam"``, ...) or a built
        model, which is computed on the layout it was built for.
    lattice : ``"1d"``, ``"square"`` or ``"hex"``.
    layout : the device to compute on, e.g. the published ``crs2d``; the bump's peak runs over
        the cell of the pixel nearest the pixels' centroid. Default: a periodic patch
        (:func:`~crs_study.quality.lattices.periodic_layout`) of ``template``.
    template : the device whose pitch, beam section, margins and skin the periodic patch takes
        (default: the shipped ``crs1d`` or ``crs2d``).
    height_mm : z_f of the bump; the criteria are scale-free for linear models.
    condition : how setpoints are rendered (``"crs"`` feeds the beams; pixel-only models
        ignore the feed).
    order, resolution : Gauss order per cell panel; quadrature nodes per pitch for int_S.
    symmetric : use the fundamental part of the cell; default :func:`symmetric_by_default`.
    estimate_error : also compute with half the order and resolution and record the change.
    """
    check_d_over_l(lattice, d_over_l)
    name = model if isinstance(model, str) else model.name
    if layout is None and not isinstance(model, str):
        layout = model.layout  # a built model is computed on the layout it was built for
    periodic = layout is None
    if layout is None:
        template = template or load_layout("crs1d" if lattice == "1d" else "crs2d")
        pitch = template.pitch_mm
        cell_reach = float(np.max(np.hypot(*cell_vertices(lattice, pitch).T)))
        layout = periodic_layout(lattice, pitch, 0.5 * pitch / d_over_l + cell_reach, template)
    elif lattice_of(layout) != lattice:
        raise DisplayModelError(f"{layout.source}: a {layout.lattice!r} layout cannot give "
                                f"{lattice!r} distortions")
    display = get_model(model, layout) if isinstance(model, str) else model
    if symmetric is None:
        symmetric = symmetric_by_default(name, lattice, periodic=periodic)
    l = layout.pitch_mm / d_over_l
    centroid = layout.pixel_xy.mean(axis=0)
    origin = layout.pixel_xy[int(np.argmin(np.hypot(*(layout.pixel_xy - centroid).T)))]

    def expectation(order: int, resolution: int) -> tuple[float, float, int]:
        evaluator = _Evaluator(display, layout, lattice, l, height_mm, condition, resolution)
        breaks = None
        if lattice == "1d":  # where the support's ends cross a pixel or a mid-point
            half = 0.5 * layout.pitch_mm
            shift = (0.5 * l) % half
            breaks = np.array([shift, half - shift, shift - half, -shift])
            if evaluator.peak_xy is None:  # and where the peak's lead turns into a lag
                edges = panel_edges(layout.pitch_mm, symmetric, breaks)
                breaks = np.concatenate([breaks, evaluator.shift_roots(origin, edges)])
        xs, ws = cell_rule(lattice, layout.pitch_mm, order, symmetric, breaks)
        values = np.array([evaluator(origin, x) for x in xs])
        dp, ds = ws @ values
        return float(dp), float(ds), len(xs)

    dp, ds, n = expectation(order, resolution)
    error = {}
    if estimate_error:
        dp2, ds2, _ = expectation(max(2, order // 2), max(4, resolution // 2))
        error = {"D_P": abs(dp - dp2), "D_S": abs(ds - ds2)}
    return Distortion(lattice, name, float(d_over_l), dp, ds, n, error, layout.name)


def hull_distortion(model: str, layout: Layout, *, samples: int = 300, seed: int = 0,
                    height_mm: float = DEFAULT_HEIGHT_MM, d_over_l: float = 1 / 3,
                    condition: str = "crs") -> tuple[Distortion, int]:
    """D_P and D_S over bump centres uniform in the pixels' convex hull of a finite device.

    The paper's expectation (and :func:`distortion`) runs over one cell of an infinite lattice;
    on the 19-pixel device a third of the hull is edge cells, where a beam ends at its clamp.
    Plain Monte Carlo (seeded): the standard errors are on :attr:`Distortion.error`. Positions
    whose rendering is refused (a feed beyond the beam's longest stable shape) are left out and
    counted in the second return value. Measured on crs2d at d/l = 1/3 (300 positions, seed 7):
    beam D_P 0.041 +- 0.002, D_S 0.158 +- 0.005 (central cell 0.033, 0.093); nearest 0.117,
    0.472 (central cell 0.117, 0.451).
    """
    from scipy.spatial import Delaunay

    lattice = lattice_of(layout)
    check_d_over_l(lattice, d_over_l)
    hull = Delaunay(layout.pixel_xy) if lattice != "1d" else None
    lo, hi = layout.pixel_xy.min(axis=0), layout.pixel_xy.max(axis=0)
    rng = np.random.default_rng(seed)
    centres = []
    while len(centres) < samples:
        point = lo + (hi - lo) * rng.random(2)
        if hull is None or hull.find_simplex(point) >= 0:
            centres.append(point)
    evaluator = _Evaluator(get_model(model, layout), layout, lattice, layout.pitch_mm / d_over_l,
                           height_mm, condition, resolution=12)
    values, refused = [], 0
    for centre in centres:
        try:
            values.append(evaluator(np.zeros(2), centre))
        except DisplayModelError:
            refused += 1
    if not values:
        raise DisplayModelError(f"{model} on {layout.name}: every bump position was refused")
    v = np.array(values)
    se = v.std(axis=0, ddof=1) / math.sqrt(len(v)) if len(v) > 1 else np.full(2, np.nan)
    result = Distortion(lattice, model, float(d_over_l), float(v[:, 0].mean()),
                        float(v[:, 1].mean()), len(v), {"D_P": float(se[0]), "D_S": float(se[1])},
                        layout.name)
    return result, refused


def support_rule(layout: Layout, bump: Bump, resolution: int = 12
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n, 2) and weights of int_S over the support of ``bump`` on ``layout``: the rule
    :func:`distortion` integrates Eqs. 2 and 6 with (module docstring), for a measured surface
    to be integrated alike (:mod:`crs_study.quality.measured`)."""
    evaluator = _Evaluator(get_model("nearest", layout), layout, lattice_of(layout),
                           bump.diameter_mm, bump.height_mm, None, resolution)
    return evaluator.support(np.asarray(bump.centre_mm, dtype=float))


def shape_distortion(model: DisplayModel, bump: Bump, setpoints: np.ndarray, *,
                     resolution: int = 12) -> tuple[float, float]:
    """The two terms of the expectations of Eqs. 1, 2 (1D) or 5, 6 (2D) for one shape shown:
    (|x_r - X| / l, sqrt(int_S (phi - psi)^2 / int_S phi^2)), psi the surface ``model`` gives
    for ``setpoints`` (as a session sent them, feed cap included), phi the ``bump`` (Eq. 7)
    and x_r psi's peak, found as :func:`distortion` finds it."""
    evaluator = _Evaluator(model, model.layout, lattice_of(model.layout), bump.diameter_mm,
                           bump.height_mm, None, resolution)
    return evaluator.shown(bump, np.asarray(setpoints, dtype=float))
