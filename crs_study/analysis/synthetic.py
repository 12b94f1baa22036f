"""Synthetic BIDS datasets drawn from a known model, to check and time the analysis.

The generating model is the analysis' own: ``logit P(correct) = b_condition + u_participant +
v_digit`` with ``u ~ N(0, participant_sd^2)`` and ``v ~ N(0, digit_sd^2)``; an error names
another digit, more often a neighbour; response times are log-normal, errors slower. Files
follow ``crs_study.dataset.schema`` and the layout of :mod:`crs_study.dataset.folder`, with each
session's sidecar a real :class:`~crs_study.dataset.SessionMetadata` (the runner's format,
read as strictly) whose ``TrialsSha256`` is the sha256 of its ``_beh.tsv`` bytes, so the loader's
checks pass. The column dictionary is the runner's (:func:`crs_study.dataset.column_dictionary`).
This is a test and benchmark aid; real datasets come from ``crs-study run`` / ``dry-run``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from crs_study import __version__
from crs_study._files import sha256_bytes
from crs_study.dataset import SessionMetadata, SessionPaths, column_dictionary
from crs_study.dataset.schema import MISSING, TASK, TRIAL_COLUMNS

#: The frame rate a synthetic session records (the shipped protocol's).
SYNTHETIC_FRAME_RATE_HZ = 15.0


@dataclass(frozen=True)
class SyntheticSpec:
    """What to simulate. ``accuracy`` maps condition -> mean probability correct."""

    n_participants: int = 8
    repetitions: int = 4                      # per digit and condition
    digits: tuple[int, ...] = tuple(range(10))
    accuracy: dict[str, float] = field(
        default_factory=lambda: {"pixel-only": 0.503, "crs": 0.678})
    participant_sd: float = 0.5
    #: the SD over participants of every non-reference condition's effect (logit scale)
    participant_slope_sd: float = 0.0
    digit_sd: float = 0.3
    practice_trials: int = 2
    p_timeout: float = 0.01
    p_fault: float = 0.005
    p_anticipation: float = 0.005
    level_column: str = ""                    # e.g. "digit_height": adds a varied level
    levels: tuple[float, ...] = ()
    level_threshold: float = 0.0              # logistic midpoint of the level effect
    level_slope: float = 4.0
    seed: int = 1


def _logit(p: float) -> float:
    """log(p / (1 - p)), infinite at 0 and 1 (a condition always right or always wrong)."""
    if p <= 0.0 or p >= 1.0:
        return float("-inf") if p <= 0.0 else float("inf")
    return float(np.log(p / (1 - p)))


def simulate_trials(spec: SyntheticSpec, participant: int, rng: np.random.Generator,
                    digit_effects: np.ndarray) -> list[dict[str, object]]:
    """One participant's session rows (practice first, then test trials in random order).

    A participant's effect of each non-reference condition is drawn from a stream of their
    own (``default_rng([seed, 2, participant])``), so a spec without slopes draws the
    datasets it drew before slopes existed."""
    u = rng.normal(0.0, spec.participant_sd)
    slope_rng = np.random.default_rng([spec.seed, 2, participant])
    slopes = {c: (0.0 if k == 0 else float(slope_rng.normal(0.0, spec.participant_slope_sd)))
              for k, c in enumerate(spec.accuracy)}
    plan = [(c, d, r) for c in spec.accuracy for d in range(len(spec.digits))
            for r in range(spec.repetitions)]
    order = rng.permutation(len(plan))
    rows: list[dict[str, object]] = []
    onset = 1.0
    conditions = list(spec.accuracy)
    items = [("practice", conditions[i % len(conditions)], i % len(spec.digits), i)
             for i in range(spec.practice_trials)]
    items += [("test", *plan[k]) for k in order]
    n_digits = len(spec.digits)
    for index, (kind, condition, digit_pos, repetition) in enumerate(items):
        eta = _logit(spec.accuracy[condition]) + u + slopes[condition] + digit_effects[digit_pos]
        level = None
        if spec.level_column and spec.levels:
            level = float(spec.levels[rng.integers(len(spec.levels))])
            guess, lapse = 1.0 / n_digits, 0.02
            x = spec.level_slope * (level - spec.level_threshold) + eta
            p = guess + (1 - guess - lapse) / (1.0 + np.exp(-x))
        else:
            p = 1.0 / (1.0 + np.exp(-eta))
        digit = spec.digits[digit_pos]
        correct = rng.random() < p
        if correct:
            response = digit
        else:
            step = rng.choice([-1, 1, 2, 3], p=[0.35, 0.35, 0.15, 0.15])
            response = spec.digits[(digit_pos + step) % n_digits]
        duration = float(rng.uniform(2.0, 3.0))
        rt = float(np.exp(rng.normal(np.log(2.2 if correct else 2.8), 0.3)))
        timed_out = rng.random() < spec.p_timeout
        fault = rng.random() < spec.p_fault
        if rng.random() < spec.p_anticipation:
            rt = float(rng.uniform(0.02, 0.12))
        row: dict[str, object] = {
            "trial_index": index, "trial_type": kind, "block": 0 if kind == "practice" else 1,
            "condition": condition, "repetition": repetition, "digit": digit,
            "response": MISSING if timed_out else response,
            "correct": MISSING if timed_out else int(response == digit),
            "response_time": MISSING if timed_out else round(rt, 4),
            "response_time_from_offset": MISSING if timed_out else round(rt - duration, 4),
            "onset": round(onset, 4), "stimulus_duration": round(duration, 4),
            "timed_out": int(timed_out), "device_fault": int(fault), "rerun": 0,
            "frames": int(duration * 50), "late_frames": int(rng.poisson(0.2)),
            "median_wire_latency": round(float(rng.uniform(0.01, 0.02)), 5),
            "responder": "observer",
        }
        onset += duration + (rt if not timed_out else 10.0) + 1.0
        row["trial_end"] = round(onset, 4)
        if spec.level_column:
            row[spec.level_column] = MISSING if level is None else level
        rows.append(row)
    return rows


def write_tsv(path: Path, columns: list[str], rows: list[dict[str, object]]) -> bytes:
    """Write rows as a BIDS TSV (``n/a`` for missing) and return the bytes written."""
    lines = ["\t".join(columns)]
    for row in rows:
        lines.append("\t".join(str(row[c]) for c in columns))
    data = ("\n".join(lines) + "\n").encode("utf-8")
    path.write_bytes(data)
    return data


def write_dataset(root: str | Path, spec: SyntheticSpec = SyntheticSpec()) -> Path:
    """Write a complete synthetic dataset under ``root`` and return its path."""
    rng = np.random.default_rng(spec.seed)
    digit_effects = rng.normal(0.0, spec.digit_sd, size=len(spec.digits))
    sessions = {f"{i + 1:02d}": simulate_trials(spec, i, rng, digit_effects)
                for i in range(spec.n_participants)}
    extra = [spec.level_column] if spec.level_column else []
    return write_sessions(root, sessions, extra, seed=spec.seed)


def write_sessions(root: str | Path, sessions: dict[str, list[dict[str, object]]],
                   extra_columns: list[str] | None = None, seed: int = 1) -> Path:
    """Write a dataset holding one session (``ses-1``) per participant label, rows as given.

    Every row must hold every column of ``TRIAL_COLUMNS`` plus ``extra_columns``; the sidecar
    records the checksums the loader verifies.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset_description.json").write_text(json.dumps({
        "Name": "synthetic digit identification", "BIDSVersion": "1.9.0",
        "DatasetType": "raw", "Authors": ["crs-study synthetic"],
        "GeneratedBy": [{"Name": "crs-study", "Version": __version__,
                         "Description": "crs_study.analysis.synthetic"}],
    }, indent=2) + "\n")
    columns = list(TRIAL_COLUMNS) + list(extra_columns or [])
    (root / f"task-{TASK}_beh.json").write_text(json.dumps(column_dictionary(), indent=2)
                                               + "\n")
    (root / "README").write_text("Synthetic digit-identification dataset written by "
                                 "crs_study.analysis.synthetic for tests and benchmarks.\n")
    labels = list(sessions)
    (root / "participants.tsv").write_text(
        "participant_id\n" + "".join(f"sub-{label}\n" for label in labels))
    (root / "participants.json").write_text(json.dumps(
        {"participant_id": {"Description": "pseudonymous label"}}, indent=2) + "\n")
    protocol_text = ('[study]\nid = "synthetic"\n'
                     'analysis_plan = "analysis/digit_identification.toml"\n')
    device_text = "# synthetic\n"
    start = datetime(2026, 1, 1, 9, tzinfo=UTC)
    for i, (label, rows) in enumerate(sessions.items()):
        paths = SessionPaths(root, label, 1)
        paths.beh_dir.mkdir(parents=True, exist_ok=True)
        data = write_tsv(paths.tsv, columns, rows)
        metadata = SessionMetadata(
            task_name=TASK, task_description="Synthetic digit identification",
            instructions="none: simulated answers", protocol_text=protocol_text,
            protocol_sha256=sha256_bytes(protocol_text.encode()),
            protocol_path="protocols/synthetic.toml", study_id="synthetic", study_version="1",
            device_file_text=device_text, device_file_sha256=sha256_bytes(device_text.encode()),
            device_url="sim://", software_version=__version__, seed=seed * 1000 + i,
            counterbalance=i, plan_sha256=sha256_bytes(f"synthetic plan {label}".encode()),
            stimulus_sha256=None, participant=label, session=1,
            consent_form_version="synthetic", responder="observer", clock="virtual",
            frame_rate_hz=SYNTHETIC_FRAME_RATE_HZ, start_time=start,
            end_time=start + timedelta(hours=1), status="complete", trials_planned=len(rows),
            trials_completed=len(rows), trials_sha256=sha256_bytes(data))
        paths.sidecar.write_text(metadata.to_json(), encoding="utf-8")
    return root
