"""The unit of work: a block of simulated studies at every point of the curve.

:func:`run_task` is a pure function of a :class:`PowerTask` (design, model, seed, the points
and a range of study numbers) to a small :class:`TaskResult`; the backends map it over a
process pool or a Dask cluster by the same code (:mod:`crs_study.power_analysis.backends`).

Each simulated study is tested as ``analyze`` tests a dataset
(:func:`crs_study.analysis.primary.primary_test`): the plan's random structure (maximal by
default: ``correct ~ condition + (1 + condition | participant) + (1 + condition |
symbol)``), reduced by the plan's rule where a fit fails or is singular, and per
non-reference condition the model without it; the likelihood-ratio statistic of each
comparison; a separated condition tested at the supremum; a reduced model that cannot be
fitted: the Wald p; a full model that cannot be fitted: Fisher's exact test on the pooled
table. A study's outcome records which of these it was (``KINDS``).

Where the plan's p is the parametric bootstrap (``design.bootstrapped(n)``), a study's LR
statistic is referred to the LR statistics of as many null studies of its point, drawn from
the generating model without the comparison's effect (:func:`calibrated_pvalues`): the
bootstrap's reference distribution computed once per point, not per study.

Two paths give the fits. The batched path (:func:`crs_study.analysis.glmm_batch.fit_batch`)
fits all studies of a point at once to the maximum ``fit_glmm`` finds (its boundary rule
included), each model of each study from where ``fit_glmm`` starts it, the moment start
of its own data (:mod:`crs_study.analysis.glmm_start`); a study it does not settle (a condition at
0 % or 100 %, where ``fit_glmm`` tests at the supremum; a Newton iteration that stalls; a
plan with adaptive quadrature) goes the reference path:
:func:`crs_study.analysis.primary.fit_primary` itself on the study's cells. The chi2 p is
:func:`crs_study.analysis.glmm.lrt`'s: ``2 (l_full - l_reduced)``, differences below 1e-6
taken as 0, against chi2(1), floored at the smallest positive float.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from crs_study.analysis.accuracy import floor_p
from crs_study.analysis.glmm import GlmmFitError
from crs_study.analysis.glmm_batch import fit_batch, study_fit
from crs_study.analysis.glmm_result import P_FLOOR
from crs_study.analysis.glmm_terms import RandomTerm
from crs_study.analysis.primary import fisher_comparisons, fit_primary
from crs_study.analysis.structure import reduce_terms, reduction_reasons
from crs_study.power_analysis.cells import (
    PointCells,
    curvature_shape,
    fitted_covariances,
    planned_power_terms,
    recorded,
    theta_start,
)
from crs_study.power_analysis.design import PowerDesign
from crs_study.power_analysis.model import GenerativeModel, fitted_covariance
from crs_study.power_analysis.simulate import cells_frame, simulate_studies

#: How each comparison of a study was tested (index = the code stored in ``kind``).
KINDS = ("lr", "separated", "wald", "fisher", "none")
LR, SEPARATED, WALD, FISHER, NONE = range(len(KINDS))


@dataclass(frozen=True)
class PowerTask:
    """Studies ``studies[0] <= s < studies[1]`` at every (participants, repetitions) point."""

    design: PowerDesign
    model: GenerativeModel
    seed: int
    participants: tuple[int, ...]
    repetitions: tuple[int, ...]
    studies: tuple[int, int]

    @property
    def points(self) -> list[tuple[int, int]]:
        return [(n, r) for r in self.repetitions for n in self.participants]

    @property
    def n_studies(self) -> int:
        return self.studies[1] - self.studies[0]


@dataclass(frozen=True)
class TaskResult:
    """Per point (axis 0) and study (axis 1): ``p_value`` and ``kind`` per comparison
    (axis 2), ``log_odds`` the full model's estimate per comparison (NaN when none),
    ``theta`` its parameters (fixed effects, then the SDs), ``converged``, ``boundary`` (a
    variance estimated at 0), ``reference`` (fitted by ``fit_glmm``), ``loglike`` the full
    model's maximum and ``loglike_reduced`` each reduced model's (the supremum where
    separated; binomial constants of the cells included, as lme4's ``logLik`` of
    ``cbind(successes, failures)``); ``seconds`` of CPU."""

    studies: tuple[int, int]
    p_value: np.ndarray
    kind: np.ndarray
    log_odds: np.ndarray
    theta: np.ndarray
    converged: np.ndarray
    boundary: np.ndarray
    reduced: np.ndarray
    reference: np.ndarray
    loglike: np.ndarray
    loglike_reduced: np.ndarray
    seconds: float
    null_statistic: np.ndarray | None = None


def run_task(task: PowerTask) -> TaskResult:
    """Simulate the task's studies and test each at every point (module docstring); where
    the plan's test is the parametric bootstrap, the same number of null studies too, whose
    LR statistics calibrate the test (:func:`calibrated_pvalues`)."""
    start = time.process_time()
    out, *nulls = _points(task, [(task.model, task.seed, True)] + _null_draws(task))
    out["null_statistic"] = _null_statistic(task, nulls)
    return TaskResult(task.studies, seconds=time.process_time() - start, **out)


def _null_draws(task: PowerTask) -> list[tuple[GenerativeModel, int, bool]]:
    """What the null studies of comparison ``j`` are drawn from: ``model.without_effect(j)``
    with :func:`null_seed`, at the points where the plan's test is the bootstrap."""
    return [(task.model.without_effect(j), null_seed(task.seed, j), False)
            for j in range(len(task.design.comparisons))]


