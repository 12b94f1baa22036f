"""Measurement protocols: which target waveforms a surface measurement shows, and how they are
compared with the model.

The paper measured D_P and D_S on the device by digital image correlation (DIC): speckle on
the surface, the off-surface displacement measured while the display held a target waveform,
"the measured waveforms ... compared with the corresponding input waveforms to obtain the
distortions, which are then averaged" (Wang, Meng & Chen, "Continuity reinforcement skeleton
for pixel-based haptic display", Nature Communications: Fig. 2c-d for 1D, Fig. 4d-g for 2D).
A measurement protocol is a strict TOML file (unknown keys are errors) naming the device, the
conditions, the bump diameters l (so d/l = pitch / l) and how many bump centres X_i to show::

    name = "crs2d"
    device = "crs2d"                   # a shipped device or a path beside this file
    conditions = ["pixel-only", "crs"] # each a block, with its own reference capture
    diameters_mm = [90.0, 120.0]       # l; d/l = 1/3 and 1/4 at the 30 mm pitch
    height_mm = 5.0                    # z_f of Eq. 7
    shapes = 15                        # bump centres per condition and diameter
    region = "cell"                    # X_i over the central pixel's cell, or "hull"
    sampling = "random"                # X_i ~ U(region) (Eqs. 1, 5), or "grid" (midpoints)
    seed = 29
    [models]                           # the display model that predicts each condition
    pixel-only = "linear"
    crs = "beam"
    [timing]
    settle_s = 1.0                     # after a shape is sent, before its capture window
    hold_s = 2.0                       # the capture window
    [analysis]                         # every key optional; the defaults below
    registration = "rigid"             # or "similarity" (a scale too, applied to heights)
    max_fiducial_rms_mm = 0.5          # refuse a registration whose fiducials miss by more
    max_hole_fraction = 0.05           # of a bump's support without data (NaN, masked)
    strip_mm = 2.0                     # 1D: half-width of the strip along the beam
    confidence = 0.95                  # of the bootstrap intervals over shapes
    resamples = 2000
    tolerance_D_P = 0.01               # the model's band: measured - model within this
    tolerance_D_S = 0.02
    offset_limit_mm = 0.2              # a pixel's neutral offset beyond this is named
    gain_limit = 0.05                  # ... or its stroke's gain beyond 1 +- this

``sampling = "random"`` draws X_i uniformly over the region, as the expectations of Eqs. 1
and 5 require, so the bootstrap intervals over shapes are those of a simple random sample;
``"grid"`` places them on the midpoints of a regular grid over the region (about ``shapes``
of them in 2D), a quadrature of the same expectation for checks against exact values.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from crs_study._toml import Section, parse_toml, parse_toml_file
from crs_study._toml_lines import locate
from crs_study.display import MODELS
from crs_study.errors import ConfigError, ProtocolError
from crs_study.geometry.layout import BUILTIN_DEVICES, Layout, layout_from_dict, load_layout
from crs_study.paths import data_dir, is_name
from crs_study.quality.criteria import MAX_D_OVER_L, MIN_D_OVER_L
from crs_study.quality.lattices import cell_vertices, lattice_of
from crs_study.rendering.render import CONDITIONS

Region = Literal["cell", "hull"]
Sampling = Literal["random", "grid"]
Registration = Literal["rigid", "similarity"]

#: The shipped measurement protocols' folder (``crs1d``, ``crs2d`` by name).
SHIPPED_FOLDER = "measurements"

_TOP_KEYS = ("name", "description", "device", "conditions", "diameters_mm", "height_mm",
             "shapes", "region", "sampling", "seed", "models", "timing", "analysis")


@dataclass(frozen=True)
class Timing:
    """How long each shape is held: ``settle_s`` after it is sent (the servos travel 9 mm in
    72 ms), then the capture window of ``hold_s``."""

    settle_s: float = 1.0
    hold_s: float = 2.0


@dataclass(frozen=True)
class AnalysisSettings:
    """How captures are registered and compared (module docstring, ``[analysis]``)."""

    registration: Registration = "rigid"
    max_fiducial_rms_mm: float = 0.5
    max_hole_fraction: float = 0.05
    strip_mm: float | None = None  # None: half the beam's width (1D devices)
    confidence: float = 0.95
    resamples: int = 2000
    tolerance_D_P: float = 0.01
    tolerance_D_S: float = 0.02
    offset_limit_mm: float = 0.2
    gain_limit: float = 0.05


@dataclass(frozen=True)
class MeasurementProtocol:
    """A measurement protocol as read (:func:`load_measurement_protocol`)."""

    name: str
    description: str
    device: str
    conditions: tuple[str, ...]
    diameters_mm: tuple[float, ...]
    height_mm: float
    shapes: int
    region: Region
    sampling: Sampling
    seed: int
    models: dict[str, str]
    timing: Timing = Timing()
    analysis: AnalysisSettings = AnalysisSettings()
    text: str = field(default="", repr=False)
    sha256: str = ""
    path: str = ""

    def layout(self) -> Layout:
        """The device the protocol names (a shipped name, or a path beside the protocol)."""
        return load_layout(device_path(self.device, self.path))


@dataclass(frozen=True)
class PlannedCapture:
    """One capture of a measurement: a reference (the display neutral) or a shape."""

    index: int
    name: str  # "ref-crs", "shape-0007": the capture file's stem
    kind: Literal["reference", "shape"]
    condition: str
    diameter_mm: float  # l (nan for a reference)
    centre_mm: tuple[float, float]  # X_i (nan for a reference)
    height_mm: float  # z_f (0 for a reference)

    def to_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "kind": self.kind,
                "condition": self.condition, "diameter_mm": self.diameter_mm,
                "x_mm": self.centre_mm[0], "y_mm": self.centre_mm[1],
                "height_mm": self.height_mm}


def reference_name(condition: str) -> str:
    """The capture name of a condition's reference (``ref-pixel-only``)."""
    return f"ref-{condition}"


