"""Device geometry from a device file: pixels, beams, boundary servos, channels, calibration.

A device file (TOML) describes one CRS display. Two ship with the package and are chosen by
name (``crs2d``, the published 19-pixel hexagonal device; ``crs1d``, the published 5-pixel
line); any other file is chosen by path. Units: millimetres and newtons throughout
(E in N/mm^2 = MPa, I in mm^4, EI in N mm^2, the foundation stiffness beta in N/mm^2).

Geometry
    Pixels sit on lattice points: ``lattice = "line"`` (x = i d) or ``"hex"`` (axial
    coordinates (q, r): x = d (q + r/2), y = d r sqrt(3)/2). Each beam is an ordered list of
    pixels that are consecutive neighbours along one lattice direction. The beam is clamped at
    base height with zero slope at each end, ``end_margin_pitch`` pitches beyond its end pixels,
    where a boundary servo feeds length into the display (paper, Fig. 3a and Methods).

Actuators
    Actuator order is fixed: the pixels in file order, then for each beam its start servo and
    its end servo. ``setpoint`` vectors (mm) follow that order: pixel heights above base, then
    boundary feed (length pushed into the display, >= 0).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from crs_study._toml import Section, read_toml
from crs_study.errors import DeviceFileError
from crs_study.paths import data_dir

#: Device files shipped with the package, by name.
BUILTIN_DEVICES = ("crs2d", "crs1d")

#: Pulse widths an LSC board accepts (docs/device.md, "Calibration"): 500 to 2500 us.
PULSE_MIN_US = 500
PULSE_MAX_US = 2500

_CHANNEL_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_-]*):(\d+)$")
_HEX_DIRECTIONS = ((1, 0), (0, 1), (-1, 1))  # axial unit steps for the three lattice directions


@dataclass(frozen=True)
class Controller:
    """One LSC-24 board: its name in channel references and how it numbers channels."""

    name: str
    channel_base: int  # 0 or 1: the number of the first channel (unconfirmed: docs/device.md)
    channels: int  # how many channels the board has (24 for the LSC-24)
    index: int  # position in the device file = position of its port in a serial:// URL


@dataclass(frozen=True)
class Calibration:
    """The device file's linear map between stroke (mm) and pulse width (us) for one channel.

    ``pulse = zero_us + (full_us - zero_us) * mm / travel_mm``; ``zero_us > full_us`` reverses
    the direction. The calibrated range is [0, travel_mm] mm. The map itself, with its limits
    and whole-us quantisation, is :class:`crs_study.device.calibration.PulseMap` (one place,
    used by every device and the wire estimate).
    """

    zero_us: float
    full_us: float
    travel_mm: float


@dataclass(frozen=True)
class Actuator:
    """A servo: a pixel (``kind == "pixel"``) or a boundary servo at a beam end."""

    index: int  # position in the setpoint vector
    kind: str  # "pixel" or "boundary"
    name: str  # "pixel 3", "beam 2 start"
    controller: str
    channel: int
    calibration: Calibration


@dataclass(frozen=True)
class Beam:
    """A steel beam through a line of pixels, clamped at base height at both ends."""

    index: int
    pixels: tuple[int, ...]  # pixel indices in order from start to end
    start: tuple[float, float]  # clamp point (mm)
    end: tuple[float, float]
    start_servo: int  # actuator index of the boundary servo at the start
    end_servo: int

    @property
    def straight_length(self) -> float:
        """Distance between the clamps (mm): the beam's length in the display when flat."""
        return math.dist(self.start, self.end)

    @property
    def direction(self) -> np.ndarray:
        """Unit vector from start to end."""
        v = np.subtract(self.end, self.start)
        return v / np.linalg.norm(v)


@dataclass(frozen=True)
class BeamSection:
    """Material and cross-section of the beams (mm, N)."""

    material: str
    youngs_modulus_mpa: float  # E, N/mm^2
    width_mm: float
    thickness_mm: float
    yield_strength_mpa: float

    @property
    def second_moment_mm4(self) -> float:
        """I = w t^3 / 12 for bending about the width axis (out of plane)."""
        return self.width_mm * self.thickness_mm**3 / 12.0

    @property
    def area_mm2(self) -> float:
        return self.width_mm * self.thickness_mm

    @property
    def bending_stiffness(self) -> float:
        """EI in N mm^2."""
        return self.youngs_modulus_mpa * self.second_moment_mm4

    @property
    def yield_curvature_per_mm(self) -> float:
        """Largest curvature before the surface fibre yields: kappa = 2 sigma_y / (E t)."""
        return 2.0 * self.yield_strength_mpa / (self.youngs_modulus_mpa * self.thickness_mm)


