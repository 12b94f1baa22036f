"""The primary test's Type I error, and power testing what analyze tests.

Outside reference: the definition of a test's level, checked by simulation. Null studies of
the shipped protocol's design (no condition effect for the typical participant; participant
intercept SD 0.6, a by-participant condition slope of SD 0.6 or 1.0, symbol intercept SD 0.3)
are drawn by the power simulation's generator and tested as ``analyze`` tests them: the
plan's maximal model and, below ``bootstrap_below`` participants, the parametric bootstrap of
the LR statistic (Halekoh & Hojsgaard 2014, J. Stat. Softw. 59(9)); from there on, chi2. The
rejection rate must be within Monte Carlo error of the level or below: the one-sided binomial
test of "rate > level" at 0.01 must not reject. On the same studies random intercepts alone
reject far more often (Barr et al. 2013, J. Mem. Lang. 68:255, measured the same with lme4).

The bootstrap's p ``(1 + k) / (1 + B)`` read as ``p < alpha`` has the level
``ceil(alpha (B + 1)) - 1`` over ``B + 1`` when the bootstrap is exact (Davison & Hinkley
1997, sec. 4.2): with ``B = 20`` and alpha 0.05, 1 / 21 = 0.0476, which checks the
procedure's calibration at a fiftieth of the default's cost (``B = 1000``: ``B`` adds Monte
Carlo error to a study's p, not bias); ``crs-study bench validity`` measures it on 1000
studies a cell.

``power`` refers a study's LR statistic, where the plan's test is the bootstrap, to the
statistics of as many null studies of its design point (drawn once from the generating
model, not per study from its own fit); with an effect and without, its decisions agree with
each study's own bootstrap within Monte Carlo error.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from crs_study.analysis.bootstrap import StudyRows, bootstrap_studies
from crs_study.analysis.primary import design as primary_design
from crs_study.power_analysis import design_from_protocol, model_from_parameters
from crs_study.power_analysis.result import PowerResult, merge
from crs_study.power_analysis.simulate import simulate_studies
from crs_study.power_analysis.study import (
    PowerTask,
    calibrated_pvalues,
    cells_frame,
    lr_statistic,
    planned_power_terms,
    run_task,
)

B = 20
LEVEL = 1 / (B + 1)          # p < 0.05 with B = 20: no replicate at or above the statistic


@pytest.fixture(scope="module")
def design():
    design = design_from_protocol("digit_identification")
    assert (design.structure, design.singular_fit, design.p_value) == (
        "maximal", "keep", "auto")                              # the shipped plan's test
    return design


def _model(design, crs: float, slope_sd: float):
    return model_from_parameters(design, {"pixel-only": 0.5, "crs": crs}, participant_sd=0.6,
                                 digit_sd=0.3, participant_slope_sd=slope_sd)


def _own_bootstraps(design, model, participants: int, studies: int, seed: int):
    """Each study's own bootstrap p (as analyze's, B replicates), all fits batched."""
    Y = simulate_studies(model, seed, range(studies), participants,
                         design.repetitions)[:, :, -1].astype(float)
    trials = design.cell_trials(design.repetitions)
    first = cells_frame(design, Y[0], trials)
    full_design = primary_design(first, list(design.conditions), design.reference)
    terms = planned_power_terms(design)
    rows = [StudyRows.of(cells_frame(design, y, trials), full_design, terms,
                         trials="n_trials") for y in Y]
    start = np.r_[model.start(design), 0.6, 0.0, 0.6, 0.3, 0.0, 0.3]
    return bootstrap_studies(rows[0], np.array([r.successes for r in rows]),
                             "condition[crs]", B, seed, start)


def calibrated_pvalues_each(statistic: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Study ``s``'s calibrated p against its own row of reference statistics."""
    return np.array([calibrated_pvalues(statistic[s:s + 1], reference[s])[0]
                     for s in range(len(statistic))])


def _not_above(rejected: np.ndarray, level: float) -> bool:
    k, n = int(rejected.sum()), len(rejected)
    return stats.binomtest(k, n, level, alternative="greater").pvalue > 0.01


