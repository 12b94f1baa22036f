"""Simulated confusion matrices with a known transmitted information, to check the interval.

The generating model: each of ``n_digits`` digits is shown ``repetitions`` times to every
participant; a participant with ``logit(accuracy_j) = logit(accuracy) + u_j``, ``u_j ~ N(0,
participant_sd^2)``, answers the digit itself with probability ``accuracy_j`` and otherwise
a neighbour, as :mod:`crs_study.analysis.synthetic` does (one below or above 35 % each, two or
three above 15 % each). The population's joint distribution of (stimulus, response) is that
channel at the mean accuracy ``E[accuracy_j]`` (the channel is linear in the accuracy), with
uniform stimuli; its mutual information is the true value the interval should cover.

``python -m crs_study.analysis.confusion_simulate [REPLICATIONS]`` prints the coverage of the
95 % interval for a table of designs.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from scipy import integrate, stats
from scipy.special import expit, logit

from crs_study.analysis.confusion import bootstrap_interval

#: Error distribution over the digit offset (as the synthetic datasets).
ERRORS = {-1: 0.35, 1: 0.35, 2: 0.15, 3: 0.15}


@dataclass(frozen=True)
class Design:
    """Who answers how often: ``unit`` is the bootstrap unit (``"trial"`` for one person)."""

    n_participants: int
    repetitions: int
    accuracy: float
    participant_sd: float = 0.5
    n_digits: int = 10

    @property
    def unit(self) -> str:
        return "participant" if self.n_participants > 1 else "trial"

    @property
    def label(self) -> str:
        return (f"{self.n_participants} x {self.repetitions} rep, acc {self.accuracy:g}, "
                f"sd {self.participant_sd:g}")


def channel(accuracy: float, n_digits: int = 10) -> np.ndarray:
    """``P(response = j | digit = i)``, a ``(K, K)`` row-stochastic matrix."""
    matrix = np.zeros((n_digits, n_digits))
    for i in range(n_digits):
        matrix[i, i] += accuracy
        for step, weight in ERRORS.items():
            matrix[i, (i + step) % n_digits] += (1.0 - accuracy) * weight
    return matrix


def mean_accuracy(design: Design) -> float:
    """``E[expit(logit(accuracy) + u)]``, ``u ~ N(0, sd^2)``, by quadrature."""
    if design.participant_sd == 0:
        return design.accuracy
    centre, sd = logit(design.accuracy), design.participant_sd
    value, _ = integrate.quad(lambda u: expit(centre + u) * stats.norm.pdf(u, 0.0, sd),
                              -12 * sd, 12 * sd)
    return float(value)


def true_information(design: Design) -> float:
    """Mutual information (bits) of the population's joint distribution, by its definition
    ``sum p_ij log2(p_ij / (p_i. p_.j))`` (Miller & Nicely 1955, Eq. 1)."""
    joint = channel(mean_accuracy(design), design.n_digits) / design.n_digits
    outer = joint.sum(axis=1, keepdims=True) * joint.sum(axis=0, keepdims=True)
    cells = joint > 0
    return float(np.sum(joint[cells] * np.log2(joint[cells] / outer[cells])))


def simulate_counts(design: Design, rng: np.random.Generator) -> np.ndarray:
    """One confusion matrix per participant, ``(n_participants, K, K)``."""
    k = design.n_digits
    counts = np.zeros((design.n_participants, k, k))
    for j in range(design.n_participants):
        accuracy = expit(logit(design.accuracy) + rng.normal(0.0, design.participant_sd))
        probabilities = channel(accuracy, k)
        for i in range(k):
            counts[j, i] = rng.multinomial(design.repetitions, probabilities[i])
    return counts


def coverage(design: Design, replications: int, n_boot: int = 2000, seed: int = 0,
             alpha: float = 0.05, bias_correction: str = "miller-madow") -> float:
    """Fraction of ``replications`` simulated datasets whose interval covers the truth."""
    truth = true_information(design)
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(replications):
        (low, high), _ = bootstrap_interval(simulate_counts(design, rng), bias_correction,
                                            n_boot, design.unit, rng, alpha)
        hits += low <= truth <= high
    return hits / replications


DESIGNS = (Design(6, 3, 0.5), Design(6, 3, 0.678), Design(8, 4, 0.503), Design(20, 10, 0.503),
           Design(40, 20, 0.678), Design(12, 5, 0.9), Design(4, 3, 0.678), Design(3, 3, 0.5),
           Design(40, 2, 0.5), Design(6, 10, 0.678, 1.0), Design(1, 20, 0.6, 0.0),
           Design(1, 60, 0.5, 0.0), Design(1, 10, 0.6, 0.0), Design(1, 5, 0.6, 0.0))


def main(argv: list[str]) -> None:
    replications = int(argv[0]) if argv else 400
    print(f"coverage of the 95 % information-transfer interval, {replications} datasets each")
    for design in DESIGNS:
        print(f"  {design.label:32s} true {true_information(design):.3f} bits  "
              f"coverage {100 * coverage(design, replications):5.1f} %", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
