"""Bench area ``glmm``: our ML fit against statsmodels' BinomialBayesMixedGLM and R's lme4.

Data: 40 participants x 400 trials (16,000 rows, two conditions, 200 trials each), random
intercept per participant (variance 0.5), condition effect 0.7 on the logit scale, seeded.
Times are medians of repeats; the baseline of each time is statsmodels' fit on the same data.

Targets (issue 12): the Laplace fit of 40 x 400 within 0.05 s (median); the whole primary test
(:func:`~crs_study.analysis.primary.primary_test`: the crossed full and reduced fits with
``(1 | participant) + (1 | digit)`` and every profile interval) at least 20x faster than
lme4's ``glmer`` of both models + ``confint(method = "profile")`` on the same 16,000 0/1 rows,
timed in the same run through ``Rscript`` whenever R with lme4 is installed (the figure says
so when it is not).
The estimate figures compare statsmodels' standard errors and variances with ours (ratio 1 =
agreement): its variational Bayes (``fit_vb``) standard errors ignore the posterior correlation
of fixed and random effects (mean-field) and come out too small, and its MAP fit collapses the
herd variance of lme4's cbpp example to about 0 (ours: lme4's 0.6423 standard deviation).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import numpy as np

from crs_study.analysis.glmm import fit_glmm
from crs_study.analysis.glmm_reference import load_cbpp
from crs_study.analysis.glmm_simulate import simulate_trials
from crs_study.analysis.primary import primary_test
from crs_study.benchmarks import Figure, median_seconds

AREA = "glmm"
DESCRIPTION = "mixed logistic regression (Laplace/AGQ) vs statsmodels BinomialBayesMixedGLM"

TARGET_SECONDS = 2.0
#: Median of the Laplace fit of 40 participants x 400 trials (issue 12).
TARGET_FIT_SECONDS = 0.05
#: lme4's glmer (both models) + confint(profile) over our whole primary test (issue 12).
TARGET_LME4_RATIO = 20.0

_LME4_SCRIPT = r"""
suppressPackageStartupMessages(library(lme4))
d <- read.csv(commandArgs(TRUE)[1])
d$participant <- factor(d$participant); d$digit <- factor(d$digit)
d$condition <- factor(d$condition, levels = c("c0", "c1"))
elapsed <- system.time({
  full <- glmer(correct ~ condition + (1 | participant) + (1 | digit), d, binomial)
  reduced <- glmer(correct ~ 1 + (1 | participant) + (1 | digit), d, binomial)
  ci <- suppressWarnings(confint(full, method = "profile"))
})[["elapsed"]]
cat(sprintf("elapsed %.6f\n", elapsed))
"""


def _statsmodels_model(df, formula: str, group: str):
    from statsmodels.genmod.bayes_mixed_glm import BinomialBayesMixedGLM

    return BinomialBayesMixedGLM.from_formula(formula, {group: f"0 + C({group})"}, df)


def _quiet(func):
    """Run ``func`` with statsmodels' convergence chatter silenced (a bench, not a test)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return func()