def _null_statistic(task: PowerTask, nulls: list[dict[str, np.ndarray]]) -> np.ndarray:
    """(point, study, comparison): the LR statistics of the null studies (NaN where the
    plan's test is not the bootstrap)."""
    statistic = np.full((len(task.points), task.n_studies, len(nulls)), np.nan)
    for i, (n, _) in enumerate(task.points):
        for j, null in enumerate(nulls if task.design.bootstrapped(n) else ()):
            statistic[i, :, j] = lr_statistic(null, i, j)
    return statistic


def null_statistics(task: PowerTask) -> np.ndarray:
    """(point, study, comparison): the LR statistics of the task's null studies where the
    plan's test is the bootstrap (NaN elsewhere); null study ``s`` of comparison ``j`` is
    drawn from ``model.without_effect(j)`` with :func:`null_seed`."""
    return _null_statistic(task, _points(task, _null_draws(task)))


def run_null_task(task: PowerTask) -> TaskResult:
    """Only the null studies of a task (mode 3 calibrates its dry-runs with them)."""
    start = time.process_time()
    shape = (len(task.points), task.n_studies)
    out = outcomes(task.design, shape)
    out["null_statistic"] = null_statistics(task)
    return TaskResult(task.studies, seconds=time.process_time() - start, **out)


def _points(task: PowerTask, draws: list[tuple[GenerativeModel, int, bool]]
            ) -> list[dict[str, np.ndarray]]:
    """The outcome arrays of the task's studies drawn from each ``(model, seed, every)``
    at each point (``every`` False: only where the plan's test is the bootstrap). The
    draws' studies of a point are fitted as one batch (fewer array operations, each on
    more studies): a study's fits depend on its own data alone."""
    design, studies = task.design, range(*task.studies)
    S = len(studies)
    outs = [outcomes(design, (len(task.points), S)) for _ in draws]
    wanted = [[every or design.bootstrapped(n) for n, _ in task.points]
              for _, _, every in draws]
    cumulative = {}
    for k, (model, seed, _) in enumerate(draws):
        points = [p for p, w in zip(task.points, wanted[k], strict=True) if w]
        if points:
            cumulative[k] = simulate_studies(model, seed, studies, max(n for n, _ in points),
                                             max(r for _, r in points))
    previous: dict[tuple[int, int], tuple[int, np.ndarray]] = {}   # (draw, reps): (N, curv.)
    for i, (n, r) in enumerate(task.points):
        here = [k for k in cumulative if wanted[k][i]]
        if not here:
            continue
        Y = np.concatenate([cumulative[k][:, :n, r - 1] for k in here]).astype(float)
        # The full model's curvature at the previous N of the same study, scaled by the
        # participants (the information grows with them): a per-study start for the fits'
        # Hessian, so a study's answer still depends on nothing but its own data (zeros,
        # where there is none, are a start the fits replace by differences).
        last = [previous.get((k, r)) for k in here]
        curvature = None if all(x is None for x in last) else np.concatenate(
            [np.zeros((S,) + curvature_shape(design)) if x is None else x[1] * (n / x[0])
             for x in last])
        point = decide_studies(design, Y, r, curvature)
        for b, k in enumerate(here):
            part = slice(b * S, (b + 1) * S)
            previous[(k, r)] = (n, point["curvature"][part])
            for key, value in outs[k].items():
                value[i] = point[key][part]
    return outs


