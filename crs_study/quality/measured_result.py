"""Measured D_P and D_S beside the model's prediction and the paper's lines, with a verdict.

Per condition and bump diameter (so per d/l), over the shapes measured:

* the measured D_P and D_S: the means over shapes of the terms of Eqs. 1-2 (1D) or 5-6 (2D),
  with percentile bootstrap intervals over shapes (:func:`scipy.stats.bootstrap`, the
  protocol's confidence and resamples, seeded by the protocol's seed);
* the model's prediction for the same device, the same targets and the same setpoints: the
  condition's display model sampled at the measured points and read by the same fit
  (``model``: what the measurement would give were the device the model), and, for
  reference, the model's own exact terms (``exact``, :func:`~crs_study.quality.criteria.
  shape_distortion`: the quadrature of the criteria, no sampling);
* the paper's lines at that d/l (Wang, Meng & Chen, "Continuity reinforcement skeleton for
  pixel-based haptic display": pixel-only D_P = 0.25 d/l and D_S = 0.994 d/l in 1D, the
  linear connection's D_S = 1.545 (d/l)^2; hexagonal pixels D_P = 0.3510 d/l, D_S =
  1.318 d/l), where the paper gives one for the condition;
* the paired difference measured - model, its bootstrap interval, and a verdict against the
  protocol's tolerance t: ``as predicted`` when the interval lies within +-t, ``differs``
  when it lies wholly beyond one of them, ``inconclusive`` otherwise (more shapes, or less
  noise, would decide). A condition's verdict is the worst of its rows, with the shapes that
  depart most from the model named.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from crs_study.quality import measured_report
from crs_study.quality.criteria import theory
from crs_study.quality.registration import Registration
from crs_study.quality.residual_map import ResidualMap
from crs_study.rendering.conditions import get_condition

VERDICTS = ("as predicted", "inconclusive", "differs")  # from best to worst
#: How many of a condition's shapes its verdict names.
WORST_SHAPES = 3


@dataclass(frozen=True)
class ShapeRow:
    """One measured shape: its target, its terms measured, as the model predicts them
    (sampled like the measurement) and the model's exact ones."""

    capture: str
    source: str
    condition: str
    diameter_mm: float
    d_over_l: float
    x_mm: float
    y_mm: float
    D_P: float
    D_S: float
    peak_x_mm: float
    peak_y_mm: float
    peak_fit: str
    holes: float
    points: int
    model_D_P: float
    model_D_S: float
    exact_D_P: float
    exact_D_S: float


@dataclass(frozen=True)
class Interval:
    """A mean with its bootstrap interval."""

    estimate: float
    low: float
    high: float

    def to_list(self) -> list[float | None]:
        return [None if not math.isfinite(v) else v for v in (self.estimate, self.low,
                                                                self.high)]


@dataclass(frozen=True)
class ConditionRow:
    """One (condition, d/l) of the measurement."""

    condition: str
    model: str
    diameter_mm: float
    d_over_l: float
    shapes: int
    D_P: Interval
    D_S: Interval
    model_D_P: Interval
    model_D_S: Interval
    exact_D_P: float
    exact_D_S: float
    diff_D_P: Interval
    diff_D_S: Interval
    paper_D_P: float | None
    paper_D_S: float | None
    verdict_D_P: str
    verdict_D_S: str


@dataclass(frozen=True)
class Verdict:
    """A condition's verdict and the shapes that depart most from the model."""

    condition: str
    verdict: str
    worst: tuple[str, ...]
    detail: str


