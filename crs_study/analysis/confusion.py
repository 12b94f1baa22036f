"""Confusion matrices per condition and the information they transmit.

The confusion matrix ``N[i, j]`` counts trials showing digit ``i`` answered ``j`` (answered
trials only; time-outs are counted apart). The information transmitted from stimulus to
response (Miller & Nicely 1955, J. Acoust. Soc. Am. 27:338, Eq. 1; Shannon's mutual
information) is, in bits,

``T = sum_ij p_ij log2(p_ij / (p_i. p_.j))``, with ``p_ij = N_ij / N``,

and the relative transmission ``T / H(stimulus)``. The plug-in ``T`` is biased upwards in
small samples; the Miller-Madow correction (Miller 1955, "Note on the bias of information
estimates") applied to each entropy of ``T = H(S) + H(R) - H(S, R)`` subtracts

``(m_SR - m_S - m_R + 1) / (2 N ln 2)``,

``m`` counting the non-empty cells of each distribution; this is the first-order bias of
Panzeri & Treves 1996 (Network 7:87) with the "naive" count of relevant bins. The interval is
a seeded percentile bootstrap that resamples participants (their trials together) or trials.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

LN2 = np.log(2.0)


def confusion_counts(trials: pd.DataFrame, labels: list[int]) -> pd.DataFrame:
    """Counts ``digit`` (rows) x ``response`` (columns) over answered trials, all ``labels``."""
    answered = trials.loc[trials["response"].notna()]
    response = answered["response"].astype("int64")
    table = pd.crosstab(answered["digit"], response).reindex(index=labels, columns=labels,
                                                              fill_value=0)
    table.index.name, table.columns.name = "digit", "response"
    return table.astype(int)


def entropy_bits(counts: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Plug-in Shannon entropy (bits) of counts, over the last axes or all."""
    counts = np.asarray(counts, dtype=float)
    total = counts.sum(axis=axis, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(counts > 0, counts / total, 0.0)
        terms = np.where(p > 0, -p * np.log2(np.where(p > 0, p, 1.0)), 0.0)
    return terms.sum(axis=axis)


def information_transfer(counts: np.ndarray, bias_correction: str = "miller-madow"
                         ) -> np.ndarray:
    """Transmitted information (bits) of confusion matrices ``(..., K, K)``, vectorised.

    ``T = H(S) + H(R) - H(S, R)`` minus, for ``"miller-madow"``, ``(m_SR - m_S - m_R + 1) /
    (2 N ln 2)`` (see the module notes).
    """
    counts = np.asarray(counts, dtype=float)
    flat = counts.reshape(*counts.shape[:-2], -1)
    rows, cols = counts.sum(axis=-1), counts.sum(axis=-2)
    t = entropy_bits(rows, -1) + entropy_bits(cols, -1) - entropy_bits(flat, -1)
    if bias_correction == "miller-madow":
        n = flat.sum(axis=-1)
        m = (flat > 0).sum(-1) - (rows > 0).sum(-1) - (cols > 0).sum(-1) + 1
        with np.errstate(divide="ignore", invalid="ignore"):
            t = t - np.where(n > 0, m / (2.0 * n * LN2), 0.0)
    return t


@dataclass(frozen=True)
class ConfusionResult:
    """Per condition: ``counts`` and row ``proportions`` (K x K), the transmitted information
    ``bits`` (bias-corrected as named), ``bits_plugin``, ``ci95`` (bootstrap), the stimulus
    entropy ``stimulus_bits``, ``relative`` = bits / stimulus_bits, ``n_trials``,
    ``n_no_response`` (time-outs, not in the matrix)."""

    condition: str
    counts: pd.DataFrame
    proportions: pd.DataFrame
    bits: float
    bits_plugin: float
    ci95: tuple[float, float] | None
    stimulus_bits: float
    relative: float
    n_trials: int
    n_no_response: int
    bias_correction: str
    bootstrap: dict = field(default_factory=dict)
    note: str = ""

    def to_dict(self) -> dict:
        return {"condition": self.condition, "bits": self.bits,
                "bits_plugin": self.bits_plugin,
                "ci95": None if self.ci95 is None else list(self.ci95),
                "stimulus_bits": self.stimulus_bits, "relative": self.relative,
                "n_trials": self.n_trials, "n_no_response": self.n_no_response,
                "bias_correction": self.bias_correction, "bootstrap": self.bootstrap,
                "labels": [int(x) for x in self.counts.index],
                "counts": self.counts.to_numpy().tolist(), "note": self.note}


def analyse_confusions(trials: pd.DataFrame, conditions: list[str],
                       bias_correction: str = "miller-madow", n_bootstrap: int = 2000,
                       unit: str = "participant", seed: int = 0, alpha: float = 0.05
                       ) -> tuple[dict[str, ConfusionResult], list[str]]:
    """Confusions and information transfer for each condition, with bootstrap intervals."""
    labels = sorted({int(d) for d in trials["digit"]} |
                    {int(r) for r in trials["response"].dropna()})
    results, warnings = {}, []
    for index, condition in enumerate(conditions):
        subset = trials.loc[trials["condition"] == condition]
        counts = confusion_counts(subset, labels)
        matrix = counts.to_numpy()
        n = int(matrix.sum())
        with np.errstate(divide="ignore", invalid="ignore"):
            sums = matrix.sum(axis=1, keepdims=True)
            proportions = pd.DataFrame(np.where(sums > 0, matrix / np.where(sums > 0, sums, 1),
                                                0.0), index=counts.index,
                                       columns=counts.columns)
        bits = float(information_transfer(matrix, bias_correction))
        plugin = float(information_transfer(matrix, "none"))
        h_stimulus = float(entropy_bits(matrix.sum(axis=1)))
        rng = np.random.default_rng([seed, 6, index])
        ci, info, note = _bootstrap(subset, labels, bias_correction, n_bootstrap, unit, rng,
                                    alpha)
        if note:
            warnings.append(f"information transfer of {condition!r}: {note}")
        results[condition] = ConfusionResult(
            condition, counts, proportions, bits, plugin, ci, h_stimulus,
            bits / h_stimulus if h_stimulus > 0 else 0.0, n,
            int(subset["response"].isna().sum()), bias_correction, info, note)
    return results, warnings


def _bootstrap(trials: pd.DataFrame, labels: list[int], bias_correction: str, n_boot: int,
               unit: str, rng: np.random.Generator, alpha: float):
    """Percentile bootstrap of the transmitted information; returns (ci, info, note)."""
    if n_boot == 0:
        return None, {}, "no bootstrap interval (plan.confusion.bootstrap = 0)"
    answered = trials.loc[trials["response"].notna()]
    if answered.empty:
        return None, {}, "no answered trials: no information transfer interval"
    index = {label: i for i, label in enumerate(labels)}
    k = len(labels)
    cells = answered["digit"].map(index).to_numpy() * k + \
        answered["response"].astype("int64").map(index).to_numpy()
    note = ""
    participants = answered["participant_id"].to_numpy()
    units = pd.unique(participants)
    if unit == "participant" and len(units) < 2:
        note = ("one participant only: resampled trials instead of participants (the interval "
                "ignores differences between participants)")
        unit = "trial"
    if unit == "participant":
        codes = pd.Categorical(participants, categories=units).codes
        per_unit = np.zeros((len(units), k * k))
        np.add.at(per_unit, (codes, cells), 1.0)
        draws = rng.integers(0, len(units), size=(n_boot, len(units)))
        # counts of each participant in each resample, times their matrices
        weights = np.zeros((n_boot, len(units)))
        np.add.at(weights, (np.repeat(np.arange(n_boot), len(units)), draws.ravel()), 1.0)
        samples = weights @ per_unit
    else:
        observed = np.bincount(cells, minlength=k * k).astype(float)
        samples = rng.multinomial(int(observed.sum()), observed / observed.sum(),
                                  size=n_boot).astype(float)
    bits = information_transfer(samples.reshape(n_boot, k, k), bias_correction)
    low, high = np.quantile(bits, [alpha / 2, 1 - alpha / 2])
    info = {"method": "percentile", "resamples": n_boot, "unit": unit}
    return (float(low), float(high)), info, note
