"""Import of surface measurements: what DIC tools export for one captured shape.

A capture is a table of points in the DIC's own frame (millimetres): an in-plane position
(x, y) and the out-of-plane coordinate z of the surface, its displacement w from the DIC's
reference image, or both. Read here (:func:`read_surface`):

* **plain CSV/TSV** (any of ``,`` ``;`` tab or spaces between values): columns ``x``, ``y``
  and ``z`` and/or ``w``, optionally ``u``, ``v`` (in-plane displacement);
* **VIC-3D style** (Correlated Solutions): ``X``, ``Y``, ``Z`` (metric, the calibration's
  units), ``U``, ``V``, ``W`` (displacements) and ``sigma`` (the match's confidence, -1
  where a point has no data); the lower-case ``x``, ``y``, ``u``, ``v`` of the same file
  are image coordinates in pixels and are never read;
* **GOM Correlate style**: ``x [mm]``, ``y [mm]``, ``z [mm]``, ``dX [mm]``, ``dY [mm]``,
  ``dZ [mm]``, often ``;`` between values and a decimal comma, lines of metadata above the
  header;
* **DICe** (Sandia's Digital Image Correlation Engine, stereo): ``MODEL_COORDINATES_X/Y/Z``,
  ``MODEL_DISPLACEMENT_X/Y/Z`` and ``SIGMA`` (-1 for a failed subset), in the calibration's
  units; ``COORDINATE_X/Y`` and ``DISPLACEMENT_X/Y`` are pixels;
* **MATLAB .mat** (v4 to v7, read by :func:`scipy.io.loadmat`): variables ``x``, ``y`` and
  ``z`` and/or ``w`` (any shape, the same number of elements; NaN where there is no data),
  as a MultiDIC- or DICe-based script saves them. A v7.3 file (HDF5) is refused with the
  line to save it in v7.

Units: a unit in the header (``x [mm]``, ``X (m)``, ``z_um``) is converted to millimetres;
pixels are refused (an uncalibrated, 2D export has no out-of-plane displacement); a header
without units is taken in ``units`` (millimetres by default). Empty cells, ``NaN``, ``-`` and
``n/a`` are holes, as is a point whose ``sigma`` is negative. Everything wrong is one line
naming the file (and the line): missing columns, a unit that is no length, a cell that is no
number, fewer than :data:`MIN_POINTS` points with data.

Fiducials (:func:`read_fiducials`) are a table of the same kind: ``pixel`` (the pixel's index
in the device file, from 0) and its ``x``, ``y`` in the DIC's frame, marked on the reference
capture (the knot that ties the fabric to the pixel).
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crs_study.errors import MeasurementError

#: Fewest points with data a capture may hold.
MIN_POINTS = 10
#: Text formats by suffix; ``.mat`` is MATLAB's.
TEXT_SUFFIXES = (".csv", ".tsv", ".txt", ".dat")
SUFFIXES = (*TEXT_SUFFIXES, ".mat")
#: Length units a header may name, in millimetres.
UNITS_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0, "um": 1e-3, "µm": 1e-3, "μm": 1e-3,
            "micron": 1e-3, "in": 25.4, "inch": 25.4}
_IMAGE_UNITS = {"px", "pix", "pixel", "pixels"}
#: Cells that mean "no data".
NA_TOKENS = ("", "nan", "NaN", "NAN", "-", "n/a", "N/A", "NA", "--")
#: How far into a file the header is looked for (metadata lines above it).
HEADER_SEARCH_LINES = 200

#: Column names of each role, most specific first: an exact match wins over a case-blind
#: one, so VIC-3D's metric ``X`` is read, never its pixel ``x``.
ROLES: dict[str, tuple[str, ...]] = {
    "x": ("MODEL_COORDINATES_X", "X", "x"),
    "y": ("MODEL_COORDINATES_Y", "Y", "y"),
    "z": ("MODEL_COORDINATES_Z", "Z", "z"),
    "u": ("MODEL_DISPLACEMENT_X", "U", "dX", "dx", "u"),
    "v": ("MODEL_DISPLACEMENT_Y", "V", "dY", "dy", "v"),
    "w": ("MODEL_DISPLACEMENT_Z", "W", "dZ", "dz", "w"),
    "sigma": ("SIGMA", "sigma"),
    "pixel": ("pixel",),
}
_UNIT_RE = re.compile(r"^(?P<name>.*?)\s*(?:\[(?P<a>[^\]]*)\]|\((?P<b>[^)]*)\))\s*$")
_SUFFIX_UNIT_RE = re.compile(r"^(?P<name>.+?)_(?P<unit>mm|m|cm|um|in)$")
_DECIMAL_COMMA_RE = re.compile(r"^[+-]?\d+,\d+(?:[eE][+-]?\d+)?$")


@dataclass(frozen=True)
class SurfaceCapture:
    """The points of one DIC export, in the DIC's frame (mm).

    ``x``, ``y``: the deformed (current) position, ``X + U`` where the export gives
    displacements; ``z``: the surface's out-of-plane coordinate there (``Z + W``), or None;
    ``w``: the out-of-plane displacement from the DIC's reference image, or None. ``valid``
    marks points with data (finite values, ``sigma`` not negative).
    """

    source: str
    format: str  # "vic3d", "gom", "dice", "plain", "mat"
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray | None
    w: np.ndarray | None
    valid: np.ndarray

    @property
    def n_points(self) -> int:
        return int(self.valid.sum())

    @property
    def hole_fraction(self) -> float:
        """Points without data over all points of the file."""
        return 1.0 - self.n_points / len(self.valid) if len(self.valid) else 1.0

    def xy(self) -> np.ndarray:
        return np.column_stack([self.x, self.y])


@dataclass(frozen=True)
class Fiducials:
    """Pixels marked in a capture: their indices and positions in the DIC's frame (mm)."""

    source: str
    pixels: np.ndarray  # (n,) int
    xy: np.ndarray  # (n, 2)