def device_path(device: str, protocol_path: str | os.PathLike[str]) -> str:
    """A protocol's device: a shipped name as is, a relative path beside the protocol."""
    if device in BUILTIN_DEVICES or Path(device).is_absolute() or not protocol_path:
        return device
    return str(Path(protocol_path).parent / device)


def resolve_measurement_protocol(name_or_path: str | os.PathLike[str]) -> Path:
    """A shipped measurement protocol's file by name (``crs2d``), else the path as given."""
    text = os.fspath(name_or_path)
    if is_name(text):
        shipped = sorted(p.stem for p in (data_dir() / SHIPPED_FOLDER).glob("*.toml"))
        if text not in shipped:
            raise ProtocolError(f"{text!r} is not a shipped measurement protocol (shipped: "
                                f"{', '.join(shipped)}); give the path of your own file")
        return data_dir() / SHIPPED_FOLDER / f"{text}.toml"
    return Path(text)


def load_measurement_protocol(source: str | os.PathLike[str]) -> MeasurementProtocol:
    """Read and check a measurement protocol; every problem is a one-line ProtocolError."""
    path = str(resolve_measurement_protocol(source))
    return parse_toml_file(path, "measurement protocol",
                           lambda data, where, text: _checked(data, where, text, None),
                           ProtocolError)


def measurement_protocol_from_text(text: str, source: str, *,
                                   device_text: str | None = None) -> MeasurementProtocol:
    """The protocol of TOML ``text`` read from ``source``. ``device_text``: the device file's
    text to check it against (a stored measurement's copy) instead of the file it names."""
    data = parse_toml(text, source, ProtocolError)
    try:
        return _checked(data, source, text, device_text)
    except ConfigError as exc:
        raise locate(exc, source, text) from None


def _checked(data: dict, source: str, text: str, device_text: str | None
             ) -> MeasurementProtocol:
    """The protocol of parsed ``data``, checked on its device (a problem of the device file
    is named as a problem of the protocol's ``device`` key)."""
    protocol = _from_dict(data, source, text)
    try:
        if device_text is None:
            layout = protocol.layout()
        else:
            layout = layout_from_dict(parse_toml(device_text, protocol.device, ProtocolError),
                                      source=protocol.device)
    except ConfigError as exc:
        raise ProtocolError(str(exc), source=source, key_path="device") from None
    _check_on_device(protocol, layout, Section(data, source, "", ProtocolError, text=text))
    return protocol