@dataclass(frozen=True)
class Layout:
    """A CRS display as described by its device file. Build with :func:`load_layout`."""

    name: str
    description: str
    source: str  # file the layout was read from
    lattice: str  # "line" or "hex"
    pitch_mm: float
    lattice_coords: tuple[tuple[int, ...], ...]
    pixel_xy: np.ndarray  # (n_pixels, 2) mm; y = 0 for a line
    beams: tuple[Beam, ...]
    actuators: tuple[Actuator, ...]
    controllers: tuple[Controller, ...]
    travel_mm: float  # pixel travel above base
    boundary_travel_mm: float  # largest feed a boundary servo gives
    servo_speed_s_per_mm: float  # time per mm of stroke (0.08 s/cm = 0.008 s/mm)
    end_margin_pitch: float
    beam_section: BeamSection
    foundation_stiffness: float  # Winkler beta, N/mm^2 (force per length per deflection)

    @property
    def n_pixels(self) -> int:
        return len(self.pixel_xy)

    @property
    def n_actuators(self) -> int:
        return len(self.actuators)

    @cached_property
    def pixel_actuators(self) -> tuple[Actuator, ...]:
        return tuple(a for a in self.actuators if a.kind == "pixel")

    @cached_property
    def boundary_actuators(self) -> tuple[Actuator, ...]:
        return tuple(a for a in self.actuators if a.kind == "boundary")

    def neutral_setpoints(self) -> np.ndarray:
        """All pixels at base height, no boundary feed: the safe pose."""
        return np.zeros(self.n_actuators)

    def with_pitch(self, pitch_mm: float) -> Layout:
        """The same device scaled to another pixel pitch (used for d/l sweeps)."""
        scale = pitch_mm / self.pitch_mm
        beams = tuple(
            Beam(
                b.index, b.pixels,
                (b.start[0] * scale, b.start[1] * scale),
                (b.end[0] * scale, b.end[1] * scale),
                b.start_servo, b.end_servo,
            )
            for b in self.beams
        )
        return replace(self, pitch_mm=pitch_mm, pixel_xy=self.pixel_xy * scale, beams=beams)


def layout_key(layout: Layout) -> tuple:
    """A hashable fingerprint of everything in a layout that shapes rendered setpoints (the
    key of the caches of rendered frames and of display models)."""
    return (layout.name, layout.source, layout.pixel_xy.tobytes(), layout.beams,
            layout.travel_mm, layout.boundary_travel_mm, layout.n_actuators)


#: Finest fabric mesh (subdivisions of a pitch) the 2D display models will build.
MAX_FABRIC_SUBDIVISIONS = 64
#: Lower bounds of a device file's lengths and speeds: far below any real display (a 1/64
#: pitch margin, a 0.01 mm stroke, a servo 0.001 s/cm fast), far above where arithmetic fails.
MIN_END_MARGIN_PITCH = 1 / MAX_FABRIC_SUBDIVISIONS
MIN_TRAVEL_MM = 0.01
MIN_SPEED_S_PER_CM = 0.001


def fabric_mesh_for_margin(margin_pitch: float, at_least: int = 8) -> int | None:
    """The 2D fabric's mesh, subdivisions m of a pitch: the smallest m >= ``at_least`` that
    puts the beam clamps (``margin_pitch`` pitches beyond the end pixels) on mesh nodes, i.e.
    ``margin_pitch * m`` whole; None when no m up to :data:`MAX_FABRIC_SUBDIVISIONS` does."""
    for m in range(max(1, at_least), MAX_FABRIC_SUBDIVISIONS + 1):
        if abs(margin_pitch * m - round(margin_pitch * m)) < 1e-9:
            return m
    return None


