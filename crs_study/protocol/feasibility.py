"""Can the device show this protocol? Every check of a protocol against its device, once.

:func:`check_feasibility` returns a :class:`Feasibility`: one :class:`Finding` per check
(severity ``"ok"``, or ``"error"`` for each check that fails; a check that needs a failed one
passed is not run: rendering needs the stimulus inside the display, within travel and
curvature), each with the protocol key it concerns, a one-line message and the numbers behind
it. :func:`check_on_device` is what loading a protocol runs: the lines of the checks passed,
or the first failure as a :class:`~crs_study.errors.ProtocolError` at the key's line
(:func:`crs_study.protocol.problems.protocol_problems` lists them all).

The checks, in the order a failure is reported:

1. the device file loads (``study.device``) and the consent form has the protocol's version
   (``study.consent_form``, ``study.consent_form_version``);
2. symbols need a 2D (hexagonal) display;
3. with a skeleton condition, the bump's curvature 2 pi^2 z_f / l^2 (Eq. 7's largest |z''|)
   below the beam's yield curvature 2 sigma_y / (E t) (:func:`crs_study.quality.mechanics.
   stimulus_limits`): both ``bump_height_mm`` and ``bump_diameter_mm`` are named, with the
   bound each would have to meet given the other;
4. the bump centre's path (every drawn frame of every symbol) inside the convex hull of the
   pixels: ``offset_mm`` is named when the same symbols fit at the display centre, else
   the width (``digit_width_pitch`` for the digit set) when their horizontal extent alone
   leaves the area, else the height (the vertical extent alone, or a corner); a size set by
   ``[levels]`` is named by its level;
5. the bump height within the pixel travel;
6. the frame rate within the wire: a frame that moves every channel of the busiest controller
   (3 n + 7 bytes at 9600 baud, :func:`crs_study.device.base.full_frame_wire_time_s`);
7. with a skeleton condition, no collapse: Delta >= 1 (Eq. 4);
8. every frame of every symbol rendered in every condition with ``policy="error"`` (within
   the pixels' and boundary servos' travel, no feed cap): the frames go to the one render
   cache (:func:`crs_study.rendering.frames.render_frames`) that sessions then read.

A protocol with ``[levels]`` is checked at each level as a fixed stimulus; lines shared by all
levels are kept once, the others carry their level, and a failure is named
``levels.values[i]: at PARAMETER = VALUE: KEY: ...``. An adaptive protocol is checked at every
level its procedure can show (the grid and the practice level); a failure names the bound
nearer to the level (``adaptive.max: at PARAMETER = VALUE: ...``).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from crs_study._toml_lines import find_line, one_line
from crs_study.consent.form import read_form
from crs_study.device.base import full_frame_rate_hz, full_frame_wire_time_s
from crs_study.errors import (
    ConfigError,
    ConsentError,
    CrsStudyError,
    ProtocolError,
    RenderError,
)
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol, consent_form_path
from crs_study.quality.mechanics import StimulusLimits, layout_delta, stimulus_limits
from crs_study.rendering.conditions import get_condition
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import (
    Stimulus,
    StimulusSpec,
    display_centre,
    inside_convex_hull,
    placement_centre,
    stimulus_for,
)
from crs_study.stimuli.targets import Bump

Severity = Literal["ok", "warning", "error"]


@dataclass(frozen=True)
class Finding:
    """One check of a protocol: passed (``"ok"``), odd but legal (``"warning"``) or failed.

    ``key_path`` is the protocol key concerned (``stimulus.frame_rate_hz``; None when no one
    key is), ``line`` its line in the protocol file, ``message`` one line without file, line
    or key, and ``values`` the numbers behind the message (e.g. ``frame_rate_hz`` and
    ``max_frame_rate_hz``)."""

    severity: Severity
    key_path: str | None
    message: str
    values: dict[str, float | int | str | None] = field(default_factory=dict)
    line: int | None = None

    def describe(self, source: str | None = None) -> str:
        """``SOURCE:LINE: KEY: MESSAGE``, each part left out when unknown."""
        where = "" if source is None else (f"{source}:{self.line}: " if self.line
                                           else f"{source}: ")
        return where + (f"{self.key_path}: " if self.key_path else "") + self.message


@dataclass(frozen=True)
class Feasibility:
    """The findings of :func:`check_feasibility` on the protocol file ``source``."""

    source: str
    findings: tuple[Finding, ...]

    @property
    def passed(self) -> tuple[str, ...]:
        """The messages of the checks passed, in order (what ``validate`` lists)."""
        return tuple(f.message for f in self.findings if f.severity == "ok")

    @property
    def errors(self) -> tuple[Finding, ...]:
        return tuple(f for f in self.findings if f.severity == "error")

    @property
    def feasible(self) -> bool:
        return not self.errors

    def error(self) -> ProtocolError | None:
        """The first failure as a one-line :class:`ProtocolError` (None when all passed)."""
        if not self.errors:
            return None
        first = self.errors[0]
        return ProtocolError(first.message, source=self.source, line=first.line,
                             key_path=first.key_path)

    def to_frame(self):
        """One row per finding: severity, key_path, line, message, values (a dict)."""
        import pandas as pd  # only here: validate and sessions need no pandas

        return pd.DataFrame([asdict(f) for f in self.findings],
                            columns=["severity", "key_path", "line", "message", "values"])

    def to_json(self) -> str:
        return json.dumps({"source": self.source, "feasible": self.feasible,
                           "findings": [asdict(f) for f in self.findings]}, indent=1)


def collapse_delta(layout: Layout) -> float:
    """The no-collapse number of Eq. 4 for a device (inf when the skin has no stiffness)."""
    return layout_delta(layout)


def check_on_device(protocol: Protocol) -> tuple[str, ...]:
    """Check the protocol against its device; return one line per check passed.

    Raises :class:`ProtocolError` (naming the protocol key and its line) for the first check
    that fails. The heavy part (rendering every frame of every symbol) is cached per stimulus
    and device (:func:`crs_study.rendering.frames.render_frames`).
    """
    result = check_feasibility(protocol)
    error = result.error()
    if error is not None:
        raise error
    return result.passed


def check_feasibility(protocol: Protocol, layout: Layout | None = None) -> Feasibility:
    """Every check of the module docstring, in order; every failure is a finding (never
    raises for a failed check). ``layout`` replaces the protocol's device (``device check
    --layout``)."""
    findings = _findings(protocol, layout)
    located = tuple(f if f.key_path is None else
                    Finding(f.severity, f.key_path, f.message, f.values,
                            find_line(protocol.text, f.key_path)) for f in findings)
    return Feasibility(str(protocol.path), located)


def _findings(protocol: Protocol, layout: Layout | None) -> list[Finding]:
    if layout is None:
        try:
            layout = protocol.layout()
        except ConfigError as exc:
            return [Finding("error", "study.device", one_line(exc))]
    found = [Finding("ok", "study.device", f"device {layout.name}: {layout.n_pixels} pixels, "
                     f"{len(layout.beams)} beams, {layout.n_actuators} actuators",
                     {"pixels": layout.n_pixels, "beams": len(layout.beams),
                      "actuators": layout.n_actuators})]
    found.append(_consent(protocol))  # the device checks run whatever the form says
    levels = protocol.levels
    if levels is None:
        return found + _spec_findings(protocol.stimulus, protocol.conditions, layout, True)
    per_level: list[list[Finding]] = []
    for i, value in enumerate(levels.values):
        checked = _spec_findings(protocol.stimulus_at(value), protocol.conditions, layout,
                                 sized=not levels.varies_size)
        failed = [f for f in checked if f.severity == "error"]
        if failed:  # the first level that fails, with every check failing there
            return found + [Finding("error", level_key(protocol, i, value),
                                    f"at {levels.parameter} = {value:g}: "
                                    + inner.describe(), inner.values) for inner in failed]
        per_level.append(checked)
    # lines shared by all levels are kept once, the others are prefixed with their level
    shared = set.intersection(*({f.message for f in lines} for lines in per_level))
    found += [f for f in per_level[0] if f.message in shared]
    for value, lines in zip(levels.values, per_level, strict=True):
        found += [Finding("ok", f.key_path, f"{levels.parameter} = {value:g}: {f.message}",
                          f.values) for f in lines if f.message not in shared]
    return found


def level_key(protocol: Protocol, i: int, value: float) -> str:
    """The key a finding at the protocol's ``i``-th level ``value`` names:
    ``levels.values[i]``, or for an adaptive protocol the bound nearer to it (or
    ``adaptive.practice_level``)."""
    spec = protocol.adaptive
    if spec is None:
        return f"levels.values[{i}]"
    if spec.practice_level is not None and value == spec.practice and value not in spec.grid():
        return "adaptive.practice_level"
    middle = spec.from_axis(sum(spec.axis_bounds) / 2)
    return "adaptive.max" if value >= middle else "adaptive.min"


def _consent(protocol: Protocol) -> Finding:
    try:
        form = read_form(consent_form_path(protocol))
    except (ConfigError, ConsentError) as exc:
        return Finding("error", "study.consent_form", one_line(exc))
    if form.version != protocol.consent_form_version:
        return Finding("error", "study.consent_form_version",
                       f"expected the form's version {form.version!r} "
                       f"({protocol.consent_form}), got {protocol.consent_form_version!r}",
                       {"form_version": form.version})
    return Finding("ok", "study.consent_form_version",
                   f"consent form {protocol.consent_form} version {form.version}",
                   {"form_version": form.version})


def _spec_findings(spec: StimulusSpec, conditions: tuple[str, ...], layout: Layout,
                   sized: bool) -> list[Finding]:
    """The device checks of one stimulus spec: the passed ones, or every check that failed
    (the checks that need them passed are not run)."""
    try:
        return _device_checks(spec, conditions, layout, sized)
    except ConfigError as exc:  # a symbol without strokes, a stimulus too slow to draw
        return [Finding("error", exc.key_path, exc.reason)]
    except CrsStudyError as exc:
        return [Finding("error", None, one_line(exc))]


def _device_checks(spec: StimulusSpec, conditions: tuple[str, ...], layout: Layout,
                   sized: bool) -> list[Finding]:
    if layout.lattice != "hex":
        return [Finding("error", "study.device", f"{spec.symbol_set.plural} need a 2D display, "
                        "got "
                        f"{layout.name!r} with a {layout.lattice!r} lattice")]
    limits = stimulus_limits(layout, Bump((0.0, 0.0), spec.bump_diameter_mm,
                                          spec.bump_height_mm))
    beams = [c for c in conditions if get_condition(c).drives_beams]
    curvature = _curvature(spec, limits) if beams else None
    stimuli = [stimulus_for(spec, layout.pitch_mm, placement_centre(spec, layout), d)
               for d in spec.symbols]
    first = [_inside(spec, layout, stimuli, sized), _height(spec, limits), _wire(spec, layout)]
    found = [first[1], first[2], first[0]]
    if curvature is not None:
        found.append(curvature)
        delta = collapse_delta(layout)
        found.append(Finding("error", "conditions.names", f"the beams collapse on this device "
                             f"(Eq. 4: Delta = {delta:.2f} < 1); got conditions {beams!r}",
                             {"delta": delta}) if delta < 1.0 else
                     Finding("ok", "conditions.names",
                             f"no collapse: Delta = {delta:.2f} >= 1 (Eq. 4)", {"delta": delta}))
    # each check above stands alone: every one that fails is reported, in the order of the
    # module docstring; rendering needs them all passed
    failed = [f for f in found[3:4] + first + found[4:] if f.severity == "error"]
    if failed:
        return failed
    for condition in conditions:
        rendered = _rendered(condition, layout, stimuli, spec)
        if rendered.severity == "error":
            return [rendered]
        found.append(rendered)
    return found


def _curvature(spec: StimulusSpec, limits: StimulusLimits) -> Finding:
    """The bump's curvature against the beam's yield curvature (both keys named)."""
    z_f, l_mm = spec.bump_height_mm, spec.bump_diameter_mm
    curvature, limit = limits.curvature, limits.yield_curvature
    values = {"curvature_per_mm": curvature, "yield_curvature_per_mm": limit}
    if curvature > limit:
        return Finding(
            "error", "stimulus.bump_height_mm",
            f"the bump's curvature {curvature:.4f}/mm (2 pi^2 z_f / l^2 with z_f = "
            f"stimulus.bump_height_mm = {z_f!r} and l = stimulus.bump_diameter_mm = {l_mm!r}) "
            f"exceeds the beam's yield curvature {limit:.4f}/mm; expected bump_height_mm <= "
            f"{limit * l_mm ** 2 / (2 * math.pi ** 2):.3g} at this diameter or "
            f"bump_diameter_mm >= {math.sqrt(2 * math.pi ** 2 * z_f / limit):.3g} at this "
            "height", values)
    return Finding("ok", "stimulus.bump_height_mm", f"curvature {curvature:.4f}/mm <= yield "
                   f"{limit:.4f}/mm", values)


def _inside(spec: StimulusSpec, layout: Layout, stimuli: list[Stimulus], sized: bool
            ) -> Finding:
    """The bump centre's path inside the pixel area, naming the key at fault."""
    placed = np.asarray(placement_centre(spec, layout))
    drawn = np.concatenate([s.centres_mm[s.drawn] for s in stimuli])
    inside, margin = inside_convex_hull(drawn, layout.pixel_xy)
    if inside.all():
        return Finding("ok", "stimulus", f"bump centre path inside the pixel area (margin "
                       f"{margin:.1f} mm)", {"margin_mm": margin})
    worst = drawn[np.argmin(inside)]
    noun, plural = spec.symbol_set.noun, spec.symbol_set.plural
    height_key, width_key = (f"stimulus.{spec.file_key(k)}" for k in
                             ("symbol_height_pitch", "symbol_width_pitch"))
    where = (f"the bump centre leaves the pixel area (by {-margin:.1f} mm at "
             f"({worst[0]:.1f}, {worst[1]:.1f}) mm); expected the {noun} inside the display")
    values = {"margin_mm": margin}
    relative = drawn - placed
    centre = np.asarray(display_centre(layout))
    if spec.placement == "offset" and inside_convex_hull(relative + centre,
                                                         layout.pixel_xy)[0].all():
        return Finding("error", "stimulus.offset_mm", f"{where}, got {list(spec.offset_mm)!r} "
                       f"(the {plural} fit at the display centre)", values)
    if not sized:
        return Finding("error", height_key, where, values)
    # the size alone, at the display centre: does the width, or the height, leave the area?
    across = np.column_stack([relative[:, 0], np.zeros(len(relative))]) + centre
    if not inside_convex_hull(across, layout.pixel_xy)[0].all():
        return Finding("error", width_key, f"{where}, got {spec.symbol_width_pitch!r} "
                       f"(the {plural}' width alone leaves it)", values)
    upright = np.column_stack([np.zeros(len(relative)), relative[:, 1]]) + centre
    alone = "height alone leaves it" if not inside_convex_hull(
        upright, layout.pixel_xy)[0].all() else \
        f"a corner leaves it: height and width {spec.symbol_width_pitch!r} together"
    return Finding("error", height_key, f"{where}, got {spec.symbol_height_pitch!r} "
                   f"(the {plural}' {alone})", values)


