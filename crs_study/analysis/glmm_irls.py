"""Penalised IRLS for the modes of the random effects, shared by the Laplace likelihoods
(:mod:`crs_study.analysis.glmm_laplace`, :mod:`crs_study.analysis.glmm_dense`): the binomial
kernel, the stopping rules and the step-halving that keeps each step an ascent of
``h(u) = sum_i kernel_i - u'u / 2`` (Bates et al. 2015, "Fitting linear mixed-effects models
using lme4", J Stat Softw 67(1), sec. 5.2, penalised iteratively reweighted least squares).
"""

from __future__ import annotations

import numpy as np

#: Penalised IRLS stops when no coordinate of u moves more than this.
INNER_TOL = 1e-11
#: A full Newton step shorter than this is the last one: on this strongly concave function
#: the next would be of the order of its square (1e-9), which moves ``l`` only through
#: ``log det H`` (``h`` is stationary at the mode): a thousandth of the fits' gradient
#: tolerance. A differenced Hessian's points (moved 1e-5) then take one inner step, not two.
LAST_STEP = 3e-5
INNER_MAXITER = 60
#: Newton steps longer than this (in any coordinate of u) are checked for ascent first;
#: shorter ones lie where Newton's method on this strongly concave function converges.
FULL_STEP = 0.05


def kernel(y: np.ndarray, m: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """``y eta - m log(1 + e^eta)``, elementwise and stable."""
    return y * eta - m * np.logaddexp(0.0, eta)


def step_fractions(size, y, m, eta, u, h_at) -> np.ndarray:
    """The fraction of each study's IRLS step taken: 1 where the step is no longer than
    :data:`FULL_STEP` in any coordinate (``size``), else halved, at most 31 times, until
    ``h(u) = sum kernel - u'u / 2`` does not fall; ``h_at(long, t)`` is ``h`` at
    ``u + t step`` for the studies ``long``, ``eta`` the linear predictor at ``u``."""
    t = np.ones(len(size))
    long = np.flatnonzero(size > FULL_STEP)
    if not len(long):
        return t
    current = kernel(y[long], m, eta[long]).sum(axis=1) - 0.5 * np.einsum(
        "sq,sq->s", u[long], u[long])
    for _ in range(31):
        worse = ~(h_at(long, t[long]) >= current - 1e-12 * (1.0 + np.abs(current)))
        if not worse.any():
            break
        t[long[worse]] *= 0.5
    return t


class StudyBatch:
    """What the Laplace likelihoods share as batches of ``S`` response vectors ``Y`` (S, n)
    with their warm starts ``u`` (S, q): their number, and a subset as a batch of its own."""

    Y: np.ndarray
    u: np.ndarray

    @property
    def n_studies(self) -> int:
        return len(self.Y)

    def subset(self, index):
        """The studies ``index`` (their warm starts included) as a likelihood of their own."""
        out = type(self).__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.Y = self.Y[index]
        out.u = self.u[index].copy()
        return out
