"""A measurement's files: what was shown when (the manifest) and the record beside it.

A measurement folder (``crs-study quality measure ... --out MEAS``)::

    MEAS/
      measurement.json     the record: protocol and device file (text and sha256), the plan's
                           sha256, device URL, capture mode, clock, status and progress,
                           resumes, faults and interruptions
      manifest.tsv         one row per capture shown, appended durably (MANIFEST_COLUMNS)
      captures/            the DIC exports, one per capture, named as its ``capture`` column
                           (shape-0007.csv, ref-crs.csv, ...), and fiducials.csv
      sourcedata/frames.tsv.gz   every frame sent to the device
      derivatives/         crs-study quality analyze: report.md, results.json, figures/

The manifest's columns: ``capture_index`` (0, 1, ...), ``capture`` (the file stem),
``kind`` (``reference``: the display neutral; ``shape``), ``condition``, ``diameter_mm``
(l), ``d_over_l``, ``x_mm`` and ``y_mm`` (X_i), ``height_mm`` (z_f), ``sent_at``,
``capture_start``, ``capture_end`` (seconds of session time: the shape is sent, has
settled, is taken down), ``capture_utc`` (the wall-clock time the capture window opened, for
matching the DIC's image time stamps; ``n/a`` on a virtual clock), ``clamped`` (what the
renderer had to clip or cap, ``n/a`` when nothing) and ``setpoints_mm`` (every actuator's
setpoint, in the device file's actuator order, ``;`` between them). ``n/a`` marks a value a
reference has not.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from crs_study.errors import MeasurementError

RECORD = "measurement.json"
MANIFEST = "manifest.tsv"
CAPTURES = "captures"
DERIVATIVES = "derivatives"
FIDUCIALS = "fiducials"

MANIFEST_COLUMNS = ("capture_index", "capture", "kind", "condition", "diameter_mm",
                    "d_over_l", "x_mm", "y_mm", "height_mm", "sent_at", "capture_start",
                    "capture_end", "capture_utc", "clamped", "setpoints_mm")
STATUSES = ("running", "interrupted", "complete")


def format_setpoints(setpoints: np.ndarray) -> str:
    """``0.000000;1.250000;...``: micrometre-exact for any stroke."""
    return ";".join(f"{v:.6f}" for v in np.asarray(setpoints, dtype=float))


@dataclass(frozen=True)
class ManifestEntry:
    """One row of the manifest, typed."""

    capture_index: int
    capture: str
    kind: str
    condition: str
    diameter_mm: float
    d_over_l: float
    x_mm: float
    y_mm: float
    height_mm: float
    sent_at: float
    capture_start: float
    capture_end: float
    capture_utc: str
    clamped: str
    setpoints_mm: np.ndarray


def read_manifest(path: str | Path, n_actuators: int) -> list[ManifestEntry]:
    """The manifest's rows; a malformed one is a one-line :class:`MeasurementError`."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise MeasurementError(f"{path}: no such manifest (not a measurement folder?)") \
            from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MeasurementError(f"{path}: cannot read: {exc}") from None
    if not lines or tuple(lines[0].split("\t")) != MANIFEST_COLUMNS:
        raise MeasurementError(f"{path}: expected the header {chr(9).join(MANIFEST_COLUMNS)!r}")
    entries = []
    for number, line in enumerate(lines[1:], start=2):
        cells = line.split("\t")
        if len(cells) != len(MANIFEST_COLUMNS):
            raise MeasurementError(f"{path}:{number}: expected {len(MANIFEST_COLUMNS)} fields, "
                                   f"got {len(cells)}")
        row = dict(zip(MANIFEST_COLUMNS, cells, strict=True))
        try:
            values = {name: _number(row[name]) for name in MANIFEST_COLUMNS
                      if name not in ("capture", "kind", "condition", "capture_utc",
                                      "clamped", "setpoints_mm")}
            setpoints = np.array([float(v) for v in row["setpoints_mm"].split(";")])
        except ValueError as exc:
            raise MeasurementError(f"{path}:{number}: {exc}") from None
        if len(setpoints) != n_actuators:
            raise MeasurementError(f"{path}:{number}: {len(setpoints)} setpoints, the device "
                                   f"has {n_actuators} actuators")
        entries.append(ManifestEntry(
            capture_index=int(values.pop("capture_index")), capture=row["capture"],
            kind=row["kind"], condition=row["condition"], capture_utc=row["capture_utc"],
            clamped=row["clamped"], setpoints_mm=setpoints, **values))
    return entries


def _number(text: str) -> float:
    return math.nan if text == "n/a" else float(text)


@dataclass(frozen=True)
class MeasurementRecord:
    """``measurement.json`` (module docstring): what ran, how far, and what stopped it.

    ``trials_completed`` and ``trials_sha256`` name the progress as the session store
    (:class:`~crs_study.dataset.SessionStore`) checks it on resume: captures stand for
    trials, the manifest for the trial file.
    """

    protocol_name: str
    protocol_text: str
    protocol_sha256: str
    protocol_path: str
    device_file_text: str
    device_file_sha256: str
    device_url: str
    plan_sha256: str
    capture_mode: str
    clock: str
    software_version: str
    start_time: str
    end_time: str | None
    status: str
    captures_planned: int
    captures_completed: int
    manifest_sha256: str | None
    resumes: tuple[dict, ...] = ()
    faults: tuple[dict, ...] = ()
    interruptions: tuple[dict, ...] = ()
    kind: str = field(default="crs-study quality measurement")

    @property
    def trials_completed(self) -> int:
        return self.captures_completed

    @property
    def trials_sha256(self) -> str | None:
        return self.manifest_sha256

    @property
    def is_complete(self) -> bool:
        return self.status == "complete"

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        for key in ("resumes", "faults", "interruptions"):
            data[key] = list(data[key])
        return data

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, ensure_ascii=False) + "\n"

    @classmethod
    def read(cls, path: str | Path) -> MeasurementRecord:
        """Read strictly: a missing or stray key, or a value of the wrong type, is one line."""
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise MeasurementError(f"{path}: no such measurement record (not a measurement "
                                   "folder?)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MeasurementError(f"{path}: cannot read: {exc}") from None
        if not isinstance(data, dict):
            raise MeasurementError(f"{path}: expected a JSON object")
        names = {f.name: f for f in fields(cls)}
        stray = sorted(set(data) - set(names))
        missing = sorted(set(names) - set(data) - {"kind"})
        if stray or missing:
            what = f"unknown key {stray[0]!r}" if stray else f"missing key {missing[0]!r}"
            raise MeasurementError(f"{path}: {what}; not a record crs-study wrote")
        for name, value in data.items():
            kind = names[name].type
            ok = (isinstance(value, str) if kind == "str" else
                  value is None or isinstance(value, str) if kind == "str | None" else
                  isinstance(value, int) and not isinstance(value, bool) if kind == "int" else
                  isinstance(value, list) and all(isinstance(v, dict) for v in value))
            if not ok:
                raise MeasurementError(f"{path}: {name}: unexpected value {value!r}")
        if data["status"] not in STATUSES:
            raise MeasurementError(f"{path}: status: expected one of {STATUSES}, got "
                                   f"{data['status']!r}")
        for key in ("resumes", "faults", "interruptions"):
            data[key] = tuple(data[key])
        return cls(**data)