def null_seed(seed: int, comparison: int) -> int:
    """The seed of the null studies that calibrate comparison ``comparison``: a stream
    apart from the studies' own, the same on any backend."""
    return int(np.random.SeedSequence([seed, 31, comparison]).generate_state(1)[0])


def lr_statistic(out: dict[str, np.ndarray], point: int, comparison: int) -> np.ndarray:
    """``2 (l_full - l_reduced)`` of every study of a point tested by its likelihood ratio
    (NaN where the test was another one: separation, Wald, Fisher)."""
    statistic = 2.0 * (out["loglike"][point] - out["loglike_reduced"][point, :, comparison])
    lr = out["kind"][point, :, comparison] == LR
    return np.where(lr, np.maximum(statistic, 0.0), np.nan)


def calibrated_pvalues(statistic: np.ndarray, null: np.ndarray) -> np.ndarray:
    """Each study's p against the null studies' LR statistics of its point: ``(1 + #{null
    >= LR}) / (1 + M)``, ``M`` the null studies fitted (the bootstrap's p, its null drawn
    once per point from the generating model rather than per study from its own fit)."""
    null = np.sort(null[np.isfinite(null)])
    M = len(null)
    exceed = M - np.searchsorted(null, statistic - 1e-6, side="left")
    return np.where(np.isfinite(statistic), (1.0 + exceed) / (1.0 + M), np.nan)


def recorded_parameters(design: PowerDesign) -> list[str]:
    """The estimates kept per study (``theta``): the fixed effects, then the SD of each
    random effect (0 where the model fitted has none: a slope dropped by the plan's rule)."""
    slopes = [f"[{c}]" for c in design.comparisons]
    names = (["Intercept"] + [f"condition[{c}]" for c in design.comparisons]
             + ["participant_sd"] + [f"participant_slope_sd{c}" for c in slopes])
    if design.symbol_effect:
        names += [design.symbol_sd_name] + [f"{design.symbol_column}_slope_sd{c}"
                                            for c in slopes]
    return names


