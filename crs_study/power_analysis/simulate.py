"""Simulated studies with common random numbers: participant k is one person at every N.

Every random number of a study comes from a stream of its own, a
:class:`numpy.random.SeedSequence` with ``entropy = seed`` and a ``spawn_key`` naming what it
draws, never the worker or the batch that runs it:

* ``(study, 0)``: the symbols' random effects ``z_d`` (D standard normals, in the
  design's order of symbols: digits, letters or a set file's symbols alike);
* ``(study, 1, k)``: participant ``k`` (from 0): first ``z_k``, then the uniforms of their
  trials, ``U[rep, level, symbol, condition]``, repetition-major.

So a study with N participants is the first N participants of the same study with more,
each participant's first r repetitions are the same whatever the largest repetition count
asked (``Generator.random`` fills its array in order), and the result of a run is the same
whichever backend and how many workers run it (the point and the worker take no part in a
seed). Trial ``(rep, level, d, c)`` of participant ``k`` is correct when ``U < expit(base[l,
d, c] + sigma_p z_k + sigma_d z_d)`` (with an ability table, ``ability(z_k)[l, d, c]`` in
place of ``base + sigma_p z_k``: :meth:`~crs_study.power_analysis.model.GenerativeModel.
participant_logits`); the cells' successes are summed over levels.
"""

from __future__ import annotations

import numpy as np
from scipy.special import expit

from crs_study.power_analysis.model import GenerativeModel


def stream(seed: int, *key: int) -> np.random.Generator:
    """The generator of one named stream of a run (``key``: the spawn key, module docs)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def simulate_studies(model: GenerativeModel, seed: int, studies: range | list[int],
                     n_participants: int, repetitions: int) -> np.ndarray:
    """Cumulative successes ``(S, n_participants, repetitions, D, C)``: entry ``[s, k, r]``
    holds participant k's correct trials per (symbol, condition) cell in their first ``r + 1``
    repetitions (every level of the cell summed)."""
    base = model.base                                         # (L, D, C)
    L, D, C = base.shape
    out = np.empty((len(studies), n_participants, repetitions, D, C), dtype=np.int32)
    for i, study in enumerate(studies):
        z_symbol = stream(seed, study, 0).standard_normal(D)
        symbol_shift = model.digit_sd * z_symbol[None, :, None]
        logit_study = base + symbol_shift
        for k in range(n_participants):
            rng = stream(seed, study, 1, k)
            z = rng.standard_normal()
            if model.ability is None:
                p = expit(logit_study + model.participant_sd * z)
            else:
                p = expit(model.participant_logits(z) + symbol_shift)
            hits = rng.random((repetitions, L, D, C)) < p[None]
            out[i, k] = np.cumsum(hits.sum(axis=1), axis=0)
    return out
