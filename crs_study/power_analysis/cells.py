"""What the batched fits of one point share: its cells and the plan's terms.

Every simulated study of a point has the same cells (participant x symbol x condition, with
the design's trials), so the fits' design matrices are built once per point
(:class:`PointCells`) and every study differs only in its successes; a reduced model starts
from the covariances of the fit it reduces, as lme4's theta (:func:`theta_start`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crs_study.analysis.glmm_batch import BatchObjective
from crs_study.analysis.glmm_laplace import LaplaceLikelihood, TermRows
from crs_study.analysis.glmm_terms import RandomTerm, ThetaLayout, theta_of
from crs_study.analysis.structure import planned_terms
from crs_study.power_analysis.design import PowerDesign
from crs_study.power_analysis.simulate import cells_frame


@dataclass(frozen=True)
class PointCells:
    """The rows the fits of one point share: every (participant, symbol, condition) cell."""

    X: np.ndarray           # (n, C) treatment-coded design of each cell
    trials: np.ndarray      # (n,)
    participant: np.ndarray
    symbol: np.ndarray
    P: int
    D: int
    columns: tuple[str, ...]

    @classmethod
    def of(cls, design: PowerDesign, P: int, D: int, trials: np.ndarray) -> PointCells:
        C = len(design.conditions)
        p, d, c = (a.ravel() for a in np.meshgrid(np.arange(P), np.arange(D), np.arange(C),
                                                  indexing="ij"))
        X = design.fixed_design()[c]
        columns = ("Intercept",) + tuple(f"condition[{k}]" for k in design.comparisons)
        return cls(X, np.broadcast_to(trials, (P, D, C)).ravel().astype(float), p, d, P, D,
                   columns)

    def objective(self, terms: tuple[RandomTerm, ...], Y: np.ndarray,
                  drop: int | None = None) -> BatchObjective:
        """The batch objective of ``Y`` (S, P, D, C) under ``terms`` (fixed column ``drop``
        left out: a reduced model)."""
        rows = []
        for term in terms:
            codes, levels = ((self.participant, self.P) if term.group == "participant_id"
                             else (self.symbol, self.D))
            Z = self.X[:, [self.columns.index(c) for c in term.columns]]
            rows.append(TermRows(codes, levels, Z))
        X = self.X if drop is None else np.delete(self.X, drop, axis=1)
        likelihood = LaplaceLikelihood(X, self.trials, Y.reshape(len(Y), -1), rows)
        return BatchObjective(likelihood, ThetaLayout(X.shape[1], terms))


def planned_power_terms(design: PowerDesign) -> tuple[RandomTerm, ...]:
    """The terms the plan asks for on the design's data (every participant and symbol sees
    every condition, so condition varies within both)."""
    P, D, C = 2, len(design.symbols), len(design.conditions)
    cells = cells_frame(design, np.ones((P, D, C)), np.ones((D, C)))
    columns = {"participant": "participant_id", "symbol": design.symbol_column,
               "digit": design.symbol_column}
    terms, _ = planned_terms(design.random_spec, cells,
                             [f"condition[{c}]" for c in design.comparisons], columns)
    if not design.symbol_effect:      # a single symbol: fit_glmm drops that factor
        terms = [t for t in terms if t.group == "participant_id"]
    return tuple(terms)


def curvature_shape(design: PowerDesign) -> tuple[int, int]:
    """The shape of one study's curvature of the plan's model."""
    size = ThetaLayout(len(design.conditions), planned_power_terms(design)).size
    return size, size


def theta_start(terms, beta: np.ndarray, covariances: dict[str, np.ndarray],
                 columns: tuple[str, ...]) -> np.ndarray:
    """A start for ``terms``: ``beta`` and each term's part of the covariance given per
    grouping column over ``columns`` (the Cholesky factor; the SDs of an uncorrelated term)."""
    parts = [beta]
    for term in terms:
        index = [columns.index(c) for c in term.columns]
        cov = covariances[term.group][np.ix_(index, index)]
        if term.correlated and term.size > 1:
            T = np.linalg.cholesky(cov + 1e-4 * np.eye(len(index)))
        else:
            T = np.diag(np.sqrt(np.clip(np.diag(cov), 0.0, None)))
        parts.append(theta_of(term, T))
    return np.concatenate(parts)


def fitted_covariances(objective: BatchObjective, theta: np.ndarray,
                        columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Each grouping column's covariance over ``columns`` at a study's fit (0 where the
    fitted terms have no effect)."""
    layout = objective.layout
    out = {}
    for term, sigma in zip(layout.terms, layout.covariances(theta), strict=True):
        full = np.zeros((len(columns), len(columns)))
        index = [columns.index(c) for c in term.columns]
        full[np.ix_(index, index)] = sigma
        out[term.group] = full
    return out


def recorded(objective: BatchObjective, theta: np.ndarray, names: list[str],
              design: PowerDesign) -> np.ndarray:
    """One study's fixed effects and random-effect SDs in :func:`recorded_parameters`'
    order."""
    C = len(design.conditions)
    covariances = fitted_covariances(objective, theta,
                                      ("Intercept",) + tuple(names[1:C]))
    sds = []
    for group in ("participant_id", design.symbol_column) if design.symbol_effect else (
            "participant_id",):
        cov = covariances.get(group, np.zeros((C, C)))
        sds += np.sqrt(np.clip(np.diag(cov), 0.0, None)).tolist()
    return np.r_[theta[:C], sds]
