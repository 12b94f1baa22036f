"""Lattice geometry for the quality criteria: periodic patches of pixels and one lattice cell.

The paper's expectations (Wang, Meng & Chen 2025, Eqs. 1, 2, 5, 6) run over peak positions
uniform over the display. On an infinite lattice every quantity is periodic in the peak
position, so the expectation over the display equals the expectation over one lattice cell: the
Voronoi cell of a pixel (a segment of length d, a square of side d, a hexagon of inradius d/2).
A finite patch of pixels large enough that the bump's support never leaves it stands in for the
infinite lattice.

Lattice names: ``"1d"`` (a line of pixels), ``"square"`` and ``"hex"`` (pitch d = distance
between nearest neighbours).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Literal

import numpy as np

from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import Actuator, Beam, Calibration, Controller, Layout, load_layout

LatticeName = Literal["1d", "square", "hex"]
LATTICES: tuple[LatticeName, ...] = ("1d", "square", "hex")

#: Layout.lattice for each lattice name.
LAYOUT_LATTICE = {"1d": "line", "square": "square", "hex": "hex"}

_SQRT3 = math.sqrt(3.0)


def lattice_of(layout: Layout) -> LatticeName:
    """The lattice name of a layout (``"line"`` -> ``"1d"``)."""
    for name, kind in LAYOUT_LATTICE.items():
        if layout.lattice == kind:
            return name
    raise DisplayModelError(f"{layout.source}: lattice {layout.lattice!r} has no quality rule; "
                            f"known: line, square, hex")


def cell_vertices(lattice: LatticeName, pitch: float) -> np.ndarray:
    """Vertices (counter-clockwise) of the Voronoi cell of the pixel at the origin."""
    if lattice == "1d":
        return np.array([[-0.5 * pitch, 0.0], [0.5 * pitch, 0.0]])
    if lattice == "square":
        h = 0.5 * pitch
        return np.array([[h, -h], [h, h], [-h, h], [-h, -h]])
    if lattice == "hex":
        angles = np.deg2rad(-30.0 + 60.0 * np.arange(6))  # neighbours at 0, 60, ... degrees
        return (pitch / _SQRT3) * np.column_stack([np.cos(angles), np.sin(angles)])
    raise DisplayModelError(f"unknown lattice {lattice!r}; known: {', '.join(LATTICES)}")


def fundamental_triangle(lattice: LatticeName, pitch: float) -> np.ndarray:
    """The (1/8 square, 1/12 hexagonal) triangle of the cell that its symmetries tile it with:
    centre, the midpoint of an edge, the next vertex."""
    if lattice == "square":
        return np.array([[0.0, 0.0], [0.5 * pitch, 0.0], [0.5 * pitch, 0.5 * pitch]])
    if lattice == "hex":
        return np.array([[0.0, 0.0], [0.5 * pitch, 0.0], [0.5 * pitch, 0.5 * pitch / _SQRT3]])
    raise DisplayModelError(f"no fundamental triangle for lattice {lattice!r}")


def triangle_rule(triangles: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre product rule on triangles collapsed at their first vertex (Duffy map).

    X = a + s ((b - a) + t (c - b)), s, t in [0, 1], dA = s |det(b - a, c - b)| ds dt; the
    collapse at the cell centre makes cone-like integrands such as |X - a| smooth in (s, t).
    Returns points (n, 2) and weights summing to the triangles' total area.
    """
    x, w = np.polynomial.legendre.leggauss(order)
    u, wu = 0.5 * (x + 1.0), 0.5 * w
    s, t = np.meshgrid(u, u, indexing="ij")
    ws = np.outer(wu, wu) * s
    points, weights = [], []
    for a, b, c in triangles:
        e1, e2 = b - a, c - b
        area2 = abs(e1[0] * e2[1] - e1[1] * e2[0])
        p = a + s[..., None] * (e1 + t[..., None] * e2)
        points.append(p.reshape(-1, 2))
        weights.append((ws * area2).ravel())
    return np.concatenate(points), np.concatenate(weights)


def panel_edges(pitch: float, symmetric: bool, breaks: np.ndarray | None = None) -> np.ndarray:
    """1D: the panel ends of the cell [-d/2, d/2] (or [0, d/2] when ``symmetric``), cut at the
    pixel, at its ends and at the ``breaks`` inside it."""
    lo = 0.0 if symmetric else -0.5 * pitch
    cuts = [lo, 0.0, 0.5 * pitch]
    if breaks is not None:
        cuts += [b for b in breaks if lo < b < 0.5 * pitch]
    return np.unique(np.round(cuts, 12))