def device_file_path(name_or_path: str | Path) -> Path:
    """Path of a built-in device (``"crs2d"``, ``"crs1d"``) or of a file given by path."""
    text = str(name_or_path)
    if text in BUILTIN_DEVICES:
        return data_dir() / "devices" / f"{text}.toml"
    return Path(text)


def load_layout(name_or_path: str | Path = "crs2d") -> Layout:
    """Read and validate a device file; every problem is a one-line :class:`DeviceFileError`."""
    path = device_file_path(name_or_path)
    data = read_toml(path, DeviceFileError)
    return layout_from_dict(data, source=path.name if str(name_or_path) in BUILTIN_DEVICES
                            else str(path))


def layout_from_dict(data: dict, source: str = "<device>") -> Layout:
    """Build a :class:`Layout` from parsed TOML, checking every key."""
    root = Section(data, source, error=DeviceFileError)
    name = root.string("name")
    description = root.string("description", "")

    geometry = root.table("geometry")
    lattice = geometry.string("lattice", choices=("line", "hex"))
    pitch = geometry.number("pitch_mm", minimum=1.0, maximum=1000.0)
    # bounded below (a subnormal margin made the beam solver divide by nothing)
    margin = geometry.number("end_margin_pitch", 1.0, minimum=MIN_END_MARGIN_PITCH,
                             maximum=10.0)
    if lattice == "hex" and fabric_mesh_for_margin(margin) is None:
        raise geometry.fail("end_margin_pitch", "on a hexagonal display the clamps must fall on "
                            "the fabric's mesh: expected a multiple of 1/m pitch for some m <= "
                            f"{MAX_FABRIC_SUBDIVISIONS} (e.g. 0.25, 0.3, 1), got {margin!r}")
    coords = _read_pixels(geometry, lattice)
    beam_lists = _read_beams(geometry, len(coords))
    geometry.done()

    servos = root.table("servos")
    # bounded below: a travel of 1e-320 mm made every pulse width infinite
    travel = servos.number("travel_mm", minimum=MIN_TRAVEL_MM, maximum=100.0)
    boundary_travel = servos.number("boundary_travel_mm", minimum=MIN_TRAVEL_MM, maximum=100.0)
    speed = servos.number("speed_s_per_cm", minimum=MIN_SPEED_S_PER_CM, maximum=100.0) / 10.0
    servos.done()

    section = _read_beam_section(root.table("beam"))
    skin = root.table("skin")
    beta_kpa = skin.number("foundation_stiffness_kpa", minimum=0.0, maximum=1e6)
    skin.done()

    controllers = _read_controllers(root)
    channels = root.table("channels")
    pixel_refs = channels.array("pixels")
    boundary_refs = channels.array("boundaries")
    channels.done()
    calibration = _read_calibration(root.table("calibration"), controllers)
    root.done()

    xy = _lattice_xy(coords, lattice, pitch)
    _check_beam_lines(beam_lists, coords, lattice, source)

    if len(pixel_refs) != len(coords):
        raise DeviceFileError(
            f"{source}: channels.pixels: expected {len(coords)} channels (one per pixel), "
            f"got {len(pixel_refs)}"
        )
    if len(boundary_refs) != len(beam_lists):
        raise DeviceFileError(
            f"{source}: channels.boundaries: expected {len(beam_lists)} [start, end] pairs "
            f"(one per beam), got {len(boundary_refs)}"
        )

    actuators: list[Actuator] = []
    used: dict[tuple[str, int], str] = {}

    def add(kind: str, label: str, ref: object, key: str, travel_mm: float) -> int:
        controller, channel = _parse_channel(ref, key, source, controllers)
        if (controller, channel) in used:
            raise DeviceFileError(
                f"{source}: {key}: channel {ref!r} is already used by {used[(controller, channel)]}"
            )
        used[(controller, channel)] = label
        zero_us, full_us = calibration.get(f"{controller}:{channel}", calibration["default"])
        actuators.append(
            Actuator(len(actuators), kind, label, controller, channel,
                     Calibration(zero_us, full_us, travel_mm))
        )
        return len(actuators) - 1

    for i, ref in enumerate(pixel_refs):
        add("pixel", f"pixel {i}", ref, f"channels.pixels[{i}]", travel)
    beams = []
    for b, (members, pair) in enumerate(zip(beam_lists, boundary_refs, strict=True)):
        if not (isinstance(pair, list) and len(pair) == 2):
            raise DeviceFileError(
                f"{source}: channels.boundaries[{b}]: expected [start, end] channels, got {pair!r}"
            )
        s = add("boundary", f"beam {b} start", pair[0], f"channels.boundaries[{b}][0]",
                boundary_travel)
        e = add("boundary", f"beam {b} end", pair[1], f"channels.boundaries[{b}][1]",
                boundary_travel)
        first, last = xy[members[0]], xy[members[-1]]
        unit = (last - first) / np.linalg.norm(last - first)
        start = first - unit * margin * pitch
        end = last + unit * margin * pitch
        beams.append(Beam(b, tuple(members), (float(start[0]), float(start[1])),
                          (float(end[0]), float(end[1])), s, e))

    unused = sorted(set(calibration) - {"default"} - {f"{c}:{n}" for c, n in used})
    if unused:
        raise DeviceFileError(f"{source}: calibration.{unused[0]}: no pixel or boundary servo is "
                              f"on channel {unused[0]} (a typo would leave the real channel on "
                              "the default calibration)")
    return Layout(
        name=name, description=description, source=source, lattice=lattice, pitch_mm=pitch,
        lattice_coords=tuple(coords), pixel_xy=xy, beams=tuple(beams),
        actuators=tuple(actuators), controllers=controllers, travel_mm=travel,
        boundary_travel_mm=boundary_travel, servo_speed_s_per_mm=speed,
        end_margin_pitch=margin, beam_section=section,
        foundation_stiffness=beta_kpa * 1e-3,  # kPa = 1e-3 N/mm^2
    )