def run(quick: bool) -> list[Figure]:
    df = simulate_trials(np.random.default_rng(2026), 40, 200, [0.0, 0.7], 0.5)
    repeat = 3 if quick else 7
    slow_repeat = 1 if quick else 3

    def laplace():
        return fit_glmm(df, "correct", "condition", "participant")

    def agq():
        return fit_glmm(df, "correct", "condition", "participant", method="agq")

    def laplace_unpooled():
        return fit_glmm(df, "correct", "condition", "participant", aggregate=False)

    model = _statsmodels_model(df, "correct ~ condition", "participant")
    t_laplace = median_seconds(laplace, repeat=repeat)
    t_agq = median_seconds(agq, repeat=repeat)
    t_unpooled = median_seconds(laplace_unpooled, repeat=slow_repeat)
    fitted: dict[str, object] = {}  # the last result of each statsmodels fit, kept

    def vb_fit():
        fitted["vb"] = _quiet(model.fit_vb)

    def map_fit():
        fitted["map"] = _quiet(model.fit_map)

    t_vb = median_seconds(vb_fit, repeat=slow_repeat)
    t_map = median_seconds(map_fit, repeat=slow_repeat)
    ours, ours_agq = laplace(), agq()
    vb, map_ = fitted["vb"], fitted["map"]
    se_ml = ours.bse.to_numpy()
    sd_ml = float(np.sqrt(ours.variance_components.iloc[0]))

    figures = [
        Figure(AREA, "Laplace fit, 40 x 400 trials", t_laplace, "s", "statsmodels fit_vb",
               t_vb, f"value <= {TARGET_FIT_SECONDS:g} s", t_laplace <= TARGET_FIT_SECONDS),
        Figure(AREA, "AGQ(25) fit, 40 x 400 trials", t_agq, "s", "statsmodels fit_vb", t_vb,
               f"<= {TARGET_SECONDS:g} s", t_agq <= TARGET_SECONDS),
        Figure(AREA, "Laplace fit, 16,000 rows unpooled", t_unpooled, "s",
               "statsmodels fit_vb", t_vb, f"<= {TARGET_SECONDS:g} s",
               t_unpooled <= TARGET_SECONDS),
        Figure(AREA, "Laplace fit vs MAP", t_laplace, "s", "statsmodels fit_map", t_map),
        Figure(AREA, "condition effect: VB estimate / ML", float(vb.fe_mean[1]), "logit",
               "ML Laplace", float(ours.params.iloc[1])),
        Figure(AREA, "condition effect SE: VB / ML", float(vb.fe_sd[1]), "logit",
               "ML Laplace", float(se_ml[1])),
        Figure(AREA, "intercept SE: VB / ML", float(vb.fe_sd[0]), "logit", "ML Laplace",
               float(se_ml[0])),
        Figure(AREA, "condition effect SE: MAP / ML", float(map_.fe_sd[1]), "logit",
               "ML Laplace", float(se_ml[1])),
        Figure(AREA, "participant SD: VB / ML", float(np.exp(vb.vcp_mean[0])), "logit",
               "ML Laplace", sd_ml),
        Figure(AREA, "condition effect: AGQ(25) / Laplace", float(ours_agq.params.iloc[1]),
               "logit", "ML Laplace", float(ours.params.iloc[1])),
    ]
    figures += _primary_against_lme4(quick)
    figures += _cbpp_figures()
    return figures


def _primary_data():
    data = simulate_trials(np.random.default_rng(2026), 40, 200, [0.0, 0.7], 0.5,
                           digit_variance=0.1)
    return data


def _primary_against_lme4(quick: bool) -> list[Figure]:
    """Our primary test (two crossed fits, every profile interval) against lme4's, timed in
    the same run; without R and lme4 the lme4 figure says so instead of a time."""
    data = _primary_data()
    trials = data.rename(columns={"participant": "participant_id"})
    trials["correct"] = trials["correct"].astype(float)
    trials["condition"] = trials["condition"].astype(str)

    def ours():
        return primary_test(trials, ["c0", "c1"], "c0", ("participant", "digit"))

    t_ours = median_seconds(ours, repeat=1 if quick else 3)
    rscript = shutil.which("Rscript")
    lme4_seconds = None
    if rscript:
        with tempfile.TemporaryDirectory() as folder:
            csv = Path(folder) / "trials.csv"
            data.to_csv(csv, index=False)
            script = Path(folder) / "lme4.R"
            script.write_text(_LME4_SCRIPT)
            try:
                run = subprocess.run([rscript, str(script), str(csv)], capture_output=True,
                                     text=True, timeout=600, check=False)
            except (OSError, subprocess.TimeoutExpired):
                run = subprocess.CompletedProcess([], 1, "", "")
            for line in run.stdout.splitlines():
                if line.startswith("elapsed "):
                    lme4_seconds = float(line.split()[1])
    name = "primary test (2 crossed fits + profile CIs), 40 x 400"
    if lme4_seconds is None:
        return [Figure(AREA, f"{name}; lme4 not timed (no Rscript with lme4)", t_ours, "s",
                       "ours", t_ours)]
    return [Figure(AREA, name, t_ours, "s", "lme4 glmer x2 + confint(profile)", lme4_seconds,
                   f"lme4 / ours >= {TARGET_LME4_RATIO:g}",
                   lme4_seconds / t_ours >= TARGET_LME4_RATIO)]


def _cbpp_figures() -> list[Figure]:
    """lme4's cbpp example as 842 0/1 trials: statsmodels' MAP herd SD against ours."""
    cbpp = load_cbpp()
    rows = cbpp.loc[cbpp.index.repeat(cbpp["size"])].reset_index(drop=True)
    rows["sick"] = (rows.groupby(["herd", "period"]).cumcount() < rows["incidence"]).astype(int)
    ours = fit_glmm(rows, "sick", "C(period)", "herd")
    map_ = _quiet(_statsmodels_model(rows, "sick ~ C(period)", "herd").fit_map)
    return [Figure(AREA, "cbpp herd SD: statsmodels MAP / ML (lme4 0.6423)",
                   float(np.exp(map_.vcp_mean[0])), "logit", "ML Laplace",
                   float(np.sqrt(ours.variance_components.iloc[0])))]