def cell_rule(lattice: LatticeName, pitch: float, order: int, symmetric: bool,
              breaks: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Peak positions X (n, 2) relative to a pixel, and weights summing to 1: a rule for the
    expectation over one lattice cell.

    1D: Gauss-Legendre with ``order`` nodes on each panel of [-d/2, 0], [0, d/2] (only
    [0, d/2] when ``symmetric``), the panels cut further at ``breaks``. 2D: the Voronoi cell cut
    into triangles at its centre (or, when ``symmetric``, its fundamental triangle alone, valid
    for models and layouts with the lattice's point symmetry), each by :func:`triangle_rule`.
    """
    if lattice == "1d":
        edges = panel_edges(pitch, symmetric, breaks)
        x, w = np.polynomial.legendre.leggauss(order)
        mids, halves = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
        pts = (mids[:, None] + halves[:, None] * x).ravel()
        wts = (halves[:, None] * w).ravel()
        return np.column_stack([pts, np.zeros_like(pts)]), wts / wts.sum()
    if symmetric:
        triangles = fundamental_triangle(lattice, pitch)[None]
    else:
        v = cell_vertices(lattice, pitch)
        triangles = np.stack([np.stack([np.zeros(2), v[k], v[(k + 1) % len(v)]])
                              for k in range(len(v))])
    points, weights = triangle_rule(triangles, order)
    return points, weights / weights.sum()


def periodic_layout(lattice: LatticeName, pitch: float, reach_mm: float,
                    template: Layout | None = None) -> Layout:
    """A patch of the lattice holding every pixel within ``reach_mm`` (+2 pitches) of the origin.

    Beams run along every lattice line of the patch (1D: one beam; square: rows and columns;
    hexagonal: the lines of the three directions) with the template device's margins, beam
    section, servos and foundation; pixel 0 is at the origin. The patch stands in for an infinite
    lattice: it is a model, not a device (one virtual controller drives every actuator).
    """
    template = template or load_layout("crs1d" if lattice == "1d" else "crs2d")
    rings = int(math.ceil(reach_mm / pitch)) + 2
    if lattice == "1d":
        coords = [(0,)] + [(i,) for k in range(1, rings + 1) for i in (k, -k)]
        xy = np.array([[c[0] * pitch, 0.0] for c in coords])
        lines = [sorted(range(len(coords)), key=lambda i: coords[i][0])]
    elif lattice == "square":
        coords = sorted(((i, j) for i in range(-rings, rings + 1) for j in range(-rings, rings + 1)
                         if math.hypot(i, j) <= rings), key=lambda c: (c != (0, 0), c))
        xy = np.array(coords, dtype=float) * pitch
        lines = _lines(coords, [(1, 0), (0, 1)])
    elif lattice == "hex":
        rings = int(math.ceil(reach_mm / (pitch * _SQRT3 / 2))) + 2
        coords = sorted(((q, r) for q in range(-rings, rings + 1) for r in range(-rings, rings + 1)
                         if max(abs(q), abs(r), abs(q + r)) <= rings),
                        key=lambda c: (c != (0, 0), c))
        c = np.array(coords, dtype=float)
        xy = np.column_stack([pitch * (c[:, 0] + c[:, 1] / 2), pitch * c[:, 1] * _SQRT3 / 2])
        lines = _lines(coords, [(1, 0), (0, 1), (-1, 1)])
    else:
        raise DisplayModelError(f"unknown lattice {lattice!r}; known: {', '.join(LATTICES)}")

    default = template.actuators[0].calibration
    controller = Controller("Q", 1, 2 * len(coords) + 2 * len(lines), 0)

    def actuator(index: int, kind: str, label: str, travel: float) -> Actuator:
        return Actuator(index, kind, label, "Q", index + 1,
                        Calibration(default.zero_us, default.full_us, travel))

    actuators = [actuator(i, "pixel", f"pixel {i}", template.travel_mm)
                 for i in range(len(coords))]
    beams = []
    margin = template.end_margin_pitch * pitch
    for b, members in enumerate(lines):
        first, last = xy[members[0]], xy[members[-1]]
        unit = (last - first) / np.linalg.norm(last - first)
        s, e = len(actuators), len(actuators) + 1
        actuators += [actuator(s, "boundary", f"beam {b} start", template.boundary_travel_mm),
                      actuator(e, "boundary", f"beam {b} end", template.boundary_travel_mm)]
        start, end = first - unit * margin, last + unit * margin
        beams.append(Beam(b, tuple(members), (float(start[0]), float(start[1])),
                          (float(end[0]), float(end[1])), s, e))
    return replace(
        template, name=f"periodic-{lattice}", description=f"{lattice} lattice patch, {rings} rings",
        source=f"<periodic {lattice} patch>", lattice=LAYOUT_LATTICE[lattice], pitch_mm=pitch,
        lattice_coords=tuple(coords), pixel_xy=xy, beams=tuple(beams),
        actuators=tuple(actuators), controllers=(controller,),
    )


def _lines(coords: list[tuple[int, ...]], directions: list[tuple[int, int]]) -> list[list[int]]:
    """Every maximal run of >= 2 consecutive pixels along each lattice direction."""
    index = {c: i for i, c in enumerate(coords)}
    lines = []
    for dq, dr in directions:
        for c in coords:
            if (c[0] - dq, c[1] - dr) in index:
                continue  # not the first pixel of its run
            run, cur = [], c
            while cur in index:
                run.append(index[cur])
                cur = (cur[0] + dq, cur[1] + dr)
            if len(run) >= 2:
                lines.append(run)
    return lines
