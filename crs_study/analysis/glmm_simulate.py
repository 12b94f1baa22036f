"""Simulated identification data from a known random-intercept logistic model.

Used by the recovery tests and the ``glmm`` bench; also handy for power analyses.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy.special import expit


def simulate_trials(rng: np.random.Generator, n_participants: int, trials_per_condition: int,
                    condition_logits: Sequence[float], participant_variance: float,
                    n_digits: int = 10, digit_variance: float = 0.0) -> pd.DataFrame:
    """One row per trial: ``participant``, ``condition``, ``digit``, ``correct`` (0/1).

    ``logit P(correct) = condition_logits[c] + b_participant + d_digit`` with
    ``b ~ N(0, participant_variance)``, ``d ~ N(0, digit_variance)``; conditions are named
    ``c0, c1, ...`` (``c0`` the reference), digits cycle through ``0 .. n_digits - 1``, and
    every participant sees ``trials_per_condition`` trials in every condition.
    """
    logits = np.asarray(condition_logits, dtype=float)
    n_cond = len(logits)
    b = rng.normal(0.0, np.sqrt(participant_variance), n_participants)
    d = rng.normal(0.0, np.sqrt(digit_variance), n_digits)
    participant = np.repeat(np.arange(n_participants), n_cond * trials_per_condition)
    condition = np.tile(np.repeat(np.arange(n_cond), trials_per_condition), n_participants)
    digit = np.arange(len(participant)) % n_digits
    eta = logits[condition] + b[participant] + d[digit]
    correct = (rng.random(len(eta)) < expit(eta)).astype(np.int8)
    return pd.DataFrame({
        "participant": [f"p{i:03d}" for i in participant],
        "condition": pd.Categorical([f"c{i}" for i in condition],
                                    categories=[f"c{i}" for i in range(n_cond)]),
        "digit": digit, "correct": correct})


def slope_covariance(intercept_sd: float, slope_sd: float | Sequence[float] = 0.0,
                     correlation: float = 0.0) -> np.ndarray:
    """The covariance of (intercept, slope per contrast) with the intercept correlated
    ``correlation`` with every slope (slopes uncorrelated with each other)."""
    slopes = np.atleast_1d(np.asarray(slope_sd, dtype=float))
    sd = np.r_[intercept_sd, slopes]
    corr = np.eye(len(sd))
    corr[0, 1:] = corr[1:, 0] = correlation
    return corr * np.outer(sd, sd)


def psd_factor(cov: np.ndarray) -> np.ndarray:
    """``L`` with ``L L' = cov`` for a covariance that may be singular: the Cholesky factor
    of the effects with positive variance (zero rows elsewhere); the symmetric square root
    where those are singular too (a correlation of +-1)."""
    cov = np.atleast_2d(np.asarray(cov, dtype=float))
    L = np.zeros_like(cov)
    live = np.flatnonzero(np.diag(cov) > 0)
    if len(live):
        try:
            L[np.ix_(live, live)] = np.linalg.cholesky(cov[np.ix_(live, live)])
        except np.linalg.LinAlgError:
            values, vectors = np.linalg.eigh(cov)
            L = vectors * np.sqrt(np.clip(values, 0.0, None))
    return L


def simulate_cells(rng: np.random.Generator, n_participants: int, n_symbols: int,
                   repetitions: int | np.ndarray, condition_logits: Sequence[float],
                   participant_cov: np.ndarray, symbol_cov: np.ndarray | None = None,
                   conditions: Sequence[str] | None = None) -> pd.DataFrame:
    """Successes of every participant x symbol x condition cell, random slopes included.

    ``logit P(correct) = logits[c] + b_p[0] + b_p[c] + d_s[0] + d_s[c]`` (``b[c]`` the slope of
    condition ``c`` against the first, treatment coding) with ``b_p ~ N(0, participant_cov)``
    and ``d_s ~ N(0, symbol_cov)``, covariances of (intercept, slope per non-reference
    condition), e.g. :func:`slope_covariance`. ``repetitions``: trials per cell, a number or
    an array (P, S, C) (0 leaves a cell out). Columns ``participant_id``, ``digit``,
    ``condition``, ``correct`` (successes), ``n_trials``: the aggregated trial table the
    primary test takes.
    """
    logits = np.asarray(condition_logits, dtype=float)
    C = len(logits)
    names = list(conditions) if conditions is not None else [f"c{i}" for i in range(C)]
    participant_cov = np.atleast_2d(participant_cov)
    symbol_cov = np.zeros((C, C)) if symbol_cov is None else np.atleast_2d(symbol_cov)
    b = rng.standard_normal((n_participants, len(participant_cov))) @ psd_factor(
        participant_cov).T
    d = rng.standard_normal((n_symbols, len(symbol_cov))) @ psd_factor(symbol_cov).T
    design = np.column_stack([np.ones(C), np.eye(C)[:, 1:]])                 # (C, r)
    eta = (logits[None, None, :] + (b @ design[:, :b.shape[1]].T)[:, None, :]
           + (d @ design[:, :d.shape[1]].T)[None, :, :])                    # (P, S, C)
    m = np.broadcast_to(np.asarray(repetitions), eta.shape).astype(int)
    successes = rng.binomial(m, expit(eta))
    p, s, c = (a.ravel() for a in np.meshgrid(np.arange(n_participants), np.arange(n_symbols),
                                              np.arange(C), indexing="ij"))
    keep = m.ravel() > 0
    width = max(2, len(str(n_participants)))
    return pd.DataFrame({
        "participant_id": [f"p{k:0{width}d}" for k in p[keep]],
        "digit": s[keep], "condition": np.asarray(names, dtype=object)[c[keep]],
        "correct": successes.ravel()[keep].astype(float),
        "n_trials": m.ravel()[keep].astype(float)})
