"""The maximal GLMM against R's lme4 and glmmTMB on the random-slopes parity corpus.

``tests/fixtures/lme4_slopes/``: ``corpus.csv`` (46 datasets, aggregated successes / trials per
participant x symbol x condition; made by ``make_corpus.py``: dry-runs of the shipped digit
and letter protocols at 4-60 participants, simulations with slope SDs 0-1.5 and correlations
-0.9 to 0.9, unbalanced designs, near-singular, singular and three-condition edge cases) and
``lme4_results.json`` (lme4 1.1-31 and glmmTMB 1.1.5 under R 4.2.2, made by ``fit_lme4.R``):
``correct ~ condition + (1 + condition | participant) + (1 + condition | digit)`` and the same
without condition, their log-likelihoods, fixed effects, SDs and correlations, the LR p. The
test needs no R. ``README.md`` beside the fixture lists where the three disagree
(``compare.py`` writes it).

What must hold: our log-likelihood is never below the best of lme4's and glmmTMB's by more
than 1e-6, full and reduced model; where one of them agrees with ours (neither higher by more
than ``AGREE``; the nearer of the two), the fixed effects within 1e-4, the SDs and
correlations within 1e-3 (a correlation only where both its SDs are above
``SD_FOR_CORRELATION``: below, it is
undetermined on a flat likelihood), and the LR p within 1 % relative where one reference
reaches both maxima within ``LR_AGREE``. Where lme4 reports less than our maximum, our
Laplace log-likelihood at lme4's own estimates equals lme4's number within ``LME4_PIRLS``
(lme4 evaluates its approximation with a looser inner tolerance, as on cbpp in
tests/test_glmm.py): the same objective, and lme4 stopped at a lower point of it (by up to
10 log-likelihood units on one reduced model here). glmmTMB reports no log-likelihood (NA)
where its Hessian is not positive definite; those fits are left out.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from crs_study.analysis.glmm import fit_glmm, lrt
from crs_study.analysis.glmm_terms import RandomTerm, sd_and_correlation
from crs_study.analysis.primary import design

HERE = Path(__file__).parent / "fixtures" / "lme4_slopes"
CORPUS = pd.read_csv(HERE / "corpus.csv", dtype={"participant": str, "dataset": str,
                                                 "digit": str})
META = json.loads((HERE / "datasets.json").read_text())
REFERENCE = json.loads((HERE / "lme4_results.json").read_text())["datasets"]
AGREE = 1e-5
LR_AGREE = 1e-4
LME4_PIRLS = 3e-4
SD_FOR_CORRELATION = 0.05
LEVELS = ("pixel-only", "crs", "crs2")


@functools.cache
def ours(name: str) -> dict:
    """Our maximal fits (no reduction: the model lme4 fits) and the LR test."""
    rows = CORPUS.loc[CORPUS["dataset"] == name].reset_index(drop=True)
    conditions = [c for c in LEVELS if c in set(rows["condition"])]
    full_design = design(rows, conditions, "pixel-only")
    columns = tuple(full_design.columns)
    terms = [RandomTerm("participant", columns), RandomTerm("digit", columns)]
    fit = functools.partial(fit_glmm, rows, "successes", random=terms,
                            random_design=full_design, trials="trials")
    full = fit(full_design)
    reduced = fit(full_design[["Intercept"]])
    return {"full": full, "reduced": reduced, "lr": lrt(full, reduced),
            "conditions": conditions}


def _outside(name: str, model: str) -> list[tuple[str, dict]]:
    """The outside fits of ``model`` (``full`` or ``reduced``) that exist: lme4, glmmTMB."""
    entry = REFERENCE[name]
    found = [("lme4", entry.get(model)), ("glmmTMB", (entry.get("glmmtmb") or {}).get(model))]
    return [(who, fit) for who, fit in found
            if fit and isinstance(fit["loglik"], int | float)]


def _agreeing(name: str, model: str, within: float = AGREE):
    """The outside fit nearest our maximum, if it is within ``within`` of it."""
    ours_ll = ours(name)[model].loglike
    near = sorted(_outside(name, model), key=lambda f: abs(f[1]["loglik"] - ours_ll))
    if near and abs(near[0][1]["loglik"] - ours_ll) <= within:
        return near[0]
    return None


def _their_covariances(fit: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """SDs and correlation matrix of each grouping factor, as VarCorr gives them."""
    out = {}
    for group, vc in fit["varcorr"].items():
        sd = np.atleast_1d(np.asarray(vc["sd"], dtype=float))
        corr = np.asarray(vc["corr"], dtype=float).reshape(len(sd), len(sd), order="F")
        out[group] = (sd, corr)
    return out


def _our_covariances(result) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {term.group: sd_and_correlation(sigma.to_numpy())
            for term, sigma in zip(result.terms, result.covariances().values(), strict=True)}


NAMES = sorted(REFERENCE)


def test_the_corpus_is_what_was_asked_for():
    kinds = pd.Series({name: meta["kind"] for name, meta in META.items()})
    assert len(META) >= 40 and set(NAMES) == set(META)
    assert (kinds == "dry-run").sum() >= 6 and (kinds == "simulated").sum() >= 20
    sizes = [meta["participants"] for meta in META.values()]
    assert min(sizes) <= 4 and max(sizes) >= 60
    slopes = {meta.get("slope_sd") for meta in META.values()} - {None}
    assert {0.0, 1.5} <= slopes
    protocols = {meta.get("protocol") for meta in META.values()}
    assert {"digit_identification", "letter_identification"} <= protocols


@pytest.mark.parametrize("name", NAMES)
def test_our_maximum_is_never_below_the_outside_fits(name):
    for model in ("full", "reduced"):
        found = _outside(name, model)
        assert found, f"{name}: no outside fit of the {model} model"
        best = max(fit["loglik"] for _, fit in found)
        assert ours(name)[model].loglike >= best - 1e-6, (name, model)


@pytest.mark.parametrize("name", NAMES)
def test_where_a_fit_agrees_the_estimates_agree(name):
    agreeing = _agreeing(name, "full")
    if agreeing is None:
        pytest.skip("neither outside fit reached our maximum (README.md beside the fixture)")
    who, fit = agreeing
    result = ours(name)["full"]
    theirs = np.array(list(fit["fixef"].values()), dtype=float)
    np.testing.assert_allclose(result.params.to_numpy(), theirs, atol=1e-4,
                               err_msg=f"{name}: fixed effects against {who}")
    mine = _our_covariances(result)
    for group, (sd, corr) in _their_covariances(fit).items():
        our_sd, our_corr = mine[group]
        np.testing.assert_allclose(our_sd, sd, atol=1e-3, err_msg=f"{name} {group} SDs ({who})")
        r = len(sd)
        for i in range(r):
            for j in range(i):
                if min(sd[i], sd[j], our_sd[i], our_sd[j]) > SD_FOR_CORRELATION:
                    assert our_corr[i, j] == pytest.approx(corr[i, j], abs=1e-3), (
                        name, group, who)


@pytest.mark.parametrize("name", NAMES)
def test_where_both_fits_agree_the_lr_p_agrees(name):
    entry = REFERENCE[name]
    for who in ("lme4", "glmmTMB"):
        fits = [dict(_outside(name, model)).get(who) for model in ("full", "reduced")]
        if all(f is not None for f in fits) and all(
                abs(f["loglik"] - ours(name)[m].loglike) <= LR_AGREE
                for f, m in zip(fits, ("full", "reduced"), strict=True)):
            break
    else:
        pytest.skip("no outside fit reached both maxima (README.md)")
    statistic = 2.0 * (fits[0]["loglik"] - fits[1]["loglik"])
    df = len(ours(name)["conditions"]) - 1
    theirs = stats.chi2.sf(max(statistic, 0.0), df)
    assert ours(name)["lr"].df == df == entry["lr"]["df"]
    assert ours(name)["lr"].pvalue == pytest.approx(theirs, rel=0.01, abs=1e-12), who


@pytest.mark.parametrize("name", NAMES)
def test_at_lme4s_estimates_our_likelihood_is_lme4s(name):
    for model in ("full", "reduced"):
        fit = REFERENCE[name].get(model)
        if not fit:
            continue
        result = ours(name)[model]
        problem = result._model.problem
        groups: dict[str, list[float]] = {}
        for label, value in zip(fit["theta_names"], fit["theta"], strict=True):
            groups.setdefault(label.split(".")[0], []).append(value)
        theta = np.r_[np.array(list(fit["fixef"].values()), dtype=float),
                      groups["participant"], groups["digit"]]
        at_theirs = problem.objective(theta, grad=False) + problem.user_constant
        assert at_theirs == pytest.approx(fit["loglik"], abs=LME4_PIRLS), (name, model)
        assert at_theirs <= result.loglike + 1e-9, (name, model)


def test_most_datasets_are_compared_in_full():
    agreeing = [n for n in NAMES if _agreeing(n, "full") is not None]
    assert len(agreeing) >= 0.8 * len(NAMES)