@dataclass(frozen=True)
class MeasuredQuality:
    """A measurement compared with its model (module docstring); from
    :func:`~crs_study.quality.measured_analysis.analyze_measurement`."""

    measurement: str
    protocol: str
    device: str
    lattice: str
    pitch_mm: float
    height_mm: float  # z_f of the shapes
    confidence: float
    tolerance_D_P: float
    tolerance_D_S: float
    rows: tuple[ConditionRow, ...]
    shapes: tuple[ShapeRow, ...]
    verdicts: tuple[Verdict, ...]
    registration: Registration
    residual_map: ResidualMap
    notes: tuple[str, ...] = field(default=())

    def to_frame(self):
        """One row per (condition, d/l): ``condition``, ``model``, ``diameter_mm``,
        ``d_over_l``, ``shapes``; ``D_P``, ``D_P_low``, ``D_P_high`` (and the same for
        ``D_S``, ``model_D_P``, ``model_D_S``, ``diff_D_P``, ``diff_D_S``: measured - model);
        ``exact_D_P``, ``exact_D_S``; ``paper_D_P``, ``paper_D_S`` (NaN where the paper gives
        no line); ``verdict_D_P``, ``verdict_D_S``."""
        import pandas as pd

        records = []
        for row in self.rows:
            record = {"condition": row.condition, "model": row.model,
                      "diameter_mm": row.diameter_mm, "d_over_l": row.d_over_l,
                      "shapes": row.shapes}
            for name in ("D_P", "D_S", "model_D_P", "model_D_S", "diff_D_P", "diff_D_S"):
                interval = getattr(row, name)
                record.update({name: interval.estimate, f"{name}_low": interval.low,
                               f"{name}_high": interval.high})
            record.update({"exact_D_P": row.exact_D_P, "exact_D_S": row.exact_D_S,
                           "paper_D_P": math.nan if row.paper_D_P is None else row.paper_D_P,
                           "paper_D_S": math.nan if row.paper_D_S is None else row.paper_D_S,
                           "verdict_D_P": row.verdict_D_P, "verdict_D_S": row.verdict_D_S})
            records.append(record)
        return pd.DataFrame(records)

    def shapes_frame(self):
        """One row per shape: the fields of :class:`ShapeRow`."""
        import pandas as pd

        return pd.DataFrame([asdict(s) for s in self.shapes],
                            columns=list(ShapeRow.__dataclass_fields__))

    def headline(self) -> str:
        """One line per condition: its verdict and, per d/l, measured against model."""
        lines = []
        for verdict in self.verdicts:
            parts = [f"d/l={r.d_over_l:.3g}: D_P {r.D_P.estimate:.4f} (model "
                     f"{r.model_D_P.estimate:.4f}), D_S {r.D_S.estimate:.4f} (model "
                     f"{r.model_D_S.estimate:.4f})"
                     for r in self.rows if r.condition == verdict.condition]
            lines.append(f"{verdict.condition}: {verdict.verdict}; " + "; ".join(parts))
        flagged = self.residual_map.flagged
        if flagged:
            lines.append("residual map: " + "; ".join(f"{p.channel} (pixel {p.pixel}): {p.why}"
                                                      for p in flagged))
        else:
            lines.append("residual map: every pixel within its limits")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        def clean(value):
            if isinstance(value, float):
                return value if math.isfinite(value) else None
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            if isinstance(value, list | tuple):
                return [clean(v) for v in value]
            return value

        rows = []
        for row in self.rows:
            data = asdict(row)
            for name in ("D_P", "D_S", "model_D_P", "model_D_S", "diff_D_P", "diff_D_S"):
                data[name] = getattr(row, name).to_list()
            rows.append(data)
        return clean({
            "measurement": self.measurement, "protocol": self.protocol, "device": self.device,
            "lattice": self.lattice, "pitch_mm": self.pitch_mm, "height_mm": self.height_mm,
            "confidence": self.confidence,
            "tolerance": {"D_P": self.tolerance_D_P, "D_S": self.tolerance_D_S},
            "intervals": "[estimate, low, high]: mean over shapes, percentile bootstrap",
            "rows": rows,
            "verdicts": [asdict(v) for v in self.verdicts],
            "registration": self.registration.to_dict(),
            "residual_map": self.residual_map.to_dict(),
            "shapes": [asdict(s) for s in self.shapes],
            "notes": list(self.notes),
        })

    def to_json(self) -> str:
        """``results.json``."""
        return json.dumps(self.to_dict(), indent=2) + "\n"

    def plot(self, ax=None):
        """The Fig. 2d style chart (:func:`crs_study.quality.measured_report.plot_measured`)."""
        return measured_report.plot_measured(self, ax)

    def plot_residual_map(self, ax=None):
        """:func:`crs_study.quality.measured_report.plot_residual_map`."""
        return measured_report.plot_residual_map(self, ax)


def mean_interval(values: np.ndarray, confidence: float, resamples: int,
                  rng: np.random.Generator) -> Interval:
    """The mean of ``values`` and its percentile bootstrap interval (NaN below two values)."""
    from scipy.stats import bootstrap

    values = np.asarray(values, dtype=float)
    mean = float(values.mean()) if len(values) else math.nan
    if len(values) < 2:
        return Interval(mean, math.nan, math.nan)
    if np.ptp(values) == 0:
        return Interval(mean, mean, mean)
    result = bootstrap((values,), np.mean, confidence_level=confidence, n_resamples=resamples,
                       method="percentile", random_state=rng, vectorized=True)
    return Interval(mean, float(result.confidence_interval.low),
                    float(result.confidence_interval.high))


