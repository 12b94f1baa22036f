"""Separation: when a maximum-likelihood estimate is infinite, what the data still say.

A condition at 100 % (or 0 %) correct makes its log odds ratio run to infinity: the likelihood
rises towards a supremum it never reaches, so there is no estimate, no standard error and no
Wald interval. What stays well defined (Heinze & Schemper 2002, Stat. Med. 21:2409, for the
profile; Konis 2007 for the detection) is

* the **direction** ``d`` of separation: ``x_i'd >= 0`` on rows with only successes, ``<= 0``
  on rows with only failures, ``= 0`` on mixed rows, by the linear program of Konis (2007,
  DPhil thesis, Oxford; R's ``detectseparation``);
* the **supremum** of the log-likelihood: along ``d`` the rows with ``x_i'd != 0`` tend to
  probability 1 (or 0) and contribute 0, so the supremum is the maximum over the other rows
  alone (their random effects included: a level seen only in separated rows contributes 0 in
  the Laplace limit, its weight ``w`` -> 0);
* the **likelihood-ratio test** against a model without the term, at that supremum;
* the **one-sided profile-likelihood limit** of each separated coefficient: the finite end
  where ``2 (sup - l_prof(b)) = chi2_1(level)``, every other parameter (variances included)
  re-maximised on the *unpenalised* likelihood; the other end is infinite.

The penalised fit (normal priors, :mod:`crs_study.analysis.glmm`) gives finite numbers to
print beside these, labelled as penalised; it is never the primary figure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from crs_study.analysis.glmm_optimise import maximise


@dataclass(frozen=True)
class Separation:
    """The separated coefficients, their directions (+1: to +infinity) and the supremum of
    the unpenalised log-likelihood (binomial constants included, as ``GlmmResult.loglike``)."""

    coefficients: tuple[str, ...]
    directions: tuple[int, ...]
    sup_loglike: float
    problem: object = field(default=None, repr=False, compare=False)   # unpenalised

    def to_dict(self) -> dict:
        return {"coefficients": list(self.coefficients), "directions": list(self.directions),
                "sup_loglike": self.sup_loglike}


def separation_direction(X: np.ndarray, y: np.ndarray, m: np.ndarray,
                         row_codes) -> np.ndarray | None:
    """Konis' linear program: a direction ``d`` of (quasi-)complete separation, or None.

    ``row_codes(X)`` gives each row's distinct design row (``(inverse, unique rows)``). The
    program maximises the total margin ``sum |x_i'd|`` over the rows with only successes or
    only failures, subject to the sign constraints and ``x_i'd = 0`` on mixed rows, ``d`` in
    ``[-1, 1]^p``; a positive optimum means separation.
    """
    inverse, key = row_codes(X)
    ys, ms = np.bincount(inverse, y), np.bincount(inverse, m)
    keep = ms > 0
    key, ys, ms = key[keep], ys[keep], ms[keep]
    sign = np.where(ys == ms, 1.0, np.where(ys == 0, -1.0, 0.0))
    if not np.any(sign):
        return None
    signed = key[sign != 0] * sign[sign != 0, None]
    mixed = key[sign == 0]
    res = optimize.linprog(-signed.sum(axis=0), A_ub=-signed, b_ub=np.zeros(len(signed)),
                           A_eq=mixed if len(mixed) else None,
                           b_eq=np.zeros(len(mixed)) if len(mixed) else None,
                           bounds=[(-1, 1)] * X.shape[1], method="highs")
    if res.status != 0 or -res.fun <= 1e-7:
        return None
    return np.where(np.abs(res.x) > 1e-7, res.x, 0.0)


def separated_rows(X: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Rows pushed to probability 0 or 1 along ``direction`` (``x_i'd != 0``)."""
    return np.abs(X @ direction) > 1e-7


def one_sided_limit(separation: Separation, names: list[str], theta: np.ndarray, name: str,
                    level: float) -> tuple[float, float]:
    """The profile-likelihood interval of separated coefficient ``name``: one end finite.

    ``2 (sup - l_prof(b)) = chi2_1(level)`` on the unpenalised likelihood, every other
    parameter re-maximised by :func:`~.glmm_optimise.maximise`; ``l_prof`` rises to ``sup``
    as ``b`` runs off in the separation's direction, so the other end is infinite.
    ``theta`` (the penalised optimum) is the first warm start. NaN when no finite end is
    found within 2^12 log-odds.
    """
    problem = separation.problem
    index = names.index(name)
    sign = separation.directions[separation.coefficients.index(name)]
    top = separation.sup_loglike - problem.user_constant
    target = np.sqrt(stats.chi2.ppf(level, 1))
    warm = {float(theta[index]): theta.copy()}

    def drop(b: float) -> float:
        start = warm[min(warm, key=lambda v: abs(v - b))].copy()
        start[index] = b
        opt = maximise(problem, start, {index: b})
        warm[float(b)] = opt.theta
        return float(np.sqrt(2.0 * max(top - opt.value, 0.0))) - target

    inside = float(theta[index])
    step = 1.0
    while drop(inside) > 0:          # move towards the supremum until within the cutoff
        inside += sign * step
        step *= 2.0
        if step > 2**12:
            return float("nan"), float("nan")
    outside, step = inside - sign, 1.0
    while drop(outside) <= 0:        # and away from it until outside
        outside -= sign * step
        step *= 2.0
        if step > 2**12:
            return float("nan"), float("nan")
    a, b = sorted((inside, outside))
    limit = float(optimize.brentq(drop, a, b, xtol=1e-6))
    problem.objective(theta, grad=False)
    return (limit, float("inf")) if sign > 0 else (float("-inf"), limit)