def _split_unit(header: str) -> tuple[str, str | None]:
    """``"x [mm]"`` -> ("x", "mm"); ``"Z_mm"`` -> ("Z", "mm"); ``"X"`` -> ("X", None)."""
    text = header.strip().strip('"').strip("'").strip()
    match = _UNIT_RE.match(text)
    if match:
        return match["name"].strip(), (match["a"] if match["a"] is not None else match["b"]
                                       ).strip()
    match = _SUFFIX_UNIT_RE.match(text)
    if match:
        return match["name"], match["unit"]
    return text, None


def _find_roles(names: list[str], wanted: tuple[str, ...]) -> dict[str, int]:
    """Column index of each role found among ``names`` (already split of units)."""
    exact = {n: i for i, n in reversed(list(enumerate(names)))}
    folded = {n.casefold(): i for i, n in reversed(list(enumerate(names)))}
    # a file with both X and x is VIC-3D's: its lower-case columns are image pixels
    image_lowercase = "X" in exact and "x" in exact
    found: dict[str, int] = {}
    for role in wanted:
        for candidate in ROLES[role]:
            if candidate in exact and not (image_lowercase and candidate.islower()
                                           and candidate in ("x", "y", "u", "v")):
                found[role] = exact[candidate]
                break
        else:
            for candidate in ROLES[role]:
                if image_lowercase and candidate in ("x", "y", "u", "v"):
                    continue
                if candidate.casefold() in folded:
                    found[role] = folded[candidate.casefold()]
                    break
    return found


def _detect_format(names: list[str], delimiter: str) -> str:
    if any(n.startswith("MODEL_COORDINATES") for n in names):
        return "dice"
    if "X" in names and "sigma" in names:
        return "vic3d"
    if any(n in ("dX", "dY", "dZ") for n in names) or delimiter == ";":
        return "gom"
    return "plain"


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return next(csv.reader([line], delimiter=delimiter, skipinitialspace=True))