def verdict_of(difference: Interval, tolerance: float) -> str:
    """``as predicted``, ``differs`` or ``inconclusive`` (module docstring)."""
    low, high = difference.low, difference.high
    if not (math.isfinite(low) and math.isfinite(high)):
        return "inconclusive"
    if -tolerance <= low and high <= tolerance:
        return "as predicted"
    if low > tolerance or high < -tolerance:
        return "differs"
    return "inconclusive"


def paper_lines(lattice: str, condition: str, model: str, d_over_l: float
                ) -> tuple[float | None, float | None]:
    """The paper's D_P and D_S at ``d_over_l`` for a condition shown by ``model``: the
    pixel-only lines for a condition on the pixels alone (the linear connection's D_S in 1D
    when the model is ``linear``); none for a condition that drives the beams (the CRS),
    which the paper measured rather than drew."""
    if get_condition(condition).drives_beams:
        return None, None
    dp = theory(lattice, "nearest", "D_P", d_over_l)
    ds = theory(lattice, "linear" if model == "linear" and lattice == "1d" else "nearest",
                "D_S", d_over_l)
    return (None if dp is None else float(dp)), (None if ds is None else float(ds))


def compare(shapes: Sequence[ShapeRow], models: dict[str, str], lattice: str, *,
            confidence: float, resamples: int, tolerance_D_P: float, tolerance_D_S: float,
            seed: int) -> tuple[tuple[ConditionRow, ...], tuple[Verdict, ...]]:
    """The rows and verdicts of a measurement's shapes (module docstring)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 29]))
    rows = []
    verdicts = []
    for condition in dict.fromkeys(s.condition for s in shapes):
        mine = [s for s in shapes if s.condition == condition]
        condition_rows = []
        for diameter in sorted({s.diameter_mm for s in mine}, reverse=True):
            group = [s for s in mine if s.diameter_mm == diameter]
            arrays = {name: np.array([getattr(s, name) for s in group])
                      for name in ("D_P", "D_S", "model_D_P", "model_D_S", "exact_D_P",
                                   "exact_D_S")}

            def interval(values: np.ndarray) -> Interval:
                return mean_interval(values, confidence, resamples, rng)

            diff_p = interval(arrays["D_P"] - arrays["model_D_P"])
            diff_s = interval(arrays["D_S"] - arrays["model_D_S"])
            d_over_l = group[0].d_over_l
            paper_p, paper_s = paper_lines(lattice, condition, models[condition], d_over_l)
            condition_rows.append(ConditionRow(
                condition, models[condition], diameter, d_over_l, len(group),
                interval(arrays["D_P"]), interval(arrays["D_S"]),
                interval(arrays["model_D_P"]), interval(arrays["model_D_S"]),
                float(arrays["exact_D_P"].mean()), float(arrays["exact_D_S"].mean()),
                diff_p, diff_s, paper_p, paper_s,
                verdict_of(diff_p, tolerance_D_P), verdict_of(diff_s, tolerance_D_S)))
        rows += condition_rows
        worst_verdict = max((v for r in condition_rows for v in (r.verdict_D_P, r.verdict_D_S)),
                            key=VERDICTS.index)
        departure = sorted(mine, key=lambda s: -max(abs(s.D_P - s.model_D_P) / tolerance_D_P
                                                    if tolerance_D_P else 0.0,
                                                    abs(s.D_S - s.model_D_S) / tolerance_D_S
                                                    if tolerance_D_S else 0.0))
        worst = tuple(s.capture for s in departure[:WORST_SHAPES])
        detail = "; ".join(
            f"{s.capture} (X = ({s.x_mm:.1f}, {s.y_mm:.1f}) mm, d/l = {s.d_over_l:.3g}): "
            f"D_P {s.D_P:.4f} vs {s.model_D_P:.4f}, D_S {s.D_S:.4f} vs {s.model_D_S:.4f}"
            for s in departure[:WORST_SHAPES])
        verdicts.append(Verdict(condition, worst_verdict, worst, detail))
    return tuple(rows), tuple(verdicts)
