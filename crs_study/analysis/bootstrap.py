"""The parametric bootstrap of the likelihood-ratio test of a condition.

At the sample sizes tactile studies run (6-20 participants) the chi-square reference of a
GLMM's likelihood-ratio statistic is liberal (on simulated null studies of the shipped
protocol the maximal model's test rejected in about 6 % at 12 participants, nominal 5 %).
The parametric bootstrap replaces the chi-square by the statistic's own distribution under
the fitted null model (Halekoh & Hojsgaard 2014, "A Kenward-Roger approximation and
parametric bootstrap methods for tests in linear mixed models - the R package pbkrtest",
J. Stat. Softw. 59(9); Davison & Hinkley 1997, Bootstrap Methods and their Application,
sec. 4.2):

1. the model without the condition (the reduced fit) is the null: its fixed effects, its
   random terms and their covariances;
2. ``B`` datasets are drawn from it on the study's own rows (the same participants,
   symbols, conditions and trial counts; new random effects and new responses each time);
3. each is fitted with the model with and without the condition (the random part as the
   study's test used it), giving ``LR* = 2 (l_full* - l_reduced*)``;
4. ``p = (1 + #{LR* >= LR}) / (1 + B)``, with the Monte Carlo error of the count as its
   Clopper-Pearson interval.

When ``stop_after = h`` (the plan's ``bootstrap_stop_after``) the replicates are drawn in
order and the test stops as soon as ``h`` of them have reached the observed statistic, at
replicate ``L``: ``p = h / L`` (Besag & Clifford 1991, "Sequential Monte Carlo p-values",
Biometrika 78(2):301-304; a valid p-value, exactly as the fixed-B one). A study far from
significance is settled after a few dozen refits instead of ``B``; a small p still draws all
``B`` and is then the fixed-B formula above. The answer depends only on the replicates'
statistics in their order, never on how many were computed beyond the stopping point, so it
is the same on any backend.

The fits are the batched ones of :mod:`crs_study.analysis.glmm_batch` (hundreds of datasets in
one pass); a replicate they do not settle is refitted by ``fit_glmm`` itself, and one that
cannot be fitted at all is counted in ``failed`` and left out of ``B``, never silently.
Every replicate draws from a stream of its own, ``SeedSequence(seed, spawn_key=(b,))``, so
the answer is the same whether the replicates run in one process, in a pool or on a Dask
cluster, and however they are cut into units of work (``map``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats
from scipy.special import expit

from crs_study.analysis.glmm import GlmmFitError, fit_glmm
from crs_study.analysis.glmm_batch import BatchObjective, fit_batch
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows
from crs_study.analysis.glmm_terms import RandomTerm, ThetaLayout, loading

#: Replicates per unit of work: fixed, so the units (and every number) are the same on any
#: backend.
REPLICATES_PER_TASK = 50
#: Units of work in the first round of a sequential test (two cores' worth); each later round
#: doubles, so a test that stops early computes at most about twice what it needed.
FIRST_ROUND = 2


@dataclass(frozen=True)
class BootstrapLR:
    """The bootstrap test of one condition: ``statistic`` the observed LR, ``replicates``
    the B asked for, ``used`` those fitted up to where the test stopped (``failed`` the
    others drawn), ``exceed`` how many reached the observed statistic, ``pvalue`` and its
    Monte Carlo interval ``ci95``; ``stop_after`` the sequential rule's h (0: none) and
    ``stopped`` whether it ended the test before B."""

    statistic: float
    replicates: int
    used: int
    failed: int
    exceed: int
    pvalue: float
    ci95: tuple[float, float]
    seed: int
    reference_fits: int = 0
    stop_after: int = 0
    stopped: bool = False

    def describe(self) -> str:
        """The method in a few words, for the headline and the report."""
        if self.stopped:
            return (f"parametric bootstrap, stopped at {self.used} replicates once "
                    f"{self.exceed} reached the observed LR")
        return f"parametric bootstrap, B = {self.used}"

    def to_dict(self) -> dict:
        return {"method": "parametric bootstrap of the LR statistic", "statistic":
                self.statistic, "replicates": self.replicates, "used": self.used,
                "failed": self.failed, "exceed": self.exceed, "p_value": self.pvalue,
                "p_value_ci95": list(self.ci95), "seed": self.seed,
                "reference_fits": self.reference_fits, "stop_after": self.stop_after,
                "stopped_early": self.stopped}


@dataclass(frozen=True)
class StudyRows:
    """A study's binomial rows as the fits take them: one per participant x symbol x
    condition, the full fixed design ``X`` (named ``columns``), the trials and the
    successes, each term's levels and design."""

    X: np.ndarray
    columns: tuple[str, ...]
    trials: np.ndarray
    successes: np.ndarray
    terms: tuple[RandomTerm, ...]
    term_rows: tuple[TermRows, ...]

    @classmethod
    def of(cls, data: pd.DataFrame, design: pd.DataFrame, terms: Sequence[RandomTerm],
           response: str = "correct", trials: str | None = None) -> StudyRows:
        """Pool ``data`` (rows as ``design``'s) by the terms' groups and the design row."""
        keys = [t.group for t in terms] + list(design.columns)
        frame = pd.concat([data[[t.group for t in terms]].reset_index(drop=True),
                           design.reset_index(drop=True)], axis=1)
        frame = frame.loc[:, ~frame.columns.duplicated()]
        frame["_y"] = pd.to_numeric(data[response]).to_numpy(dtype=float)
        frame["_m"] = 1.0 if trials is None else pd.to_numeric(data[trials]).to_numpy(
            dtype=float)
        pooled = frame.groupby(list(dict.fromkeys(keys)), sort=True, observed=True)[
            ["_y", "_m"]].sum().reset_index()
        X = pooled[list(design.columns)].to_numpy(dtype=float)
        rows = []
        for term in terms:
            codes, levels = pd.factorize(pooled[term.group], sort=True)
            Z = pooled[list(term.columns)].to_numpy(dtype=float)
            rows.append(TermRows(codes.astype(np.intp), len(levels), Z))
        return cls(X, tuple(design.columns), pooled["_m"].to_numpy(), pooled["_y"].to_numpy(),
                   tuple(terms), tuple(rows))

    def objective(self, Y: np.ndarray, drop: str | None = None) -> BatchObjective:
        """The batch objective of responses ``Y`` (S, n), fixed column ``drop`` left out."""
        keep = [i for i, c in enumerate(self.columns) if c != drop]
        likelihood = LaplaceLikelihood(self.X[:, keep], self.trials, Y, list(self.term_rows))
        return BatchObjective(likelihood, ThetaLayout(len(keep), self.terms))

    def frame(self, y: np.ndarray) -> tuple[pd.DataFrame, pd.DataFrame]:
        """One replicate as a table ``fit_glmm`` takes, and its full design."""
        table = pd.DataFrame({t.group: r.codes for t, r in zip(self.terms, self.term_rows,
                                                               strict=True)})
        table["successes"], table["trials"] = y, self.trials
        design = pd.DataFrame(self.X, columns=list(self.columns))
        return table, design


