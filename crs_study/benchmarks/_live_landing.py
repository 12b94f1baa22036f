"""Bench area ``live``, part two: where the bump lands against the finger, with and without
prediction (:mod:`crs_study.live.predict`).

Each trace is sent through the live session's own code on the simulated device in virtual time
(:func:`crs_study.live.simulate.simulate`: 9600 baud, servos at 0.08 s/cm; deterministic, the
same on any machine) once with prediction off and once on. Traces:

* the ten digits (quick: 2, 5, 9), 60 mm high, minimum-jerk strokes at a mean speed of 50
  (slow), 100 (natural) and 200 (fast) mm/s;
* the natural digits with 0.3 mm of tracker jitter per packet (errors against the clean path);
* a straight 100 mm stroke at a constant 100 mm/s that stops at once (the worst case for any
  prediction: informative);
* every recording given with ``--trace FILE`` (``crs-study live --record``), at its recorded
  times, against itself.

Figures per group, the prediction's against no prediction's (the baseline) in the same run:
median over the traces of each trace's median position error at landing (frames on a pressing,
moving finger), the 95th percentile and the largest; the overshoot at stroke ends (95th
percentile over the ends) and the largest lead of any frame. Targets: with prediction the
natural speed's median <= 1.5 mm and <= 50 % of no prediction's; overshoot p95 <= 3 mm over the
digits; no frame leading the finger by more than 15 ms.
"""

from __future__ import annotations

import numpy as np

from crs_study.benchmarks import Figure
from crs_study.live.predict import PredictConfig
from crs_study.live.record import read_trace
from crs_study.live.simulate import simulate
from crs_study.live.trace import digit_trace, stroke_trace

AREA = "live"
SPEEDS = {"slow": 50.0, "natural": 100.0, "fast": 200.0}
TARGET_NATURAL_MEDIAN_MM = 1.5
TARGET_RATIO = 0.5
TARGET_OVERSHOOT_P95_MM = 3.0
TARGET_LEAD_S = 0.015


def groups(quick: bool, traces=()) -> dict[str, list[tuple]]:
    """Name -> [(trace sent, true trace)] (module docstring)."""
    digits = (2, 5, 9) if quick else range(10)
    out = {name: [(t, t) for t in (digit_trace(d, speed_mm_s=speed, profile="minimum-jerk")
                                   for d in digits)]
           for name, speed in SPEEDS.items()}
    out["natural, jitter 0.3 mm"] = [(t.jittered(0.3, seed=d), t)
                                     for d, (t, _) in zip(digits, out["natural"], strict=True)]
    stroke = stroke_trace((-50.0, 0.0), (50.0, 0.0), speed_mm_s=100.0)
    out["straight stroke, 100 mm/s, sudden stop"] = [(stroke, stroke)]
    for path in traces or ():
        recorded = read_trace(path)
        out[f"recording {recorded.name.removeprefix('recording ')}"] = [(recorded, recorded)]
    return out


def measure(group: list[tuple], predict: PredictConfig) -> dict[str, float]:
    runs = [simulate(sent, predict, truth=true).errors for sent, true in group]
    medians = [np.median(r.errors_mm) for r in runs if r.errors_mm.size]
    p95 = [np.percentile(r.errors_mm, 95) for r in runs if r.errors_mm.size]
    overshoot = np.concatenate([r.overshoot_mm for r in runs])
    leads = np.concatenate([r.leads_s for r in runs])
    return {"median": float(np.median(medians)) if medians else np.nan,
            "p95": float(np.median(p95)) if p95 else np.nan,
            "max": float(max(r.errors_mm.max() for r in runs if r.errors_mm.size)),
            "overshoot": overshoot, "lead_max": float(leads.max()) if leads.size else np.nan}


def run(quick: bool, traces=()) -> list[Figure]:
    out = []
    digits_overshoot, digits_overshoot_off, lead_max, lead_off = [], [], [], []
    for name, group in groups(quick, traces).items():
        on, off = measure(group, PredictConfig()), measure(group, PredictConfig(method="off"))
        base = "no prediction, same traces"
        for key, label in (("median", "median"), ("p95", "p95"), ("max", "max")):
            target, passed = "", None
            if name == "natural" and key == "median":
                ratio_ok = on[key] <= TARGET_RATIO * off[key]
                target = (f"<= {TARGET_NATURAL_MEDIAN_MM:g} mm and ratio <= "
                          f"{TARGET_RATIO:g}")
                passed = bool(on[key] <= TARGET_NATURAL_MEDIAN_MM and ratio_ok)
            out.append(Figure(AREA, f"position error at landing, {name}: {label}", on[key],
                              "mm", base, off[key], target, passed))
        if name in SPEEDS:
            digits_overshoot.append(on["overshoot"])
            digits_overshoot_off.append(off["overshoot"])
        lead_max.append(on["lead_max"])
        lead_off.append(off["lead_max"])
        out.append(Figure(AREA, f"overshoot at stroke ends, {name}: p95",
                          _p95(on["overshoot"]), "mm", base, _p95(off["overshoot"])))
    out.append(Figure(AREA, "overshoot at stroke ends, digits: p95",
                      _p95(np.concatenate(digits_overshoot)), "mm", "no prediction",
                      _p95(np.concatenate(digits_overshoot_off)),
                      f"<= {TARGET_OVERSHOOT_P95_MM:g} mm",
                      bool(_p95(np.concatenate(digits_overshoot)) <= TARGET_OVERSHOOT_P95_MM)))
    lead = max(lead_max) * 1e3
    out.append(Figure(AREA, "bump leads the finger, largest (any frame)", lead, "ms",
                      "no prediction", max(lead_off) * 1e3, f"<= {TARGET_LEAD_S * 1e3:g} ms",
                      bool(lead <= TARGET_LEAD_S * 1e3)))
    return out


def _p95(values: np.ndarray) -> float:
    return float(np.percentile(values, 95)) if values.size else float("nan")
