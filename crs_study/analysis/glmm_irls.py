"""Penalised IRLS for the modes of the random effects, shared by the Laplace likelihoods
(:mod:`crs_study.analysis.glmm_laplace`, :mod:`crs_study.analysis.glmm_dense`): the binomial
kernel, the stopping rules and the step-halving that keeps each step an ascent of
``h(u) = sum_i kernel_i - u'u / 2`` (Bates et al. 2015, "Fitting linear mixed-effects models
using lme4", J Stat Softw 67(1), sec. 5.2, penalised iteratively reweighted least squares).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from scipy.special import expit

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


class StudyBatch(ABC):
    """What the Laplace likelihoods share as batches of ``S`` response vectors ``Y`` (S, n)
    with their warm starts ``u`` (S, q): their number, a subset as a batch of its own,
    penalised IRLS for the modes and the Laplace value at them (:meth:`evaluate`). A
    likelihood supplies its own form of the design at the current loadings (``design``,
    :meth:`_design`) and for it :meth:`_take` (its studies ``index``), :meth:`_linear` (``X
    beta + Z Lambda u`` per row), :meth:`_adjoint` (``Lambda' Z' v``), :meth:`_newton_step`,
    :meth:`_curvature` (``log det H`` and what the gradient needs of ``H``) and
    :meth:`_gradient`."""

    X: np.ndarray
    Y: np.ndarray
    u: np.ndarray
    m: np.ndarray
    q: int

    def __init__(self, X: np.ndarray, trials: np.ndarray, Y: np.ndarray, terms: list):
        """The data every Laplace likelihood holds: the fixed design ``X`` (n, p), the
        ``trials`` (n,), the successes ``Y`` (S, n; one study as (n,)) and the random
        terms' rows (at least one)."""
        self.X = np.asarray(X, dtype=float)
        self.m = np.asarray(trials, dtype=float)
        Y = np.asarray(Y, dtype=float)
        self.Y = Y[None] if Y.ndim == 1 else Y
        if not terms:
            raise ValueError("the Laplace likelihood needs a random term")
        self.terms = terms

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

    def _take(self, design, index):
        return design[index]

    @abstractmethod
    def _design(self, loadings: list[np.ndarray]):
        """The likelihood's form of ``Z Lambda`` at ``loadings`` (``T_k`` (S, r_k, r_k))."""

    @abstractmethod
    def _linear(self, offset, u, design) -> np.ndarray:
        """``X beta + Z Lambda u`` (S, n) from ``offset = X beta``."""

    @abstractmethod
    def _adjoint(self, v, design) -> np.ndarray:
        """``Lambda' Z' v`` (S, q) for row values ``v`` (S, n)."""

    @abstractmethod
    def _newton_step(self, w, rhs, design) -> np.ndarray:
        """``H^-1 rhs`` per study, ``H = Lambda' Z' W Z Lambda + I`` at weights ``w``."""

    @abstractmethod
    def _curvature(self, w, design, full: bool):
        """``(log det H (S,), curvature)`` at weights ``w``; ``curvature`` is what
        :meth:`_gradient` reads of ``H`` (only when ``full``)."""

    @abstractmethod
    def _gradient(self, u, p, w, design, curvature):
        """``(d/dbeta (S, p), [d/dT_k (S, r_k, r_k)])`` at the modes ``u``."""

    def evaluate(self, beta: np.ndarray, loadings: list[np.ndarray], grad: bool = True):
        """``(value (S,), d/dbeta (S, p), [d/dT_k (S, r_k, r_k)])`` (the last two None when
        ``grad`` is false); updates the warm starts ``u``. The Laplace approximation at the
        modes ``u`` (Bates et al. 2015, sec. 5.2): ``sum_i kernel_i - u'u / 2 - log det H /
        2``."""
        beta = np.asarray(beta, dtype=float)
        design = self._design([np.asarray(T, dtype=float) for T in loadings])
        offset = (self.X @ beta[:, :, None])[:, :, 0]      # per study: no batch-wide BLAS
        u = self._settled_modes(offset, design)
        eta = self._linear(offset, u, design)
        p = expit(eta)
        w = self.m * p * (1.0 - p)
        logdet, curvature = self._curvature(w, design, grad)
        value = (kernel(self.Y, self.m, eta).sum(axis=1) - 0.5 * np.einsum("sq,sq->s", u, u)
                 - 0.5 * logdet)
        if not grad:
            return value, None, None
        return (value,) + self._gradient(u, p, w, design, curvature)

    def _h(self, Y, offset, u, design) -> np.ndarray:
        eta = self._linear(offset, u, design)
        return kernel(Y, self.m, eta).sum(axis=1) - 0.5 * np.einsum("sq,sq->s", u, u)

    def modes(self, offset, design, u0, Y=None) -> np.ndarray:
        """Penalised IRLS from ``u0``; each study stops after a full step shorter than
        ``LAST_STEP`` (or any step below ``INNER_TOL``), frozen thereafter, so its answer
        never depends on its batch. A step longer than ``FULL_STEP`` in some coordinate is
        halved until ``h`` does not fall (:func:`step_fractions`)."""
        Y = self.Y if Y is None else Y
        u = u0.copy()
        active = np.arange(len(u))
        everyone = True
        for _ in range(INNER_MAXITER):
            if not len(active):
                break
            if everyone:
                o, ua, y, D = offset, u, Y, design
            else:
                o, ua, y, D = offset[active], u[active], Y[active], self._take(design, active)
            eta = self._linear(o, ua, D)
            p = expit(eta)
            mp = self.m * p
            step = self._newton_step(mp * (1.0 - p), self._adjoint(y - mp, D) - ua, D)
            size = np.max(np.abs(step), axis=1)
            if not (size > FULL_STEP).any():   # every step short: each taken whole
                if everyone:
                    u += step
                else:
                    u[active] = ua + step
                done = size < LAST_STEP        # INNER_TOL < LAST_STEP
            else:
                t = step_fractions(size, y, self.m, eta, ua,
                                   lambda long, tl, o=o, ua=ua, y=y, step=step, D=D: self._h(
                                       y[long], o[long], ua[long] + tl[:, None] * step[long],
                                       self._take(D, long)))
                u[active] = ua + t[:, None] * step
                done = (size * t < INNER_TOL) | ((t == 1.0) & (size < LAST_STEP))
            if done.any():
                active = active[~done]
                everyone = False
        return u

    def _settled_modes(self, offset, design) -> np.ndarray:
        """The modes from the warm starts, a diverged start retried from 0; kept as the
        warm starts of the next evaluation."""
        u = self.modes(offset, design, self.u)
        bad = ~np.isfinite(u).all(axis=1)
        if bad.any():
            u[bad] = self.modes(offset[bad], self._take(design, bad),
                                np.zeros((bad.sum(), self.q)), self.Y[bad])
        self.u = u
        return u