def _locate_header(lines: list[str], roles: tuple[str, ...], required: tuple[str, ...]
                   ) -> tuple[int, str | None, list[str]] | None:
    """(line index, delimiter, column names) of the first line naming every required role."""
    for index, line in enumerate(lines[:HEADER_SEARCH_LINES]):
        if not line.strip() or line.lstrip().startswith(("#", "***", "//")):
            continue
        for delimiter in (",", ";", "\t", None):
            try:
                fields = _split(line, delimiter)
            except csv.Error:
                continue
            if len(fields) < 2:
                continue
            names = [_split_unit(f)[0] for f in fields]
            if all(r in _find_roles(names, roles) for r in required):
                return index, delimiter, fields
    return None


def _unit_scale(source: str, column: str, unit: str | None, default: str) -> float:
    name = default if unit is None or unit == "" else unit
    key = name.strip()
    if key.casefold() in _IMAGE_UNITS:
        raise MeasurementError(
            f"{source}: column {column!r} is in {key} (image coordinates): export calibrated "
            "metric coordinates (a stereo DIC's X, Y, Z in mm); a 2D DIC gives no "
            "out-of-plane displacement")
    for known, scale in UNITS_MM.items():
        if key == known or key.casefold() == known.casefold():
            return scale
    raise MeasurementError(f"{source}: column {column!r}: unit {key!r} is not a length "
                           f"this reader knows (expected one of {', '.join(UNITS_MM)})")