def _from_dict(data: dict, source: str, text: str) -> MeasurementProtocol:
    root = Section(data, source, error=ProtocolError, keys=_TOP_KEYS, text=text)
    name = root.string("name")
    description = root.string("description", "")
    device = root.string("device")
    conditions = tuple(_strings(root, "conditions", choices=sorted(CONDITIONS)))
    if not conditions or len(set(conditions)) != len(conditions):
        raise root.fail("conditions", f"expected one or more different conditions, got "
                                      f"{list(conditions)!r}")
    diameters = tuple(_numbers(root, "diameters_mm", minimum=1.0, maximum=10000.0))
    if not diameters or len(set(diameters)) != len(diameters):
        raise root.fail("diameters_mm", f"expected one or more different diameters, got "
                                        f"{list(diameters)!r}")
    height = root.number("height_mm", minimum=0.0, exclusive_minimum=True, maximum=100.0)
    shapes = root.integer("shapes", minimum=2, maximum=10000)
    region = root.string("region", "cell", choices=("cell", "hull"))
    sampling = root.string("sampling", "random", choices=("random", "grid"))
    seed = root.integer("seed", minimum=0, maximum=2**63 - 1)
    models_table = root.table("models", keys=conditions)
    models = {c: models_table.string(c, choices=sorted(MODELS)) for c in conditions}
    models_table.done()
    timing_table = root.table("timing", {}, keys=("settle_s", "hold_s"))
    timing = Timing(timing_table.number("settle_s", Timing.settle_s, minimum=0.0, maximum=60.0),
                    timing_table.number("hold_s", Timing.hold_s, minimum=0.0,
                                        exclusive_minimum=True, maximum=3600.0))
    timing_table.done()
    analysis = _analysis(root.table("analysis", {}, keys=AnalysisSettings.__dataclass_fields__))
    root.done()
    return MeasurementProtocol(
        name=name, description=description, device=device, conditions=conditions,
        diameters_mm=diameters, height_mm=height, shapes=shapes, region=region,
        sampling=sampling, seed=seed, models=models, timing=timing, analysis=analysis,
        text=text, sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(), path=source)


def _analysis(table: Section) -> AnalysisSettings:
    d = AnalysisSettings()
    strip = table.raw("strip_mm", None)
    settings = AnalysisSettings(
        registration=table.string("registration", d.registration, choices=("rigid",
                                                                            "similarity")),
        max_fiducial_rms_mm=table.number("max_fiducial_rms_mm", d.max_fiducial_rms_mm,
                                         minimum=0.0, exclusive_minimum=True, maximum=100.0),
        max_hole_fraction=table.number("max_hole_fraction", d.max_hole_fraction, minimum=0.0,
                                       maximum=0.9),
        strip_mm=None if strip is None else table.number("strip_mm", minimum=0.0,
                                                         exclusive_minimum=True, maximum=100.0),
        confidence=table.number("confidence", d.confidence, minimum=0.5, maximum=0.999),
        resamples=table.integer("resamples", d.resamples, minimum=100, maximum=100000),
        tolerance_D_P=table.number("tolerance_D_P", d.tolerance_D_P, minimum=0.0, maximum=1.0),
        tolerance_D_S=table.number("tolerance_D_S", d.tolerance_D_S, minimum=0.0, maximum=1.0),
        offset_limit_mm=table.number("offset_limit_mm", d.offset_limit_mm, minimum=0.0,
                                     exclusive_minimum=True, maximum=10.0),
        gain_limit=table.number("gain_limit", d.gain_limit, minimum=0.0,
                                exclusive_minimum=True, maximum=1.0),
    )
    table.done()
    return settings


def _strings(section: Section, key: str, choices: list[str]) -> list[str]:
    values = section.array(key)
    for value in values:
        if value not in choices:
            raise section.fail(key, f"expected each of {choices}, got {value!r}")
    return values


def _numbers(section: Section, key: str, minimum: float, maximum: float) -> list[float]:
    values = section.array(key)
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int | float) or \
                not minimum <= value <= maximum:
            raise section.fail(key, f"expected numbers in [{minimum:g}, {maximum:g}], got "
                                    f"{value!r}")
    return [float(v) for v in values]


def _check_on_device(protocol: MeasurementProtocol, layout: Layout, root: Section) -> None:
    """d/l in the criteria's range for the device's lattice; the bump within the travel."""
    lattice = lattice_of(layout)
    for diameter in protocol.diameters_mm:
        ratio = layout.pitch_mm / diameter
        if not MIN_D_OVER_L <= ratio <= MAX_D_OVER_L[lattice]:
            raise root.fail("diameters_mm", f"{diameter:g} mm gives d/l = {ratio:.4g} on "
                            f"{layout.name} (pitch {layout.pitch_mm:g} mm); expected d/l in "
                            f"[{MIN_D_OVER_L}, {MAX_D_OVER_L[lattice]:.4g}]")
    if protocol.height_mm > layout.travel_mm:
        raise root.fail("height_mm", f"expected at most the pixels' travel, "
                                     f"{layout.travel_mm:g} mm, got {protocol.height_mm!r}")


