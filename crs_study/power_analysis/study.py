"""The unit of work: a block of simulated studies at every point of the curve.

:func:`run_task` is a pure function of a :class:`PowerTask` (design, model, seed, the points
and a range of study numbers) to a small :class:`TaskResult`; the backends map it over a
process pool or a Dask cluster (:mod:`crs_study.power_analysis.backends`, STYLE.md point 18).

Each simulated study is tested as ``analyze`` tests a dataset
(:func:`crs_study.analysis.primary.primary_test`): the full GLMM ``correct ~ condition +
(1 | participant) [+ (1 | symbol)]`` (the symbol's intercept grouped by the design's
symbol column, ``digit`` for the digit set) and, per non-reference condition, the model without it;
the likelihood-ratio p of each comparison; a separated condition tested at the supremum; a
reduced model that cannot be fitted: the Wald p; a full model that cannot be fitted: Fisher's
exact test on the pooled table. A study's outcome records which of these it was (``KINDS``).

Two paths give those fits. The fast path (:mod:`crs_study.power_analysis.maximise`) fits all studies
of a point at once, from the generating parameters, to the maximum ``fit_glmm`` finds (its
boundary rule included); a study it does not settle (a condition at 0 % or 100 %, where
``fit_glmm`` tests at the supremum; a Newton iteration that stalls; a boundary where
``fit_glmm`` would restart from interior points; a plan with adaptive quadrature) goes the
reference path: :func:`crs_study.analysis.primary.fit_primary` itself on the study's cells.
The p-value of the fast path is :func:`crs_study.analysis.glmm.lrt`'s: ``2 (l_full -
l_reduced)``, differences below 1e-6 taken as 0, against chi2(1), floored at the smallest
positive float.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from crs_study.analysis.accuracy import floor_p
from crs_study.analysis.glmm import GlmmFitError
from crs_study.analysis.glmm_result import P_FLOOR
from crs_study.analysis.primary import fisher_comparisons, fit_primary
from crs_study.power_analysis.design import PowerDesign
from crs_study.power_analysis.laplace import BatchLaplace, CellDesign
from crs_study.power_analysis.maximise import fit_batch
from crs_study.power_analysis.model import GenerativeModel
from crs_study.power_analysis.simulate import simulate_studies

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
    reference: np.ndarray
    loglike: np.ndarray
    loglike_reduced: np.ndarray
    seconds: float


def run_task(task: PowerTask) -> TaskResult:
    """Simulate the task's studies and test each at every point (module docstring)."""
    start = time.process_time()
    design, model = task.design, task.model
    studies = range(*task.studies)
    cumulative = simulate_studies(model, task.seed, studies, max(task.participants),
                                  max(task.repetitions))
    points = task.points
    out = outcomes(design, (len(points), len(studies)))
    previous: dict[int, tuple[int, np.ndarray]] = {}     # per repetitions: (N, curvature)
    for i, (n, r) in enumerate(points):
        Y = cumulative[:, :n, r - 1].astype(float)
        # The full model's curvature at the previous N of the same study, scaled by the
        # participants (the information grows with them): a per-study start for the fits'
        # Hessian, so a study's answer still depends on nothing but its own data.
        last = previous.get(r)
        start_curvature = None if last is None else last[1] * (n / last[0])
        point = decide_studies(design, model, Y, r, start_curvature)
        previous[r] = (n, point.pop("curvature"))
        for key, value in point.items():
            out[key][i] = value
    return TaskResult(task.studies, seconds=time.process_time() - start, **out)