@dataclass(frozen=True)
class BootstrapTask:
    """Replicates ``replicates[0] <= b < replicates[1]`` of one test: the rows, the null
    model's parameters (``null_theta``: fixed effects without ``dropped``, then theta), the
    observed fits' parameters as starts, and the seed."""

    rows: StudyRows
    dropped: str
    null_theta: np.ndarray
    full_start: np.ndarray
    seed: int
    replicates: tuple[int, int]
    full_curvature: np.ndarray | None = None      # the observed fits' negative Hessians,
    reduced_curvature: np.ndarray | None = None   # a start for the refits' Newton steps


@dataclass(frozen=True)
class BootstrapChunk:
    """What a task returns: each replicate's LR statistic (NaN where it failed) and how many
    were refitted by ``fit_glmm``."""

    replicates: tuple[int, int]
    statistics: np.ndarray
    reference_fits: int


def replicate_stream(seed: int, b: int) -> np.random.Generator:
    """Replicate ``b``'s random numbers: a stream of its own, whatever runs it."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(b,))))


def simulate_null(rows: StudyRows, dropped: str, null_theta: np.ndarray, seed: int,
                  replicates: range) -> np.ndarray:
    """Responses (B, n) drawn from the null model: new random effects for every level and
    binomial responses on the rows' trials (:func:`null_linear_predictors`)."""
    out = np.empty((len(replicates), len(rows.trials)))
    for i, (rng, eta) in enumerate(null_linear_predictors(rows, dropped, null_theta, seed,
                                                          replicates)):
        out[i] = rng.binomial(rows.trials.astype(np.int64), expit(eta))
    return out


def null_linear_predictors(rows: StudyRows, dropped: str, null_theta: np.ndarray,
                           seed: int, replicates: range):
    """Each replicate's stream and its linear predictor under the null model: ``X beta +
    sum_k Z_k T_k u_k``, ``u ~ N(0, I)`` drawn for every level of every term."""
    keep = [i for i, c in enumerate(rows.columns) if c != dropped]
    layout = ThetaLayout(len(keep), rows.terms)
    offset = rows.X[:, keep] @ null_theta[:len(keep)]
    for b in replicates:
        rng = replicate_stream(seed, b)
        eta = offset.copy()
        for term, term_rows, cut in zip(rows.terms, rows.term_rows, layout.slices,
                                        strict=True):
            T = loading(term, null_theta[cut])
            effects = rng.standard_normal((term_rows.levels, term.size)) @ T.T
            eta += np.einsum("na,na->n", term_rows.Z, effects[term_rows.codes])
        yield rng, eta