def _read_table(path: Path, roles: tuple[str, ...], required: tuple[str, ...],
                units: str) -> tuple[dict[str, np.ndarray], str]:
    """The columns of ``roles`` found in a text table (numbers in mm; NaN for holes) and the
    table's format."""
    source = str(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        try:
            text = path.read_bytes().decode("latin-1")
        except OSError as exc:
            raise MeasurementError(f"{source}: cannot read: {exc.strerror or exc}") from None
    except OSError as exc:
        raise MeasurementError(f"{source}: cannot read: {exc.strerror or exc}") from None
    lines = text.splitlines()
    found = _locate_header(lines, roles, required)
    if found is None:
        hint = ""
        if any("COORDINATE_X" in line and "MODEL_COORDINATES_X" not in line
               for line in lines[:HEADER_SEARCH_LINES]):
            hint = " (DICe's COORDINATE_X/Y are image pixels: run a stereo analysis, whose " \
                   "export has MODEL_COORDINATES_X/Y/Z)"
        raise MeasurementError(
            f"{source}: no header with {' and '.join(repr(r) for r in required)} columns in "
            f"its first {HEADER_SEARCH_LINES} lines; expected e.g. "
            f"{', '.join(ROLES[r][1] for r in required)} (VIC-3D), "
            f"{', '.join(r + ' [mm]' for r in required)} (GOM) or "
            f"{', '.join(ROLES[r][0] for r in required)} (DICe){hint}")
    header_index, delimiter, fields = found
    split = [_split_unit(f) for f in fields]
    names = [name for name, _ in split]
    columns = _find_roles(names, roles)
    body = [line for line in lines[header_index + 1:] if line.strip()]
    decimal_comma = delimiter != "," and any(
        _DECIMAL_COMMA_RE.match(cell.strip().strip('"'))
        for line in body[:20] for cell in _split(line, delimiter))
    scaled = {}
    for role, values in _parse_columns(source, body, delimiter, columns, fields,
                                       decimal_comma).items():
        if role not in ("sigma", "pixel"):
            values = values * _unit_scale(source, fields[columns[role]].strip(),
                                          split[columns[role]][1], units)
        scaled[role] = values
    return scaled, _detect_format(names, delimiter or " ")


def _parse_columns(source: str, body: list[str], delimiter: str | None,
                   columns: dict[str, int], fields: list[str], decimal_comma: bool
                   ) -> dict[str, np.ndarray]:
    """The numbers of ``columns`` in the table's rows (pandas' parser; NaN for holes)."""
    import pandas as pd

    if not body:
        return {role: np.empty(0) for role in columns}
    text = "\n".join(body)
    options = dict(header=None, skipinitialspace=True, keep_default_na=False,
                   sep=r"\s+" if delimiter is None else delimiter,
                   engine="python" if delimiter is None else "c")
    wanted = sorted(set(columns.values()))
    try:  # the usual file: every cell wanted a number or a hole, read as floats at once
        frame = pd.read_csv(io.StringIO(text), usecols=wanted, dtype=float,
                            na_values=list(NA_TOKENS), decimal="," if decimal_comma else ".",
                            **options)
        return {role: np.where(np.isfinite(a := frame[column].to_numpy(dtype=float)), a,
                               np.nan) for role, column in columns.items()}
    except (pd.errors.ParserError, ValueError):
        pass  # read it as text below, to say which cell is wrong
    try:
        frame = pd.read_csv(io.StringIO(text), dtype=str, **options)
    except (pd.errors.ParserError, ValueError) as exc:
        raise MeasurementError(f"{source}: {str(exc).strip().splitlines()[0]}") from None
    out = {}
    for role, column in columns.items():
        if column >= frame.shape[1]:  # every row stops short of it: no data
            out[role] = np.full(len(frame), np.nan)
            continue
        cells = frame[column].fillna("").str.strip().str.strip('"')
        holes = cells.isin(NA_TOKENS)
        if decimal_comma:
            cells = cells.str.replace(",", ".", regex=False)
        values = pd.to_numeric(cells.where(~holes), errors="coerce")
        bad = values.isna() & ~holes
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise MeasurementError(f"{source}: row {row + 1} after the header, column "
                                   f"{fields[column].strip()!r}: expected a number, got "
                                   f"{frame[column].iloc[row]!r}")
        array = values.to_numpy(dtype=float)
        out[role] = np.where(np.isfinite(array), array, np.nan)
    return out


def _read_mat(path: Path, units: str) -> dict[str, np.ndarray]:
    """Variables x, y and z and/or w of a MATLAB file (v4 to v7), flattened, in mm."""
    from scipy.io import loadmat

    source = str(path)
    try:
        data = loadmat(path)
    except NotImplementedError:
        raise MeasurementError(f"{source}: a MATLAB v7.3 (HDF5) file; save it in v7 "
                               "(save(file, 'x', 'y', 'z', '-v7')) or export a CSV") from None
    except (ValueError, TypeError, OSError) as exc:
        raise MeasurementError(f"{source}: not a MATLAB file scipy can read: {exc}") from None
    names = [k for k in data if not k.startswith("__")]
    columns = _find_roles(names, ("x", "y", "z", "u", "v", "w"))
    out = {}
    scale = _unit_scale(source, "all variables", None, units)
    for role, index in columns.items():
        try:
            array = np.asarray(data[names[index]], dtype=float).ravel()
        except (TypeError, ValueError):
            raise MeasurementError(f"{source}: variable {names[index]!r} is not numeric") \
                from None
        out[role] = np.where(np.isfinite(array), array, np.nan) * scale
    return out


def read_surface(path: str | Path, *, units: str = "mm") -> SurfaceCapture:
    """One capture (module docstring); ``units``: those of columns whose header names none."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise MeasurementError(f"{path}: expected a DIC export ending in "
                               f"{', '.join(SUFFIXES)}")
    if not path.is_file():
        raise MeasurementError(f"{path}: no such file")
    _unit_scale(str(path), "--units", None, units)  # a bad default unit fails now
    if path.suffix.lower() == ".mat":
        columns, kind = _read_mat(path, units), "mat"
    else:
        columns, kind = _read_table(path, ("x", "y", "z", "u", "v", "w", "sigma"), ("x", "y"),
                                    units)
    source = str(path)
    missing = [r for r in ("x", "y") if r not in columns]
    if missing or ("z" not in columns and "w" not in columns):
        raise MeasurementError(
            f"{source}: expected columns (or variables) x, y and z or w (out-of-plane "
            f"coordinate or displacement); found {', '.join(sorted(columns)) or 'none'}")
    sizes = {len(v) for v in columns.values()}
    if len(sizes) != 1:
        raise MeasurementError(f"{source}: the variables differ in size ({sorted(sizes)})")
    x, y = columns["x"], columns["y"]
    if "u" in columns:
        x = x + columns["u"]
    if "v" in columns:
        y = y + columns["v"]
    w = columns.get("w")
    z = columns.get("z")
    if z is not None and w is not None:
        z = z + w  # the deformed surface: the reference coordinate plus its displacement
    valid = np.isfinite(x) & np.isfinite(y)
    for values in (z, w):
        if values is not None:
            valid &= np.isfinite(values)
    if "sigma" in columns:
        valid &= ~(columns["sigma"] < 0)
    if valid.sum() < MIN_POINTS:
        raise MeasurementError(f"{source}: {int(valid.sum())} point(s) with data of "
                               f"{len(valid)}; expected at least {MIN_POINTS}")
    return SurfaceCapture(source, kind, x, y, z, w, valid)


def heights_above_reference(capture: SurfaceCapture, reference: SurfaceCapture | None
                            ) -> np.ndarray:
    """Each point's height above the reference capture (the display neutral), mm: the
    export's out-of-plane displacement ``w`` where it has one (the DIC's reference image is
    the neutral display); else its ``z`` minus the reference's ``z`` interpolated linearly
    (:class:`scipy.interpolate.LinearNDInterpolator`) at the same point of the DIC's frame,
    NaN outside the reference's points."""
    if capture.w is not None:
        return capture.w
    if reference is None or reference.z is None:
        raise MeasurementError(f"{capture.source}: no displacement column, so a reference "
                               "capture with z (the display neutral) is needed to subtract; "
                               "none was found")
    from scipy.interpolate import LinearNDInterpolator

    valid = reference.valid
    base = LinearNDInterpolator(reference.xy()[valid], reference.z[valid])(capture.xy())
    return capture.z - base