def outcomes(design: PowerDesign, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Empty outcome arrays of :class:`TaskResult`'s fields for ``shape`` (points, studies,
    or studies, or () for one study): no test, NaN numbers, flags off."""
    K = len(design.comparisons)
    n_params = len(design.conditions) + 1 + int(design.symbol_effect)
    return {"p_value": np.full(shape + (K,), np.nan),
            "kind": np.full(shape + (K,), NONE, dtype=np.int8),
            "log_odds": np.full(shape + (K,), np.nan),
            "theta": np.full(shape + (n_params,), np.nan),
            "converged": np.zeros(shape, dtype=bool), "boundary": np.zeros(shape, dtype=bool),
            "reference": np.zeros(shape, dtype=bool), "loglike": np.full(shape, np.nan),
            "loglike_reduced": np.full(shape + (K,), np.nan)}


def decide_studies(design: PowerDesign, model: GenerativeModel, Y: np.ndarray,
                   repetitions: int, curvature: np.ndarray | None = None
                   ) -> dict[str, np.ndarray]:
    """Test studies ``Y`` (S, P, D, C) of one point as ``analyze`` would; arrays as in
    :class:`TaskResult` (without the point axis), and ``curvature`` (S, n, n) the full
    model's last negative-Hessian approximation (zeros where none), which a next point may
    pass back as its start."""
    S = len(Y)
    K = len(design.comparisons)
    trials = design.cell_trials(repetitions)
    cells = CellDesign(design.fixed_design(), trials, design.symbol_effect)
    out = outcomes(design, (S,))
    n_params = cells.n_params
    out["curvature"] = np.zeros((S, n_params, n_params))
    per_condition = Y.sum(axis=(1, 2))                                  # (S, C)
    possible = trials.sum(axis=0) * Y.shape[1]
    separated = ((per_condition == 0) | (per_condition == possible)).any(axis=1)
    fast = np.flatnonzero(~separated) if design.method == "laplace" else np.arange(0)
    settled = np.zeros(S, dtype=bool)
    if len(fast):
        full = fit_batch(BatchLaplace(cells, Y[fast]), np.tile(model.start(design),
                                                               (len(fast), 1)),
                         None if curvature is None else curvature[fast])
        out["curvature"][fast] = full.curvature
        needs = full.needs_reference.copy()
        reduced_values = np.empty((len(fast), K))
        for j in range(K):
            curvature = np.delete(np.delete(full.curvature, j + 1, axis=1), j + 1, axis=2)
            reduced = fit_batch(BatchLaplace(cells.without(j + 1), Y[fast]),
                                np.delete(full.theta, j + 1, axis=1), curvature)
            needs |= reduced.needs_reference
            reduced_values[:, j] = reduced.value
        stats_ = 2.0 * (full.value[:, None] - reduced_values)
        constant = binomial_constant(Y[fast], trials)
        ok = fast[~needs]
        out["loglike"][ok] = (full.value + constant)[~needs]
        out["loglike_reduced"][ok] = (reduced_values + constant[:, None])[~needs]
        out["p_value"][ok] = lr_pvalue(stats_[~needs])
        out["kind"][ok] = LR
        out["log_odds"][ok] = full.theta[~needs, 1:K + 1]
        out["theta"][ok] = full.theta[~needs]
        out["converged"][ok] = True
        out["boundary"][ok] = full.at_zero[~needs].any(axis=1)
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


def cells_frame(design: PowerDesign, Y: np.ndarray, trials: np.ndarray) -> pd.DataFrame:
    """One study's cells (P, D, C) as the aggregated trial table ``fit_primary`` takes: the
    symbol shown in the design's symbol column (``digit`` for the digit set, ``symbol`` for
    any other), as a dataset of the protocol names it."""
    P, D, C = Y.shape
    p, d, c = np.meshgrid(np.arange(P), np.arange(D), np.arange(C), indexing="ij")
    width = max(2, len(str(P)))
    return pd.DataFrame({
        "participant_id": [f"sim{k + 1:0{width}d}" for k in p.ravel()],
        design.symbol_column: _as_array(design.symbols)[d.ravel()],
        "condition": np.asarray(design.conditions, dtype=object)[c.ravel()],
        "correct": Y.ravel().astype(float),
        "n_trials": np.broadcast_to(trials, (P, D, C)).ravel().astype(float)})


def _as_array(symbols: tuple) -> np.ndarray:
    """The symbols as a column: integers (the digit set) as integers, others as objects
    (never numpy's fixed-width strings, and never a label turned into a number)."""
    if all(isinstance(s, int) and not isinstance(s, bool) for s in symbols):
        return np.asarray(symbols)
    out = np.empty(len(symbols), dtype=object)
    out[:] = list(symbols)
    return out


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
                           design.method, design.n_quadrature)
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
    theta = [float(full.params.get(c, np.nan)) for c in
             ["Intercept"] + [f"condition[{c}]" for c in design.comparisons]]
    variances = full.variance_components
    theta.append(float(np.sqrt(variances.get("participant_id", np.nan))))
    if design.symbol_effect:
        theta.append(float(np.sqrt(variances.get(design.symbol_column, np.nan))))
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
    out["boundary"] = bool((variances == 0).any())
    return out


def _expand(cells: pd.DataFrame) -> pd.DataFrame:
    """Aggregated cells back to 0/1 rows (for the pooled tables of the Fisher fallback)."""
    rows = cells.loc[cells.index.repeat(cells["n_trials"].astype(int))].copy()
    rank = rows.groupby(level=0).cumcount()
    rows["correct"] = (rank < rows["correct"]).astype(float)
    return rows.drop(columns="n_trials").reset_index(drop=True)