def run_bootstrap_task(task: BootstrapTask) -> BootstrapChunk:
    """The LR statistics of the task's replicates (the unit of work: a pure function)."""
    rows = task.rows
    replicates = range(*task.replicates)
    Y = simulate_null(rows, task.dropped, task.null_theta, task.seed, replicates)
    S = len(Y)

    def tiled(matrix):
        return None if matrix is None else np.tile(matrix, (S, 1, 1))

    drop_index = rows.columns.index(task.dropped)
    full_objective = rows.objective(Y)
    full = fit_batch(full_objective, _higher(full_objective, full_objective.moment_starts(),
                                             np.tile(task.full_start, (S, 1))),
                     tiled(task.full_curvature))
    reduced_objective = rows.objective(Y, task.dropped)
    reduced = fit_batch(reduced_objective, _higher(
        reduced_objective, np.delete(full.theta, drop_index, axis=1),
        np.tile(np.delete(task.full_start, drop_index), (S, 1))),
        tiled(task.reduced_curvature))
    statistics = 2.0 * (full.value - reduced.value)
    unsettled = np.flatnonzero(full.needs_reference | reduced.needs_reference)
    for s in unsettled:
        statistics[s] = _reference_statistic(rows, Y[s], task.dropped)
    return BootstrapChunk(task.replicates, np.maximum(statistics, 0.0), int(len(unsettled)))