def read_fiducials(path: str | Path, *, units: str = "mm") -> Fiducials:
    """Pixel fiducials: columns ``pixel``, ``x``, ``y`` (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise MeasurementError(f"{path}: no such fiducials file (columns pixel, x, y: each "
                               "marked pixel's index in the device file and its position in "
                               "the DIC's frame)")
    columns, _ = _read_table(path, ("pixel", "x", "y"), ("pixel", "x", "y"), units)
    pixels, xy = columns["pixel"], np.column_stack([columns["x"], columns["y"]])
    bad = ~np.isfinite(pixels) | (pixels != np.round(pixels)) | (pixels < 0)
    if bad.any():
        raise MeasurementError(f"{path}: pixel {pixels[bad][0]!r} is not a pixel index (a "
                               "whole number from 0)")
    if not np.isfinite(xy).all():
        raise MeasurementError(f"{path}: a fiducial without a position (every pixel marked "
                               "needs its x and y)")
    index = pixels.astype(int)
    if len(set(index.tolist())) != len(index):
        raise MeasurementError(f"{path}: a pixel is marked twice")
    return Fiducials(str(path), index, xy)


def write_table(columns: dict[str, np.ndarray], delimiter: str = ",") -> str:
    """A plain table of ``columns`` (header, then rows; NaN written empty): what the
    stand-in and the tests write."""
    out = io.StringIO()
    writer = csv.writer(out, delimiter=delimiter, lineterminator="\n")
    writer.writerow(list(columns))
    for row in zip(*columns.values(), strict=True):
        writer.writerow(["" if isinstance(v, float) and math.isnan(v) else
                         (repr(float(v)) if isinstance(v, float | np.floating) else v)
                         for v in row])
    return out.getvalue()