def _read_pixels(geometry: Section, lattice: str) -> list[tuple[int, ...]]:
    raw = geometry.array("pixels")
    if not raw:
        raise geometry.fail("pixels", "expected at least one pixel, got []")
    width = 1 if lattice == "line" else 2
    coords: list[tuple[int, ...]] = []
    seen: dict[tuple[int, ...], int] = {}
    for i, item in enumerate(raw):
        point = (item,) if lattice == "line" and not isinstance(item, list) else item
        if (
            not isinstance(point, list | tuple)
            or len(point) != width
            or any(isinstance(c, bool) or not isinstance(c, int) for c in point)
        ):
            shape = "a whole number" if width == 1 else "[q, r] whole numbers (axial)"
            raise geometry.fail(f"pixels[{i}]", f"expected {shape}, got {item!r}")
        point = tuple(point)
        if point in seen:
            raise geometry.fail(
                f"pixels[{i}]", f"duplicate pixel {item!r} (same as pixels[{seen[point]}])"
            )
        seen[point] = i
        coords.append(point)
    return coords


def _read_beams(geometry: Section, n_pixels: int) -> list[list[int]]:
    raw = geometry.array("beams")
    beams: list[list[int]] = []
    for b, members in enumerate(raw):
        if not isinstance(members, list) or len(members) < 2:
            raise geometry.fail(
                f"beams[{b}]", f"expected a list of at least 2 pixel indices, got {members!r}"
            )
        for m in members:
            if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < n_pixels:
                raise geometry.fail(
                    f"beams[{b}]", f"expected pixel indices 0..{n_pixels - 1}, got {m!r}"
                )
        if len(set(members)) != len(members):
            raise geometry.fail(f"beams[{b}]", f"a pixel appears twice in {members!r}")
        same = next((k for k, other in enumerate(beams) if set(other) == set(members)), None)
        if same is not None:
            raise geometry.fail(f"beams[{b}]", f"the same pixels as beams[{same}]: {members!r}")
        beams.append(list(members))
    return beams


def _check_beam_lines(beams: list[list[int]], coords: list[tuple[int, ...]], lattice: str,
                      source: str) -> None:
    """Each beam must run through consecutive lattice neighbours along one direction."""
    for b, members in enumerate(beams):
        steps = {
            tuple(np.subtract(coords[members[k + 1]], coords[members[k]]))
            for k in range(len(members) - 1)
        }
        allowed = {(1,), (-1,)} if lattice == "line" else {
            s for d in _HEX_DIRECTIONS for s in (d, (-d[0], -d[1]))
        }
        if len(steps) != 1 or not steps <= allowed:
            raise DeviceFileError(
                f"{source}: geometry.beams[{b}]: pixels {members!r} are not consecutive "
                f"neighbours along one lattice line"
            )


