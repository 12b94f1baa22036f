"""A measurement folder analysed: captures imported, registered, measured, compared.

:func:`analyze_measurement` reads what ``crs-study quality measure`` stored (the record with
its protocol and device file texts, so the analysis needs nothing beyond the folder; the
manifest of what was shown) and the DIC exports beside it, then for each capture:

1. the export is read (:mod:`~crs_study.quality.dic_import`); heights are its out-of-plane
   displacement ``w``, or, for an export of coordinates alone, ``z`` minus the condition's
   reference capture (the display neutral) interpolated at the same DIC points;
2. the points are taken into the display's frame by the registration fitted once to the
   fiducials (:mod:`~crs_study.quality.registration`; its RMS residual checked);
3. the shape's terms of Eqs. 1-2 / 5-6 are measured (:mod:`~crs_study.quality.measured`) and
   predicted: the condition's display model, fed the setpoints the manifest recorded, sampled
   at the same points with the measurement's noise level added (seeded by the protocol's seed
   and the capture) and read by the same fit; and its exact terms;
4. each pixel's height is compared with the model's (:mod:`~crs_study.quality.residual_map`);
   the reference captures give each pixel's offset at neutral.

The shapes are then compared with the model (:mod:`~crs_study.quality.measured_result`).
Every problem is a one-line :class:`~crs_study.errors.MeasurementError` naming the file.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from crs_study.display import DisplayModel, get_model
from crs_study.errors import CrsStudyError, MeasurementError
from crs_study.geometry.layout import Layout, layout_from_dict
from crs_study.quality.criteria import shape_distortion
from crs_study.quality.dic_import import (
    SUFFIXES,
    TEXT_SUFFIXES,
    SurfaceCapture,
    heights_above_reference,
    read_fiducials,
    read_surface,
)
from crs_study.quality.lattices import lattice_of
from crs_study.quality.manifest import (
    CAPTURES,
    FIDUCIALS,
    MANIFEST,
    RECORD,
    ManifestEntry,
    MeasurementRecord,
    read_manifest,
)
from crs_study.quality.measured import SampledSurface, measure_shape, window_radius
from crs_study.quality.measured_result import MeasuredQuality, ShapeRow, compare
from crs_study.quality.measurement_protocol import (
    AnalysisSettings,
    MeasurementProtocol,
    measurement_protocol_from_text,
    plan_captures,
)
from crs_study.quality.registration import fit_registration
from crs_study.quality.residual_map import pixel_heights, reference_offsets, residual_map
from crs_study.stimuli.targets import Bump

#: Radius (in point spacings, at least 1 mm) over which a pixel's height is averaged.
PIXEL_RADIUS_SPACINGS = 2.0


def find_capture(folder: Path, name: str, suffixes: tuple[str, ...] = SUFFIXES) -> Path | None:
    """The export of capture ``name`` in ``folder`` (any suffix reader knows); None when
    there is none; two of them are one ambiguity too many."""
    found = [folder / f"{name}{s}" for s in suffixes if (folder / f"{name}{s}").is_file()]
    if len(found) > 1:
        raise MeasurementError(f"{folder}: {', '.join(p.name for p in found)}: two exports of "
                               f"capture {name!r}; keep one")
    return found[0] if found else None


def load_measurement(folder: Path) -> tuple[MeasurementRecord, MeasurementProtocol, Layout]:
    """The record, protocol and device of a measurement folder (from the stored texts)."""
    record = MeasurementRecord.read(folder / RECORD)
    try:
        protocol = measurement_protocol_from_text(record.protocol_text, record.protocol_path,
                                                  device_text=record.device_file_text)
        layout = layout_from_dict(tomllib.loads(record.device_file_text),
                                  source=protocol.device)
    except (CrsStudyError, tomllib.TOMLDecodeError) as exc:
        raise MeasurementError(f"{folder / RECORD}: its stored protocol or device file no "
                               f"longer reads: {exc}") from None
    return record, protocol, layout


def analyze_measurement(folder: str | Path, *, captures: str | Path | None = None,
                        fiducials: str | Path | None = None, units: str = "mm"
                        ) -> MeasuredQuality:
    """Analyse the measurement in ``folder`` (module docstring).

    ``captures``: the folder of the DIC exports (default ``folder/captures``); ``fiducials``:
    the fiducials file (default ``fiducials.csv`` there); ``units``: the length unit of
    export columns whose header names none.
    """
    folder = Path(folder)
    record, protocol, layout = load_measurement(folder)
    if not record.is_complete:
        raise MeasurementError(
            f"{folder}: the measurement is {record.status} at capture "
            f"{record.captures_completed + 1} of {record.captures_planned}; finish it (run the "
            "same crs-study quality measure command) before analysing it")
    plan = plan_captures(protocol, layout)
    entries = read_manifest(folder / MANIFEST, layout.n_actuators)
    if [e.capture for e in entries] != [c.name for c in plan]:
        raise MeasurementError(f"{folder / MANIFEST}: its captures are not those of the "
                               "protocol's plan; the folder was edited")
    capture_dir = Path(captures) if captures is not None else folder / CAPTURES
    files = {e.capture: find_capture(capture_dir, e.capture) for e in entries}
    missing = [name for name, path in files.items() if path is None
               and not name.startswith("ref-")]
    if missing:
        raise MeasurementError(
            f"{capture_dir}: no export of {len(missing)} capture(s), first {missing[0]!r}: "
            f"save each DIC export as <capture>{'|'.join(SUFFIXES)} (the names are the "
            f"manifest's capture column)")
    fiducial_path = Path(fiducials) if fiducials is not None else \
        find_capture(capture_dir, FIDUCIALS, TEXT_SUFFIXES)
    if fiducial_path is None:
        raise MeasurementError(f"{capture_dir}: no {FIDUCIALS}.csv (columns pixel, x, y: the "
                               "pixels marked in the DIC's frame)")
    settings = protocol.analysis
    registration = fit_registration(read_fiducials(fiducial_path, units=units), layout,
                                    settings.registration)
    registration.check(settings.max_fiducial_rms_mm)

    line_y = float(layout.pixel_xy[0, 1]) if layout.lattice == "line" else None
    strip = settings.strip_mm or 0.5 * layout.beam_section.width_mm
    models = {c: get_model(protocol.models[c], layout) for c in protocol.conditions}
    references: dict[str, SurfaceCapture] = {}
    offsets = []
    notes = []
    for entry in entries:
        if entry.kind != "reference":
            continue
        if files[entry.capture] is None:
            notes.append(f"{capture_dir}: no reference capture {entry.capture!r}; the "
                         f"pixels' offsets at neutral are unknown for {entry.condition}")
            continue
        reference = read_surface(files[entry.capture], units=units)
        references[entry.condition] = reference
        if reference.z is None:
            notes.append(f"{reference.source}: no z coordinate; the pixels' offsets at "
                         "neutral are unknown")
            continue
        xy = registration.to_display(reference.xy()[reference.valid])
        z = reference.z[reference.valid] * registration.scale
        try:
            flat = SampledSurface(xy, z, line_y=line_y, strip_mm=strip)
        except MeasurementError as exc:
            raise MeasurementError(f"{reference.source}: {exc}") from None
        offsets.append(reference_offsets(xy, z, layout, max(1.0, PIXEL_RADIUS_SPACINGS *
                                                             flat.spacing), flat.noise_mm))

    shapes, commanded, residuals = [], [], []
    for entry in entries:
        if entry.kind != "shape":
            continue
        path = files[entry.capture]
        capture = read_surface(path, units=units)
        heights = heights_above_reference(capture, references.get(entry.condition))
        keep = capture.valid & np.isfinite(heights)
        xy = registration.to_display(capture.xy()[keep])
        heights = heights[keep] * registration.scale
        bump = Bump((entry.x_mm, entry.y_mm), entry.diameter_mm, entry.height_mm)
        model = models[entry.condition]
        try:
            row, pixel_model, pixel_measured = _measure(
                xy, heights, bump, entry, layout, model, line_y, strip, settings, str(path),
                protocol.seed)
        except MeasurementError as exc:
            raise MeasurementError(f"{path}: {exc}") from None
        shapes.append(row)
        commanded.append(entry.setpoints_mm[: layout.n_pixels])
        residuals.append(pixel_measured - pixel_model)

    rows, verdicts = compare(shapes, protocol.models, lattice_of(layout),
                             confidence=settings.confidence, resamples=settings.resamples,
                             tolerance_D_P=settings.tolerance_D_P,
                             tolerance_D_S=settings.tolerance_D_S, seed=protocol.seed)
    residual = residual_map(layout, np.array(commanded), np.array(residuals), offsets,
                            height_mm=protocol.height_mm,
                            offset_limit_mm=settings.offset_limit_mm,
                            gain_limit=settings.gain_limit)
    return MeasuredQuality(
        measurement=str(folder), protocol=protocol.name, device=layout.name,
        lattice=lattice_of(layout), pitch_mm=layout.pitch_mm, height_mm=protocol.height_mm,
        confidence=settings.confidence,
        tolerance_D_P=settings.tolerance_D_P, tolerance_D_S=settings.tolerance_D_S,
        rows=rows, shapes=tuple(shapes), verdicts=verdicts, registration=registration,
        residual_map=residual, notes=tuple(notes))


def _spacing(xy: np.ndarray) -> float:
    """The median distance from a point to its nearest neighbour (mm)."""
    return float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))


def _measure(xy: np.ndarray, heights: np.ndarray, bump: Bump, entry: ManifestEntry,
             layout: Layout, model: DisplayModel, line_y: float | None, strip: float,
             settings: AnalysisSettings, source: str, seed: int
             ) -> tuple[ShapeRow, np.ndarray, np.ndarray]:
    """One shape: its row, and the model's and the measurement's heights at each pixel."""
    spacing = _spacing(xy)
    reach = 0.5 * bump.diameter_mm + 0.5 * layout.pitch_mm + \
        window_radius(spacing, bump.diameter_mm) + 3.0 * spacing
    centre = np.asarray(bump.centre_mm)
    near = (np.abs(xy[:, 0] - centre[0]) <= reach) if line_y is not None else \
        (np.hypot(*(xy - centre).T) <= reach)
    surface = SampledSurface(xy[near], heights[near], line_y=line_y, strip_mm=strip)
    measured = measure_shape(surface, bump, layout,
                             max_hole_fraction=settings.max_hole_fraction)
    setpoints = entry.setpoints_mm
    noise = np.random.default_rng(np.random.SeedSequence([seed, entry.capture_index]))
    predicted = measure_shape(surface.with_heights(model.surface(setpoints, surface.xy), noise),
                              bump, layout, max_hole_fraction=1.0)
    exact = shape_distortion(model, bump, setpoints)
    pixel_measured, pixel_model = pixel_heights(
        xy, heights, model.surface(setpoints, xy), layout=layout,
        radius_mm=max(1.0, PIXEL_RADIUS_SPACINGS * spacing))
    row = ShapeRow(
        capture=entry.capture, source=source, condition=entry.condition,
        diameter_mm=bump.diameter_mm, d_over_l=layout.pitch_mm / bump.diameter_mm,
        x_mm=entry.x_mm, y_mm=entry.y_mm, D_P=measured.D_P, D_S=measured.D_S,
        peak_x_mm=measured.peak_mm[0], peak_y_mm=measured.peak_mm[1],
        peak_fit=measured.peak_fit, holes=measured.holes, points=measured.points,
        model_D_P=predicted.D_P, model_D_S=predicted.D_S, exact_D_P=exact[0],
        exact_D_S=exact[1])
    return row, pixel_model, pixel_measured