def _higher(objective, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Per study, whichever of two starts has the higher likelihood. A replicate's own
    moments (or its full fit, for the reduced model) start it nearer its maximum on a study
    of many participants; on a few, their moments are noisy and the observed fit's
    estimates are the nearer start."""
    a = objective.evaluate(first, grad=False)[0]
    b = objective.evaluate(second, grad=False)[0]
    return np.where((np.nan_to_num(a, nan=-np.inf) >= np.nan_to_num(b, nan=-np.inf))[:, None],
                    first, second)


def _reference_statistic(rows: StudyRows, y: np.ndarray, dropped: str) -> float:
    """One replicate by ``fit_glmm`` (the supremum where a condition is separated); NaN
    when it cannot be fitted."""
    table, design = rows.frame(y)
    try:
        full = fit_glmm(table, "successes", design, random=list(rows.terms),
                        random_design=design, trials="trials")
        reduced = fit_glmm(table, "successes", design.drop(columns=dropped),
                           random=list(rows.terms), random_design=design, trials="trials")
    except GlmmFitError:
        return float("nan")
    values = [r.separation.sup_loglike if r.separation else r.loglike
              for r in (full, reduced)]
    return 2.0 * (values[0] - values[1])


def bootstrap_lr(rows: StudyRows, dropped: str, statistic: float, null_theta: np.ndarray,
                 full_start: np.ndarray, replicates: int, seed: int,
                 map_tasks: Callable | None = None,
                 curvatures: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
                 stop_after: int = 0) -> BootstrapLR:
    """The bootstrap test of fixed column ``dropped`` (module docstring).

    ``statistic`` is the observed LR, ``null_theta`` the reduced fit's parameters (its fixed
    effects, then lme4's theta of ``rows.terms``), ``full_start`` the full fit's (the refits'
    start; ``curvatures``, the full and reduced fits' negative Hessians, start their Newton
    steps). ``map_tasks(function, tasks)`` runs the units of work (default: here, in order).
    ``stop_after`` > 0: Besag and Clifford's sequential test, stopping once that many
    replicates reached ``statistic``.
    """
    if isinstance(replicates, bool) or not isinstance(replicates, int) or replicates < 1:
        raise ValueError(f"bootstrap replicates: expected a whole number >= 1, got "
                         f"{replicates!r}")
    if isinstance(stop_after, bool) or not isinstance(stop_after, int) or stop_after < 0:
        raise ValueError(f"bootstrap stop_after: expected a whole number >= 0, got "
                         f"{stop_after!r}")
    starts = list(range(0, replicates, REPLICATES_PER_TASK))
    tasks = [BootstrapTask(rows, dropped, np.asarray(null_theta, float),
                           np.asarray(full_start, float), seed,
                           (start, min(start + REPLICATES_PER_TASK, replicates)), *curvatures)
             for start in starts]
    run = map_tasks or _in_order
    chunks: list[BootstrapChunk] = []
    width = FIRST_ROUND if stop_after else len(tasks)
    while len(chunks) < len(tasks):
        chunks += run(run_bootstrap_task, tasks[len(chunks):len(chunks) + width])
        chunks.sort(key=lambda c: c.replicates[0])   # whatever order the map returned
        width *= 2
        values = np.concatenate([c.statistics for c in chunks])
        outcome = sequential_count(values, statistic, stop_after)
        if outcome is not None:
            break
    else:
        outcome = sequential_count(values, statistic, 0)
    drawn, used, exceed, stopped = outcome
    ci = stats.binomtest(exceed, used).proportion_ci(0.95, method="exact") if used else None
    pvalue = exceed / used if stopped else (1.0 + exceed) / (1.0 + used)
    return BootstrapLR(float(statistic), replicates, used, drawn - used, exceed, pvalue,
                       (float("nan"), float("nan")) if ci is None else
                       (float(ci.low), float(ci.high)), seed,
                       sum(c.reference_fits for c in chunks), stop_after, stopped)


def sequential_count(values: np.ndarray, statistic: float,
                     stop_after: int) -> tuple[int, int, int, bool] | None:
    """``(drawn, used, exceed, stopped)`` of replicate statistics ``values`` (NaN: a failed
    refit) in their order: with ``stop_after`` > 0, up to the replicate at which that many
    have reached ``statistic`` (None while fewer have); with 0, all of them. A difference
    below the optimiser's precision is a tie with the observed statistic."""
    fitted = np.isfinite(values)
    reached = fitted & (np.nan_to_num(values, nan=-np.inf) >= statistic - 1e-6)
    if stop_after:
        count = np.cumsum(reached)
        hits = np.flatnonzero(count >= stop_after)
        if not len(hits):
            return None
        drawn = int(hits[0]) + 1
        return drawn, int(fitted[:drawn].sum()), stop_after, True
    return len(values), int(fitted.sum()), int(reached.sum()), False


def _in_order(function, tasks):
    return [function(t) for t in tasks]


@dataclass(frozen=True)
class StudiesBootstrap:
    """The bootstrap tests of many studies of one design: per study the observed LR
    ``statistic``, the ``pvalue`` and the replicates ``used`` (NaN and 0 where the study's own
    fits were not settled by the batched fits)."""

    statistic: np.ndarray
    pvalue: np.ndarray
    used: np.ndarray


def bootstrap_studies(rows: StudyRows, Y: np.ndarray, dropped: str, replicates: int,
                      seed: int, start: np.ndarray) -> StudiesBootstrap:
    """The parametric bootstrap test of fixed column ``dropped`` for each of the studies
    ``Y`` (S, n) on the same rows, all fits batched: each study's full and reduced fit from
    ``start``, then ``replicates`` datasets from each reduced fit, refitted together. What
    ``analyze`` does to one study (:func:`bootstrap_lr`), for a simulation of its level;
    replicate ``b`` of study ``s`` draws from ``replicate_stream(seed + s, b)``. A replicate
    the batch does not settle is refitted by ``fit_glmm``; a study whose own fits it does
    not settle is left out (NaN): the counts say so."""
    S = len(Y)
    drop = rows.columns.index(dropped)
    full = fit_batch(rows.objective(Y), np.tile(start, (S, 1)))
    reduced = fit_batch(rows.objective(Y, dropped), np.delete(full.theta, drop, axis=1))
    statistic = np.maximum(2.0 * (full.value - reduced.value), 0.0)
    settled = ~(full.needs_reference | reduced.needs_reference)
    statistic = np.where(settled, statistic, np.nan)
    studies = np.flatnonzero(settled)
    draws = np.concatenate([simulate_null(rows, dropped, reduced.theta[s], seed + int(s),
                                          range(replicates)) for s in studies])
    owner = np.repeat(studies, replicates)
    # each replicate starts from its study's fits, their curvature included
    star_full = fit_batch(rows.objective(draws), full.theta[owner], full.curvature[owner])
    star_reduced = fit_batch(rows.objective(draws, dropped), reduced.theta[owner],
                             reduced.curvature[owner])
    star = 2.0 * (star_full.value - star_reduced.value)
    for b in np.flatnonzero(star_full.needs_reference | star_reduced.needs_reference):
        star[b] = _reference_statistic(rows, draws[b], dropped)
    ok = np.isfinite(star)
    pvalue = np.full(S, np.nan)
    used = np.zeros(S, dtype=int)
    for s in studies:
        mine = (owner == s) & ok
        used[s] = int(mine.sum())
        exceed = int(np.sum(np.maximum(star[mine], 0.0) >= statistic[s] - 1e-6))
        pvalue[s] = (1.0 + exceed) / (1.0 + used[s])
    return StudiesBootstrap(statistic, pvalue, used)
