"""Simulated studies with common random numbers: participant k is one person at every N.

Every random number of a study comes from a stream of its own, a
:class:`numpy.random.SeedSequence` with ``entropy = seed`` and a ``spawn_key`` naming what it
draws, never the worker or the batch that runs it:

* ``(study, 0)``: the symbols' random intercepts ``z_d`` (D standard normals, in the
  design's order of symbols: digits, letters or a set file's symbols alike);
* ``(study, 1, k)``: participant ``k`` (from 0): first ``z_k``, then the uniforms of their
  trials, ``U[rep, level, symbol, condition]``, repetition-major;
* ``(study, 2, k)``: participant ``k``'s slope draws ``w_k`` (C - 1 standard normals);
* ``(study, 3)``: the symbols' slope draws (D x (C - 1) standard normals).

A participant's effects are ``L (z_k, w_k)`` with ``L L'`` the model's covariance of
(intercept, slopes) (:func:`~crs_study.analysis.glmm_simulate.psd_factor`: for a random
intercept alone, ``L`` has ``participant_sd`` in its corner and nothing else, so studies
without slopes are the ones drawn before slopes existed), likewise a symbol's.

So a study with N participants is the first N participants of the same study with more,
each participant's first r repetitions are the same whatever the largest repetition count
asked (``Generator.random`` fills its array in order), and the result of a run is the same
whichever backend and how many workers run it (the point and the worker take no part in a
seed). Trial ``(rep, level, d, c)`` of participant ``k`` is correct when ``U <
expit(participant_logits(z_k, w_k)[l, d, c] + e_d[0] + e_d[c])`` (:meth:`~crs_study.
power_analysis.model.GenerativeModel.participant_logits`; ``e_d`` the symbol's effects, its
slope ``e_d[c]`` 0 for the reference); the cells' successes are summed over levels.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.special import expit

from crs_study.analysis.glmm_simulate import psd_factor
from crs_study.power_analysis.design import PowerDesign
from crs_study.power_analysis.model import GenerativeModel


def stream(seed: int, *key: int) -> np.random.Generator:
    """The generator of one named stream of a run (``key``: the spawn key, module docs)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def simulate_studies(model: GenerativeModel, seed: int, studies: range | list[int],
                     n_participants: int, repetitions: int) -> np.ndarray:
    """Cumulative successes ``(S, n_participants, repetitions, D, C)``: entry ``[s, k, r]``
    holds participant k's correct trials per (symbol, condition) cell in their first ``r + 1``
    repetitions (every level of the cell summed)."""
    L, D, C = model.base.shape
    symbol_factor = psd_factor(model.covariance("symbol"))
    out = np.empty((len(studies), n_participants, repetitions, D, C), dtype=np.int32)
    for i, study in enumerate(studies):
        draws = np.column_stack([stream(seed, study, 0).standard_normal(D),
                                 stream(seed, study, 3).standard_normal((D, C - 1))])
        effects = draws @ symbol_factor.T                                   # (D, C)
        symbol_shift = (effects[:, :1] + np.c_[np.zeros(D), effects[:, 1:]])[None]
        rngs = [stream(seed, study, 1, k) for k in range(n_participants)]
        z = np.array([rng.standard_normal() for rng in rngs])
        w = np.array([stream(seed, study, 2, k).standard_normal(C - 1)
                      for k in range(n_participants)]).reshape(n_participants, C - 1)
        p = expit(model.participants_logits(z, w) + symbol_shift)           # (P, L, D, C)
        uniforms = np.array([rng.random((repetitions, L, D, C)) for rng in rngs])
        hits = uniforms < p[:, None]
        out[i] = np.cumsum(hits.sum(axis=2), axis=1)
    return out


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