# --------------------------------------------------------------------------------------------
# the plan


def region_polygon(layout: Layout, region: Region) -> np.ndarray:
    """Where the bump centres X_i lie: the Voronoi cell of the pixel nearest the pixels'
    centroid (the expectation over one lattice cell, as :func:`~crs_study.quality.criteria.
    distortion` takes it) or the pixels' convex hull; (k, 2) vertices, a segment in 1D."""
    xy = layout.pixel_xy
    lattice = lattice_of(layout)
    if region == "cell":
        centroid = xy.mean(axis=0)
        origin = xy[int(np.argmin(np.hypot(*(xy - centroid).T)))]
        return origin + cell_vertices(lattice, layout.pitch_mm)
    if lattice == "1d":
        return np.array([xy[np.argmin(xy[:, 0])], xy[np.argmax(xy[:, 0])]])
    from scipy.spatial import ConvexHull

    return xy[ConvexHull(xy).vertices]


def sample_centres(polygon: np.ndarray, n: int, sampling: Sampling,
                   rng: np.random.Generator) -> np.ndarray:
    """``n`` bump centres in the (convex) ``polygon``: uniform (``random``) or grid midpoints
    (``grid``; in 2D about ``n``, those of a square grid that fall inside)."""
    if len(polygon) == 2:  # a segment on a line of pixels
        (x0, y0), (x1, _) = polygon
        if sampling == "grid":
            t = (np.arange(n) + 0.5) / n
        else:
            t = rng.random(n)
        return np.column_stack([x0 + (x1 - x0) * t, np.full(n, y0)])
    from scipy.spatial import Delaunay

    hull = Delaunay(polygon)
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    if sampling == "grid":
        area = 0.5 * abs(np.dot(polygon[:, 0], np.roll(polygon[:, 1], 1))
                         - np.dot(polygon[:, 1], np.roll(polygon[:, 0], 1)))
        step = math.sqrt(area / n)
        xs = np.arange(lo[0] + 0.5 * step, hi[0], step)
        ys = np.arange(lo[1] + 0.5 * step, hi[1], step)
        grid = np.array([(x, y) for x in xs for y in ys])
        inside = grid[hull.find_simplex(grid) >= 0]
        # centre the grid on the region's centroid so the midpoints sit symmetrically
        return inside + (polygon.mean(axis=0) - inside.mean(axis=0))
    found = np.empty((0, 2))
    while len(found) < n:
        points = lo + (hi - lo) * rng.random((2 * n, 2))
        found = np.concatenate([found, points[hull.find_simplex(points) >= 0]])
    return found[:n]


def plan_captures(protocol: MeasurementProtocol, layout: Layout) -> tuple[PlannedCapture, ...]:
    """The captures in the order they are shown: per condition its reference (the display
    neutral), then its shapes, every diameter's centres shuffled together (seeded by the
    protocol's seed and the condition), so a drift of the rig over a block does not line up
    with d/l. Shapes are numbered through the whole measurement (``shape-0001``...)."""
    polygon = region_polygon(layout, protocol.region)
    captures: list[PlannedCapture] = []
    number = 0
    for ci, condition in enumerate(protocol.conditions):
        captures.append(PlannedCapture(len(captures), reference_name(condition), "reference",
                                       condition, math.nan, (math.nan, math.nan), 0.0))
        rng = np.random.default_rng(np.random.SeedSequence([protocol.seed, ci]))
        block = [(diameter, tuple(float(v) for v in centre))
                 for diameter in protocol.diameters_mm
                 for centre in sample_centres(polygon, protocol.shapes, protocol.sampling, rng)]
        for k in rng.permutation(len(block)):
            number += 1
            diameter, centre = block[k]
            captures.append(PlannedCapture(len(captures), f"shape-{number:04d}", "shape",
                                           condition, diameter, centre, protocol.height_mm))
    return tuple(captures)


def plan_sha256(captures: tuple[PlannedCapture, ...]) -> str:
    """The plan's fingerprint: sha256 of its captures as JSON (exact floats)."""
    text = json.dumps([c.to_dict() for c in captures], sort_keys=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