def outcomes(design: PowerDesign, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Empty outcome arrays of :class:`TaskResult`'s fields for ``shape`` (points, studies,
    or studies, or () for one study): no test, NaN numbers, flags off."""
    K = len(design.comparisons)
    n_params = len(recorded_parameters(design))
    return {"p_value": np.full(shape + (K,), np.nan),
            "kind": np.full(shape + (K,), NONE, dtype=np.int8),
            "log_odds": np.full(shape + (K,), np.nan),
            "theta": np.full(shape + (n_params,), np.nan),
            "converged": np.zeros(shape, dtype=bool), "boundary": np.zeros(shape, dtype=bool),
            "reduced": np.zeros(shape, dtype=bool),
            "reference": np.zeros(shape, dtype=bool), "loglike": np.full(shape, np.nan),
            "loglike_reduced": np.full(shape + (K,), np.nan)}


def decide_studies(design: PowerDesign, Y: np.ndarray, repetitions: int,
                   curvature: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Test studies ``Y`` (S, P, D, C) of one point as ``analyze`` would; arrays as in
    :class:`TaskResult` (without the point axis), and ``curvature`` (S, n, n) the planned
    model's last negative-Hessian approximation (zeros where none), which a next point may
    pass back as its start. Every fit starts from its study's own data, as ``fit_glmm``
    starts (the moment start of :mod:`crs_study.analysis.glmm_start`), never from the
    generating model.

    The plan's model first, for every study at once; a study whose fit calls for the plan's
    reduction rule (:func:`~crs_study.analysis.structure.reduction_reasons`) moves on to the
    next model the rule gives it (:func:`~crs_study.analysis.structure.reduce_terms`), with
    the other studies bound for that model; then, per model finally used, the models without
    each condition. A study the batched fits do not settle goes the reference path.
    """
    S, P, D, C = Y.shape
    K = len(design.comparisons)
    trials = design.cell_trials(repetitions)
    cells = PointCells.of(design, P, D, trials)
    planned = planned_power_terms(design)
    spec = design.random_spec
    out = outcomes(design, (S,))
    out["curvature"] = np.zeros((S,) + curvature_shape(design))
    per_condition = Y.sum(axis=(1, 2))                                  # (S, C)
    possible = trials.sum(axis=0) * Y.shape[1]
    separated = ((per_condition == 0) | (per_condition == possible)).any(axis=1)
    fast = np.flatnonzero(~separated) if design.method == "laplace" else np.arange(0)
    settled = np.zeros(S, dtype=bool)
    queue: list[tuple[tuple[RandomTerm, ...], list[int], list[np.ndarray] | None]] = [
        (planned, list(fast), None)]
    steps_taken: dict[int, set[str]] = {int(s): set() for s in fast}
    final: dict[tuple[RandomTerm, ...], list[tuple[int, np.ndarray, float, bool]]] = {}
    while queue:
        terms, index, starts = queue.pop(0)
        if not index:
            continue
        index_array = np.array(index)
        objective = cells.objective(terms, Y[index_array])
        warm = (curvature[index_array] if terms == planned and curvature is not None
                else None)
        if starts is None:           # the plan's model: each study from its moment start
            starts = objective.moment_starts()
        fit = fit_batch(objective, np.array(starts), warm)
        if terms == planned:
            out["curvature"][index_array] = fit.curvature
        following: dict[tuple[RandomTerm, ...], tuple[list[int], list[np.ndarray]]] = {}
        for j, s in enumerate(index):
            if fit.needs_reference[j]:
                continue
            summary = study_fit(fit, objective, j)
            step = None
            if reduction_reasons(summary, spec.singular_fit == "reduce"):
                step = reduce_terms(spec, terms, summary, steps_taken[s])
            if step is None:
                final.setdefault(terms, []).append(
                    (s, fit.theta[j], float(fit.value[j]), bool(fit.at_zero[j].any())))
                continue
            new_terms = tuple(step[0])
            fitted = fitted_covariances(objective, fit.theta[j], cells.columns)
            group = following.setdefault(new_terms, ([], []))
            group[0].append(s)
            group[1].append(theta_start(new_terms, fit.theta[j, :C], fitted, cells.columns))
            out["reduced"][s] = True
        queue += [(t, i, st) for t, (i, st) in following.items()]
    constant = binomial_constant(Y, trials)
    names = recorded_parameters(design)
    for terms, studies in final.items():
        index = np.array([s for s, *_ in studies])
        theta = np.array([t for _, t, _, _ in studies])
        value = np.array([v for _, _, v, _ in studies])
        needs = np.zeros(len(index), dtype=bool)
        reduced_values = np.empty((len(index), K))
        objective = cells.objective(terms, Y[index])
        for j in range(K):
            # from the study's moment start, where fit_glmm starts the reduced model: the
            # model without an effect can have several maxima (the effect taken up by the
            # participants' or the symbols' slopes), and a start carried over from the full
            # model's maximum ends on another peak more often than fit_glmm does
            dropped = cells.objective(terms, Y[index], drop=j + 1)
            reduced = fit_batch(dropped, dropped.moment_starts())
            needs |= reduced.needs_reference
            reduced_values[:, j] = reduced.value
        keep = ~needs
        ok = index[keep]
        statistic = 2.0 * (value[:, None] - reduced_values)
        out["loglike"][ok] = (value + constant[index])[keep]
        out["loglike_reduced"][ok] = (reduced_values + constant[index][:, None])[keep]
        out["p_value"][ok] = lr_pvalue(statistic[keep])
        out["kind"][ok] = LR
        out["log_odds"][ok] = theta[keep, 1:K + 1]
        out["theta"][ok] = [recorded(objective, t, names, design) for t in theta[keep]]
        out["converged"][ok] = True
        out["boundary"][ok] = np.array([b for *_, b in studies])[keep]
        settled[ok] = True
    for s in np.flatnonzero(~settled):
        outcome = reference_test(design, Y[s], trials)
        for key, value in outcome.items():
            out[key][s] = value
        out["reference"][s] = True
    return out