def _height(spec: StimulusSpec, limits: StimulusLimits) -> Finding:
    values = {"bump_height_mm": limits.height, "pixel_travel_mm": limits.travel}
    if "height" in limits.problems():
        return Finding("error", "stimulus.bump_height_mm", f"expected at most the pixel "
                       f"travel {limits.travel:g} mm, got {spec.bump_height_mm!r}", values)
    return Finding("ok", "stimulus.bump_height_mm", f"bump height {limits.height:g} mm <= "
                   f"pixel travel {limits.travel:g} mm", values)


def _wire(spec: StimulusSpec, layout: Layout) -> Finding:
    wire_rate = full_frame_rate_hz(layout)
    values = {"frame_rate_hz": spec.frame_rate_hz, "max_frame_rate_hz": wire_rate,
              "full_frame_wire_ms": full_frame_wire_time_s(layout) * 1e3}
    if spec.frame_rate_hz > wire_rate * (1 + 1e-9):
        return Finding(
            "error", "stimulus.frame_rate_hz",
            f"expected at most {wire_rate:.2f} frames/s (a full frame takes "
            f"{values['full_frame_wire_ms']:.1f} ms on the wire at 9600 baud), got "
            f"{spec.frame_rate_hz!r}", values)
    return Finding("ok", "stimulus.frame_rate_hz", f"frame rate {spec.frame_rate_hz:g}/s <= "
                   f"{wire_rate:.2f}/s (every channel of the busiest controller in every "
                   "frame)", values)


def _rendered(condition: str, layout: Layout, stimuli: list[Stimulus], spec: StimulusSpec
              ) -> Finding:
    """Every frame of every symbol in ``condition`` within travel (``policy="error"``)."""
    renderer = Renderer(layout, condition, policy="error")
    peak_feed = 0.0
    for stim in stimuli:
        try:
            frames = render_frames(stim, renderer)
        except RenderError as exc:
            shown = spec.symbol_set
            return Finding("error", "stimulus.bump_height_mm", f"{shown.noun} {stim.symbol} "
                           f"cannot be shown: {exc}",
                           {"condition": condition, shown.column: stim.symbol})
        if layout.boundary_actuators:
            peak_feed = max(peak_feed, float(frames[:, layout.n_pixels:].max()))
    if not get_condition(condition).drives_beams:
        return Finding("ok", "conditions.names", f"{condition}: every frame within travel",
                       {"condition": condition})
    return Finding("ok", "conditions.names", f"{condition}: every frame within travel "
                   f"(largest boundary feed {peak_feed:.2f} mm <= "
                   f"{layout.boundary_travel_mm:g} mm)",
                   {"condition": condition, "largest_boundary_feed_mm": peak_feed})
