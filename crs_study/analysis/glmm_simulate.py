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