def binomial_constant(Y: np.ndarray, trials: np.ndarray) -> np.ndarray:
    """``sum log C(m, y)`` over each study's cells (what ``fit_glmm`` adds to the kernel)."""
    from scipy.special import gammaln

    m = np.broadcast_to(trials, Y.shape[1:])
    return (gammaln(m + 1) - gammaln(Y + 1) - gammaln(m - Y + 1)).sum(axis=(1, 2, 3))


def lr_pvalue(statistic: np.ndarray) -> np.ndarray:
    """The p of :func:`crs_study.analysis.glmm.lrt` for one fixed effect and no variance
    dropped: statistic below 1e-6 (optimiser precision) is 0, chi2(1), floored."""
    statistic = np.where(statistic > 1e-6, statistic, 0.0)
    return np.maximum(stats.chi2.sf(statistic, 1), P_FLOOR)


def reference_test(design: PowerDesign, Y: np.ndarray, trials: np.ndarray) -> dict:
    """One study tested by :func:`~crs_study.analysis.primary.fit_primary` on its cells."""
    return decide_trials(design, cells_frame(design, Y, trials))


def decide_trials(design: PowerDesign, trials: pd.DataFrame) -> dict:
    """The primary test of a trial table (0/1 rows, or cells with ``n_trials``) as
    :func:`~crs_study.analysis.primary.primary_test` decides it, without the profiles."""

    out = outcomes(design, ())
    del out["reference"]
    conditions = list(design.conditions)
    try:
        fits = fit_primary(trials, conditions, design.reference, design.random_effects,
                           design.method, design.n_quadrature, **design.model_options())
    except GlmmFitError:
        # primary_test's fallback: Fisher's exact test on the pooled 2 x 2 tables; the
        # function is primary.py's own, so the p is the one analyze reports
        data = trials
        if "n_trials" in trials.columns:      # 0/1 rows for the pooled table
            data = _expand(trials)
        for j, comparison in enumerate(fisher_comparisons(data, conditions,
                                                           design.reference, design.alpha)):
            out["p_value"][j], out["kind"][j] = comparison.p_value, FISHER
            out["log_odds"][j] = comparison.log_odds
        return out
    full = fits.full
    columns = ["Intercept"] + [f"condition[{c}]" for c in design.comparisons]
    theta = [float(full.params.get(c, np.nan)) for c in columns]
    groups = ("participant_id", design.symbol_column) if design.symbol_effect else (
        "participant_id",)
    for group in groups:
        theta += np.sqrt(np.clip(np.diag(fitted_covariance(full, group, columns)), 0.0,
                                 None)).tolist()
    variances = full.variance_components
    converged = bool(full.converged)
    for j, test in enumerate(fits.tests):
        if test.test is None and test.column in full.params.index:
            out["p_value"][j], out["kind"][j] = floor_p(full.pvalues[test.column]), WALD
        elif test.test is not None:
            out["p_value"][j] = floor_p(test.test.pvalue)
            out["kind"][j] = SEPARATED if test.separated else LR
            converged = converged and bool(test.reduced.converged)
            out["loglike_reduced"][j] = test.test.loglike_reduced
        if test.log_odds is not None:
            out["log_odds"][j] = test.log_odds
    if full.separation is None:
        out["theta"] = np.array(theta)
    out["loglike"] = full.separation.sup_loglike if full.separation else full.loglike
    out["converged"] = converged
    out["boundary"] = bool((variances == 0).any() or full.is_singular)
    out["reduced"] = len(fits.steps) > 1
    return out


def _expand(cells: pd.DataFrame) -> pd.DataFrame:
    """Aggregated cells back to 0/1 rows (for the pooled tables of the Fisher fallback)."""
    rows = cells.loc[cells.index.repeat(cells["n_trials"].astype(int))].copy()
    rank = rows.groupby(level=0).cumcount()
    rows["correct"] = (rank < rows["correct"]).astype(float)
    return rows.drop(columns="n_trials").reset_index(drop=True)