def _lattice_xy(coords: list[tuple[int, ...]], lattice: str, pitch: float) -> np.ndarray:
    c = np.array(coords, dtype=float)
    if lattice == "line":
        return np.column_stack([c[:, 0] * pitch, np.zeros(len(c))])
    q, r = c[:, 0], c[:, 1]
    return np.column_stack([pitch * (q + r / 2.0), pitch * r * math.sqrt(3.0) / 2.0])


def _read_beam_section(beam: Section) -> BeamSection:
    section = BeamSection(
        material=beam.string("material"),
        # bounds: any real beam material and section, far from floating-point trouble
        youngs_modulus_mpa=beam.number("youngs_modulus_gpa", minimum=0.1, maximum=2000.0) * 1e3,
        width_mm=beam.number("width_mm", minimum=0.001, maximum=100.0),
        thickness_mm=beam.number("thickness_mm", minimum=0.001, maximum=100.0),
        yield_strength_mpa=beam.number("yield_strength_mpa", minimum=1.0, maximum=10000.0),
    )
    beam.done()
    return section


def _read_controllers(root: Section) -> tuple[Controller, ...]:
    raw = root.array("controllers")
    if not raw:
        raise root.fail("controllers", "expected at least one [[controllers]] table")
    out = []
    for i, item in enumerate(raw):
        sec = Section(item, root.source, f"controllers[{i}]", DeviceFileError)
        name = sec.string("name")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
            raise sec.fail("name", f"expected a letter then letters, digits, - or _, got {name!r}")
        base = sec.integer("channel_base", 1, minimum=0, maximum=1)
        count = sec.integer("channels", 24, minimum=1, maximum=32)
        sec.done()
        if any(c.name == name for c in out):
            raise sec.fail("name", f"duplicate controller name {name!r}")
        out.append(Controller(name, base, count, i))
    return tuple(out)


def _parse_channel(ref: object, key: str, source: str,
                   controllers: tuple[Controller, ...]) -> tuple[str, int]:
    match = _CHANNEL_RE.match(ref) if isinstance(ref, str) else None
    if not match:
        raise DeviceFileError(
            f"{source}: {key}: expected \"CONTROLLER:CHANNEL\" like \"A:1\", got {ref!r}"
        )
    name, channel = match.group(1), int(match.group(2))
    by_name = {c.name: c for c in controllers}
    if name not in by_name:
        raise DeviceFileError(
            f"{source}: {key}: unknown controller {name!r} in {ref!r} "
            f"(controllers: {', '.join(by_name)})"
        )
    c = by_name[name]
    if not c.channel_base <= channel < c.channel_base + c.channels:
        raise DeviceFileError(
            f"{source}: {key}: channel {channel} is outside controller {name!r}'s channels "
            f"{c.channel_base}..{c.channel_base + c.channels - 1}"
        )
    return name, channel


def _read_calibration(cal: Section, controllers: tuple[Controller, ...]) -> dict:
    """``default = {zero_us, full_us}`` plus per-channel overrides keyed ``"A:3"``."""
    out = {}
    for key in list(cal.data):
        item = Section(cal.raw(key), cal.source, cal.key_path(key), DeviceFileError)
        zero = item.number("zero_us", minimum=PULSE_MIN_US, maximum=PULSE_MAX_US)
        full = item.number("full_us", minimum=PULSE_MIN_US, maximum=PULSE_MAX_US)
        item.done()
        if abs(full - zero) < 10:
            raise item.fail("full_us", f"expected a range of at least 10 us from zero_us={zero!r}, "
                            f"got {full!r}")
        if key != "default":  # "A:03" and "A:3" are one channel: the lookup uses "A:3"
            controller, channel = _parse_channel(key, cal.key_path(key), cal.source, controllers)
            normal = f"{controller}:{channel}"
            if normal in out:
                raise cal.fail(key, f"channel {normal} is calibrated twice")
            key = normal
        out[key] = (zero, full)
    if "default" not in out:
        raise cal.fail("default", "missing: give default = { zero_us = ..., full_us = ... }")
    cal.done()
    return out
