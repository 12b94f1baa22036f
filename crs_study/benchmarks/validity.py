"""Bench area ``validity``: the Type I error of the primary test, and what validity costs.

A grid of 6, 12 and 24 participants x a by-participant condition slope SD of 0, 0.6 and 1.0
(logit scale; participant intercept SD 0.6, symbol intercept SD 0.3, the shipped protocol's
design and plan): null studies (no condition effect for the typical participant) drawn by the
power simulation's generator, each tested two ways: the likelihood-ratio statistic against
chi2, and the plan's default test (``p_value = "auto"``: the parametric bootstrap below 20
participants, each study with its own ``B`` replicates, as ``analyze`` runs it; chi2 from
there). Each rate is against alpha = 0.05, with its Clopper-Pearson 95 % interval (the Monte
Carlo error of the number of studies). The bootstrap's p ``(1 + k) / (1 + B)`` read as
``p < 0.05`` has the level ``(ceil(0.05 (B + 1)) - 1) / (B + 1)`` when the bootstrap is
exact (Davison & Hinkley 1997, sec. 4.2): with ``B = 20`` that is 1/21 = 0.0476, the level
it is judged against. ``B`` only adds Monte Carlo error to a study's p; whether the fitted
null is the right reference, which is what the grid checks, does not depend on it, so the
grid uses 20 where ``analyze`` uses 1000 (a fiftieth of the cost; the full grid of 6000
bootstrapped studies takes about half an hour on two cores).

Target: the default test's rate <= 0.06 wherever its interval can tell, i.e. the interval's
lower end at or below 0.06 (a cell whose interval lies wholly above fails). Then the power of
both tests at one effect (12 participants, slope SD 0.6, CRS 65 % against 50 %): the cost of
validity.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy import stats

from crs_study.analysis.bootstrap import StudyRows, bootstrap_studies
from crs_study.analysis.primary import design as primary_design
from crs_study.benchmarks import Figure
from crs_study.power_analysis import design_from_protocol, model_from_parameters
from crs_study.power_analysis.simulate import simulate_studies
from crs_study.power_analysis.study import (
    PowerTask,
    cells_frame,
    planned_power_terms,
    run_task,
)

AREA = "validity"
DESCRIPTION = "Type I error of the primary test (chi2 LR and the plan's default) on null studies"

TARGET_RATE = 0.06
SIZES = (6, 12, 24)
SLOPES = (0.0, 0.6, 1.0)


def _model(design, crs: float, slope_sd: float):
    return model_from_parameters(design, {"pixel-only": 0.5, "crs": crs}, participant_sd=0.6,
                                 digit_sd=0.3, participant_slope_sd=slope_sd)


def _rates(design, model, participants: int, studies: int, replicates: int, seed: int):
    """(rejected by chi2, rejected by the default test) over the studies tested."""
    result = run_task(PowerTask(design, model, seed, (participants,), (design.repetitions,),
                                (0, studies)))
    chi2 = result.p_value[0, :, 0]
    if not design.bootstrapped(participants):
        tested = np.isfinite(chi2)
        return chi2[tested] < design.alpha, chi2[tested] < design.alpha
    Y = simulate_studies(model, seed, range(studies), participants,
                         design.repetitions)[:, :, -1].astype(float)
    trials = design.cell_trials(design.repetitions)
    full_design = primary_design(cells_frame(design, Y[0], trials), list(design.conditions),
                                 design.reference)
    terms = planned_power_terms(design)
    rows = [StudyRows.of(cells_frame(design, y, trials), full_design, terms,
                         trials="n_trials") for y in Y]
    start = np.r_[model.start(design), 0.6, 0.0, 0.6, 0.3, 0.0, 0.3]
    own = bootstrap_studies(rows[0], np.array([r.successes for r in rows]),
                            "condition[crs]", replicates, seed, start)
    tested = np.isfinite(own.pvalue) & np.isfinite(chi2)
    return chi2[tested] < design.alpha, own.pvalue[tested] < design.alpha


def _figure(name: str, rejected: np.ndarray, level: float, target: bool) -> Figure:
    k, n = int(rejected.sum()), len(rejected)
    ci = stats.binomtest(k, n).proportion_ci(0.95, method="exact")
    label = f"{name}: {k}/{n} (95 % CI {ci.low:.3f}-{ci.high:.3f})"
    if not target:
        return Figure(AREA, label, k / n, "rate", "nominal level", level)
    limit = TARGET_RATE * level / 0.05
    return Figure(AREA, label, k / n, "rate", "nominal level", level,
                  f"rate <= {limit:.3g} where the interval tells", ci.low <= limit)


def run(quick: bool) -> Iterator[Figure]:
    """Each cell's figures as they are measured: the full grid takes half an hour."""
    design = design_from_protocol("digit_identification")
    studies, replicates = (60 if quick else 1000), 20
    level = (np.ceil(design.alpha * (replicates + 1)) - 1) / (replicates + 1)
    sizes, slopes = ((6, 24), (0.6,)) if quick else (SIZES, SLOPES)
    for n in sizes:
        for slope in slopes:
            chi2, default = _rates(design, _model(design, 0.5, slope), n, studies, replicates,
                                   9000 + n)
            tag = f"N = {n}, slope SD {slope:g}"
            yield _figure(f"Type I, chi2 LR, {tag}", chi2, design.alpha, False)
            which = "bootstrap" if design.bootstrapped(n) else "chi2"
            yield _figure(f"Type I, default test ({which}), {tag}", default,
                          level if which == "bootstrap" else design.alpha, True)
    chi2, default = _rates(design, _model(design, 0.65, 0.6), 12, studies // 2, replicates,
                           9100)
    yield Figure(AREA, "power at CRS 65 % vs 50 %, N = 12, slope SD 0.6: default "
                       "(bootstrap) / chi2 LR", float(default.mean()), "power",
                 "chi2 LR", float(chi2.mean()))
