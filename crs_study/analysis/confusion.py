"""Confusion matrices per condition and the information they transmit.

The confusion matrix ``N[i, j]`` counts trials showing symbol ``i`` answered ``j`` (answered
trials only; time-outs are counted apart); its labels are the set's symbols (the digits, the
letters, ...) as the trials hold them, in their order. The information transmitted from stimulus to
response (Miller & Nicely 1955, J. Acoust. Soc. Am. 27:338, Eq. 1; Shannon's mutual
information) is, in bits,

``T = sum_ij p_ij log2(p_ij / (p_i. p_.j))``, with ``p_ij = N_ij / N``,

and the relative transmission ``T / H(stimulus)``. The plug-in ``T`` is biased upwards in
small samples; the Miller-Madow correction (Miller 1955, "Note on the bias of information
estimates") applied to each entropy of ``T = H(S) + H(R) - H(S, R)`` subtracts

``(m_SR - m_S - m_R + 1) / (2 N ln 2)``,

``m`` counting the non-empty cells of each distribution; this is the first-order bias of
Panzeri & Treves 1996 (Network 7:87) with the "naive" count of relevant bins.

The interval is a seeded bootstrap that resamples participants (their trials together) or
trials. A percentile interval around ``T`` inherits the upward bias twice over: the resampled
matrices are sparser than the data, so their values sit above the estimate by about the bias
the estimate itself has above the truth (measured: coverage 20-95 % across designs, 47 % with
6 participants x 3 repetitions of 10 digits). The interval is therefore the *basic* (pivotal)
bootstrap interval, whose pivot is the estimate minus the value of the resampled population,
i.e. the plug-in ``T`` of the observed matrix (Davison & Hinkley 1997, Bootstrap Methods and
their Application, sec. 5.2): ``[T_hat - (q_hi - T_plugin), T_hat - (q_lo - T_plugin)]``
with ``q`` quantiles of the resampled (bias-corrected) values. With few participants a
bootstrap spread is too narrow (by ``sqrt((n - 1) / n)``, and like a z instead of a t
interval); the quantiles are taken at
Hesterberg's expanded level ``Phi(-sqrt(n / (n - 1)) t_{n-1}(1 - alpha/2))`` instead of
``alpha / 2`` (Hesterberg 2015, Am. Stat. 69:371, the "expanded percentile interval";
``n`` the participants resampled, or the trials). The ends are kept within ``[0, H(stimulus)]``,
the range of ``T``. Measured coverage of the 95 % interval
(:mod:`crs_study.analysis.confusion_simulate`, 400 datasets a design): 84-98 % from 3
participants x 3 repetitions up (90-97 % but for 6 participants whose accuracies vary widely,
logit sd 1: 84 %), 90 % for one participant x 20 repetitions, against 20-95 % and 44 % for
the percentile interval; BCa (``scipy.stats.bootstrap``) does worse than the percentile one
(36-68 % below 10 participants: nearly every resample lies above the estimate, so its bias
correction runs off the end of the distribution). With no more answered trials than cells in
the matrix the bias correction itself falls short (55-85 % for one participant x 5-10
repetitions of 10 digits) and a warning says so.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import special, stats

from crs_study._display import Display, Displayed
from crs_study.analysis.accuracy import symbol_column_of
from crs_study.analysis.jsonable import json_text

LN2 = np.log(2.0)


def _responses(answered: pd.DataFrame) -> pd.Series:
    """The answered trials' responses as plain values (ints for a digit dataset's nullable
    integers, the labels of any other set as they are)."""
    response = answered["response"]
    return response.astype("int64") if pd.api.types.is_integer_dtype(response) else response


def confusion_counts(trials: pd.DataFrame, labels: list) -> pd.DataFrame:
    """Counts symbol shown (rows, named as the trials name it: ``digit``, ``symbol``) x
    ``response`` (columns) over answered trials, all ``labels``."""
    column = symbol_column_of(trials)
    answered = trials.loc[trials["response"].notna()]
    table = pd.crosstab(answered[column], _responses(answered)).reindex(
        index=labels, columns=labels, fill_value=0)
    table.index.name, table.columns.name = column, "response"
    return table.astype(int)


def entropy_bits(counts: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Plug-in Shannon entropy (bits) of counts over ``axis`` (all when None); 0 when empty.

    ``H = log2 N - sum_i c_i log2 c_i / N``: the same as ``scipy.stats.entropy(counts,
    base=2)``, in one pass over the counts (``scipy.special.xlogy`` gives ``0 log 0 = 0``),
    which matters for the thousands of matrices of a bootstrap.
    """
    counts = np.asarray(counts, dtype=float)
    total = counts.sum(axis=axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = (special.xlogy(total, total) - special.xlogy(counts, counts).sum(axis=axis)) \
            / (total * LN2)
    return np.where(total > 0, np.maximum(h, 0.0), 0.0)


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


@dataclass(frozen=True, repr=False)
class ConfusionResult(Displayed):
    """Per condition: ``counts`` and row ``proportions`` (K x K), the transmitted information
    ``bits`` (bias-corrected as named), ``bits_plugin``, ``ci95`` (basic bootstrap), the stimulus
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

    def _display(self) -> Display:
        ci = "" if self.ci95 is None else f" [{self.ci95[0]:.3g}, {self.ci95[1]:.3g}]"
        return Display(f"ConfusionResult of {self.condition!r}",
                       (("information transfer", f"{self.bits:.3g} bits{ci} of "
                         f"{self.stimulus_bits:.3g}"), ("trials", str(self.n_trials))),
                       (self.note,) if self.note else (), ".counts, .proportions, .to_frame()")

    def to_dict(self) -> dict:
        return {"condition": self.condition, "bits": self.bits,
                "bits_plugin": self.bits_plugin,
                "ci95": None if self.ci95 is None else list(self.ci95),
                "stimulus_bits": self.stimulus_bits, "relative": self.relative,
                "n_trials": self.n_trials, "n_no_response": self.n_no_response,
                "bias_correction": self.bias_correction, "bootstrap": self.bootstrap,
                "labels": [x.item() if isinstance(x, np.generic) else x
                           for x in self.counts.index],
                "counts": self.counts.to_numpy().tolist(), "note": self.note}

    def to_frame(self) -> pd.DataFrame:
        """The confusion matrix: counts, the symbol shown by row, the symbol answered by
        column (labelled as the trials write them)."""
        return self.counts.copy()


#: The columns of :meth:`Confusions.to_frame`.
TRANSFER_COLUMNS = ("condition", "bits", "ci_low", "ci_high", "bits_plugin", "stimulus_bits",
                    "relative", "n_trials", "n_no_response", "bias_correction")


@dataclass(frozen=True, eq=False, repr=False)
class Confusions(Displayed, Mapping[str, ConfusionResult]):
    """Each condition's :class:`ConfusionResult`, in the analysis' order of conditions."""

    by_condition: dict[str, ConfusionResult]

    def __getitem__(self, condition: str) -> ConfusionResult:
        return self.by_condition[condition]

    def __iter__(self) -> Iterator[str]:
        return iter(self.by_condition)

    def __len__(self) -> int:
        return len(self.by_condition)

    def _display(self) -> Display:
        rows = tuple((c, r._display().rows[0][1]) for c, r in self.by_condition.items())
        return Display(f"Confusions of {len(self)} conditions (information transfer)", rows,
                       tuple(r.note for r in self.by_condition.values() if r.note),
                       ".to_frame(), [condition]")

    def to_frame(self) -> pd.DataFrame:
        """Information transfer: one row per condition (:data:`TRANSFER_COLUMNS`; ``ci_low``,
        ``ci_high`` the bootstrap interval, None without one)."""
        rows = [{"condition": c, "bits": r.bits,
                 "ci_low": None if r.ci95 is None else r.ci95[0],
                 "ci_high": None if r.ci95 is None else r.ci95[1],
                 "bits_plugin": r.bits_plugin, "stimulus_bits": r.stimulus_bits,
                 "relative": r.relative, "n_trials": r.n_trials,
                 "n_no_response": r.n_no_response, "bias_correction": r.bias_correction}
                for c, r in self.by_condition.items()]
        return pd.DataFrame(rows, columns=list(TRANSFER_COLUMNS))

    def to_dict(self) -> dict:
        """``results.json``'s ``information_transfer``: per condition its result."""
        return {c: r.to_dict() for c, r in self.by_condition.items()}

    def to_json(self) -> str:
        return json_text(self.to_dict())


def analyse_confusions(trials: pd.DataFrame, conditions: list[str],
                       bias_correction: str = "miller-madow", n_bootstrap: int = 2000,
                       unit: str = "participant", seed: int = 0, alpha: float = 0.05
                       ) -> tuple[dict[str, ConfusionResult], list[str]]:
    """Confusions and information transfer for each condition, with bootstrap intervals."""
    labels = sorted(set(trials[symbol_column_of(trials)].tolist())
                    | set(trials["response"].dropna().tolist()))
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


def _bootstrap(trials: pd.DataFrame, labels: list, bias_correction: str, n_boot: int,
               unit: str, rng: np.random.Generator, alpha: float):
    """Bootstrap interval of the transmitted information; returns (ci, info, note)."""
    if n_boot == 0:
        return None, {}, "no bootstrap interval (plan.confusion.bootstrap = 0)"
    answered = trials.loc[trials["response"].notna()]
    if answered.empty:
        return None, {}, "no answered trials: no information transfer interval"
    index = {label: i for i, label in enumerate(labels)}
    k = len(labels)
    cells = answered[symbol_column_of(answered)].map(index).to_numpy() * k + \
        _responses(answered).map(index).to_numpy()
    notes = []
    participants = answered["participant_id"].to_numpy()
    units = pd.unique(participants)
    if unit == "participant" and len(units) < 2:
        notes.append("one participant only: resampled trials instead of participants (the "
                     "interval ignores differences between participants)")
        unit = "trial"
    codes = pd.Categorical(participants, categories=units).codes
    per_unit = np.zeros((len(units), k * k))
    np.add.at(per_unit, (codes, cells), 1.0)
    ci, info = bootstrap_interval(per_unit.reshape(-1, k, k), bias_correction, n_boot, unit,
                                  rng, alpha)
    if len(answered) <= k * k:
        notes.append(f"{len(answered)} answered trials for the {k * k} cells of a {k} x {k} "
                     "matrix: too few for the bias correction, so the estimate and its "
                     "interval tend to lie above the true value")
    return ci, info, "; ".join(notes)


def bootstrap_interval(per_unit: np.ndarray, bias_correction: str, n_boot: int, unit: str,
                       rng: np.random.Generator, alpha: float = 0.05
                       ) -> tuple[tuple[float, float], dict]:
    """Expanded basic bootstrap interval of the transmitted information (module notes).

    Parameters
    ----------
    per_unit : counts ``(n_units, K, K)``, one confusion matrix per participant.
    bias_correction : ``"miller-madow"`` or ``"none"``, the estimator the interval is for.
    n_boot : resamples.
    unit : ``"participant"`` resamples the matrices (participants with all their trials);
        ``"trial"`` resamples the pooled trials (a multinomial draw from the pooled matrix).
    rng, alpha : the generator, and ``1 - level``.

    Returns
    -------
    ``(low, high)`` and ``info``: ``method``, ``resamples``, ``unit``, ``n_units`` (the ``n``
    of the expansion) and ``tail`` (the probability in each tail of the resamples used).
    """
    per_unit = np.asarray(per_unit, dtype=float)
    k = per_unit.shape[-1]
    flat = per_unit.reshape(len(per_unit), k * k)
    observed = flat.sum(axis=0)
    estimate = float(information_transfer(observed.reshape(k, k), bias_correction))
    plugin = float(information_transfer(observed.reshape(k, k), "none"))
    if unit == "participant":
        n = len(flat)
        draws = rng.integers(0, n, size=(n_boot, n))
        # each participant's count in each resample, times their matrices
        weights = np.zeros((n_boot, n))
        np.add.at(weights, (np.repeat(np.arange(n_boot), n), draws.ravel()), 1.0)
        samples = weights @ flat
    else:
        n = int(observed.sum())
        samples = rng.multinomial(n, observed / observed.sum(), size=n_boot).astype(float)
    bits = information_transfer(samples.reshape(n_boot, k, k), bias_correction)
    # Hesterberg's expanded tail: sqrt(n / (n - 1)) t_{n-1} standard errors instead of z
    tail = float(stats.norm.cdf(-np.sqrt(n / (n - 1)) * stats.t.ppf(1 - alpha / 2, n - 1))
                 ) if n > 1 else alpha / 2
    q_low, q_high = np.quantile(bits, [tail, 1.0 - tail])
    top = float(entropy_bits(observed.reshape(k, k).sum(axis=1)))
    low = min(max(estimate - (q_high - plugin), 0.0), top)
    high = min(max(estimate - (q_low - plugin), 0.0), top)
    info = {"method": "basic bootstrap around the plug-in value, expanded for the number "
                      "resampled (Hesterberg 2015)", "resamples": n_boot, "unit": unit,
            "n_units": n, "tail": tail}
    return (low, high), info