def test_below_twenty_participants_the_bootstrap_holds_its_level(design):
    """24 null studies of 6 participants, each with its own bootstrap: the one-sided test at
    0.01 fails from 5 rejections (21 %), so a rate of 30 % is caught with probability 0.89
    and one of half, as random intercepts alone reject, with probability 0.999 (the
    bootstrap of the intercepts-only null model rejected 9 of these 24); ``crs-study bench
    validity`` measures the rate itself on 1000 studies a cell."""
    assert design.bootstrapped(6)
    model = _model(design, 0.5, 0.6)
    own = _own_bootstraps(design, model, 6, 24, 606)
    tested = np.isfinite(own.pvalue)
    assert tested.sum() >= 22 and (own.used[tested] >= B - 2).all()
    rejected = own.pvalue[tested] < design.alpha
    assert _not_above(rejected, LEVEL), rejected.mean()


@pytest.mark.parametrize("structure", ["maximal", "intercepts"])
def test_with_twenty_four_the_chi2_lr_test_holds_the_level_intercepts_do_not(design,
                                                                             structure):
    assert not design.bootstrapped(24)
    tested = dataclasses.replace(design, structure=structure)
    result = run_task(PowerTask(tested, _model(design, 0.5, 1.0), 424, (24,),
                                (design.repetitions,), (0, 200)))
    rejected = result.p_value[0, :, 0] < design.alpha
    if structure == "maximal":
        assert _not_above(rejected, design.alpha), rejected.mean()
    else:
        assert rejected.mean() > 4 * design.alpha, rejected.mean()


@pytest.mark.slow
@pytest.mark.parametrize(("crs", "seed"), [pytest.param(0.7, 707, id="effect"),
                                         pytest.param(0.5, 505, id="null")])
def test_power_decides_as_each_studys_own_bootstrap_would(design, crs, seed):
    """The same 24 studies of 6 participants, with an effect and without (``--effect-scale
    0``): power's reference (24 null studies of the point, drawn once from the generating
    model) and each study's own bootstrap (B = 20 datasets from its own null fit) reject
    alike: McNemar's exact test on the paired decisions, p > 0.01. Power's side is read at
    the bootstrap's resolution (a study rejects when none of 20 of the null studies, drawn
    for it at random, reaches its LR), so the decisions differ only by where the reference
    comes from. Without an effect neither rejects above its level."""
    model, studies = _model(design, crs, 0.6), 24
    result = run_task(PowerTask(design, model, seed, (6,), (design.repetitions,),
                                (0, studies)))
    raw = merge([result])
    statistic = lr_statistic(raw, 0, 0)
    null = raw["null_statistic"][0, :, 0]
    null = null[np.isfinite(null)]
    rng = np.random.default_rng(seed)
    reference = np.array([rng.choice(null, B, replace=False) for _ in range(studies)])
    own = _own_bootstraps(design, model, 6, studies, seed)
    both = np.isfinite(statistic) & np.isfinite(own.pvalue)
    power_rejects = calibrated_pvalues_each(statistic, reference)[both] < design.alpha
    own_rejects = own.pvalue[both] < design.alpha
    discordant = [int((power_rejects & ~own_rejects).sum()),
                  int((~power_rejects & own_rejects).sum())]
    if sum(discordant):
        assert stats.binomtest(discordant[0], sum(discordant)).pvalue > 0.01, discordant
    if crs == 0.5:
        assert _not_above(power_rejects, LEVEL) and _not_above(own_rejects, LEVEL)
    else:
        assert power_rejects.mean() > LEVEL and own_rejects.mean() > LEVEL
    # the p power reports: against all 24 null studies
    power = PowerResult(design, model, ((6, design.repetitions),), raw)
    calibrated = calibrated_pvalues(statistic, raw["null_statistic"][0, :, 0])
    np.testing.assert_array_equal(power.pvalues()[0, both, 0], calibrated[both])
    assert power.to_frame()["test"].iloc[0].startswith("LR, bootstrap-calibrated")
