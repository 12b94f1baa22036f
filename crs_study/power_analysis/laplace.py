"""The primary GLMM's Laplace log-likelihood for many simulated studies at once.

A power simulation fits the same model to thousands of datasets of one design: every
participant sees every (digit, condition) cell equally often. Aggregated to binomial cells the
successes of ``S`` studies are one array ``Y[s, p, d, c]`` (study, participant, digit,
condition) over the same trial counts ``m[d, c]``, so the objective of
:mod:`crs_study.analysis.glmm_core` (``CrossedFactors``, ``SingleFactor`` with the Laplace
approximation) can be evaluated for all of them in one pass of array operations, each study
with its own parameters. That is the whole saving: the same likelihood, the same maximum,
none of the per-fit interpreter overhead (``tests/test_power_laplace.py`` checks value and
gradient against ``glmm_core`` on random data and parameters).

The model (lme4's parameterisation, Bates et al. 2015, J. Stat. Softw. 67(1), eqs. 2-4)::

    logit P(correct) = x_c' beta + sigma_p u_p + sigma_d u_d,   u ~ N(0, I)

``l(theta) = sum_i k(y_i, m_i, eta_i*) - |u*|^2 / 2 - log det(H) / 2`` (the kernel
``k = y eta - m log(1 + e^eta)``, binomial constants left out as in ``glmm_core``) with the
conditional modes ``u*`` from penalised IRLS and ``H = Lambda Z'WZ Lambda + I``. ``H`` is
solved by the Schur complement of the participant block (diagonal, since each cell has one
participant): ``S = C - B' A^-1 B`` with ``A``, ``C`` the diagonal participant and digit
blocks and ``B[p, d] = sigma_p sigma_d sum_c w``; the digit block is ``D x D`` (ten digits),
batched over studies by numpy's ``linalg``.

Gradient (exact, by implicit differentiation of ``u*``; the same formulas as
``CrossedFactors._gradient``): ``dl/dt = dh/dt - tr(H^-1 dH/dt) / 2`` where ``dH/dt`` has the
term of ``dLambda/dt`` and ``Lambda Z' diag(w' deta/dt) Z Lambda`` with ``deta/dt = d_t eta +
Z Lambda du*/dt`` and ``du*/dt = H^-1 dg/dt`` (``g`` the score in ``u``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

#: Penalised IRLS stops when no coordinate of u moves more than this (glmm_core's tolerance).
INNER_TOL = 1e-11
INNER_MAXITER = 60
#: Inner Newton steps longer than this (in any coordinate of u) are checked by step-halving.
FULL_STEP = 0.05


@dataclass(frozen=True)
class CellDesign:
    """The design shared by the studies of one power point.

    ``X`` (C, k): the fixed-effects row of each condition (treatment coding: ``Intercept``
    and one indicator per other condition; a reduced model drops a column). ``trials`` (D, C):
    the trials each participant has in each (digit, condition) cell. ``digit_effect``: the
    model has a random intercept of digit besides the participant's.
    """

    X: np.ndarray
    trials: np.ndarray
    digit_effect: bool

    @property
    def n_fixed(self) -> int:
        return self.X.shape[1]

    @property
    def n_params(self) -> int:
        return self.n_fixed + 1 + int(self.digit_effect)

    def without(self, column: int) -> CellDesign:
        """The reduced model's design: fixed-effect ``column`` dropped."""
        return CellDesign(np.delete(self.X, column, axis=1), self.trials, self.digit_effect)


def kernel(y: np.ndarray, m: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """``y eta - m log(1 + e^eta)``, elementwise and stable (glmm_core's ``_kernel``)."""
    return y * eta - m * np.logaddexp(0.0, eta)


class _Schur:
    """``H = [[diag(A), B], [B', diag(C)]]`` per study, through ``S = diag(C) - B' A^-1 B``.

    ``S`` is solved directly while the modes are sought; at the modes (``full``) its inverse
    and log-determinant are formed once for the value, the gradient's solves and the entries
    of ``H^-1`` the gradient needs.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray | None, C: np.ndarray | None,
                 full: bool = False):
        self.A = A
        self.B = B
        self.logdet_A = np.log(A).sum(axis=1)
        if B is None:
            self.logdet = self.logdet_A
            return
        self.E = B / A[:, :, None]                                    # (S, P, D)
        S = -(np.swapaxes(B, 1, 2) @ self.E)      # matmul: ~15x einsum's time here
        idx = np.arange(S.shape[1])
        S[:, idx, idx] += C
        self.S = S
        self.S_inv = None
        if full:
            L = np.linalg.cholesky(S)                                 # raises if not PD
            self.logdet = self.logdet_A + 2.0 * np.log(
                np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)
            self.S_inv = np.linalg.inv(S)

    def solve(self, bp: np.ndarray, bd: np.ndarray | None):
        """``H^-1 [bp; bd]`` with ``bp`` (S, P[, k]) and ``bd`` (S, D[, k])."""
        if self.B is None:
            A = self.A if bp.ndim == 2 else self.A[:, :, None]
            return bp / A, None
        vector = bp.ndim == 2
        bp3 = bp[:, :, None] if vector else bp
        bd3 = bd[:, :, None] if vector else bd
        rhs = bd3 - np.swapaxes(self.E, 1, 2) @ bp3
        xd = np.linalg.solve(self.S, rhs) if self.S_inv is None else self.S_inv @ rhs
        xp = bp3 / self.A[:, :, None] - self.E @ xd
        if vector:
            return xp[:, :, 0], xd[:, :, 0]
        return xp, xd

    def inverse_blocks(self):
        """``(diag of H^-1 participant block (S, P), H^-1 participant-digit block (S, P, D),
        H^-1 digit block (S, D, D))`` (after ``full``)."""
        if self.B is None:
            return 1.0 / self.A, None, None
        F = self.E @ self.S_inv                                       # E S^-1
        Hpp = 1.0 / self.A + (F * self.E).sum(axis=2)
        return Hpp, -F, self.S_inv


@dataclass
class Warm:
    """Where each study's next penalised IRLS starts: the modes ``u`` (S, q) found at
    ``theta`` (S, n) and their derivative ``J = du*/dtheta`` (S, q, n) there, so the start
    at a new ``theta'`` is the first-order prediction ``u + J (theta' - theta)``."""

    u: np.ndarray
    theta: np.ndarray
    J: np.ndarray

    @classmethod
    def zeros(cls, S: int, q: int, n: int) -> Warm:
        return cls(np.zeros((S, q)), np.zeros((S, n)), np.zeros((S, q, n)))

    def take(self, index) -> Warm:
        return Warm(self.u[index].copy(), self.theta[index].copy(), self.J[index].copy())

    def put(self, index, other: Warm) -> None:
        self.u[index], self.theta[index], self.J[index] = other.u, other.theta, other.J

    def copy(self) -> Warm:
        return Warm(self.u.copy(), self.theta.copy(), self.J.copy())

    def start(self, theta: np.ndarray) -> np.ndarray:
        u = self.u + np.einsum("sqn,sn->sq", self.J, theta - self.theta)
        bad = ~np.isfinite(u).all(axis=1)
        u[bad] = 0.0
        return u


class BatchLaplace:
    """The Laplace log-likelihood kernel of ``S`` studies of one :class:`CellDesign`.

    ``Y`` (S, P, D, C) successes (study, participant, digit, condition; held internally as
    (S, C, P, D), digits innermost, so the sums over conditions are sums of slabs).
    :meth:`evaluate` takes ``theta`` (S, k + 1 [+ 1]) laid out as ``glmm_core``'s (fixed
    effects, then sigma of participant[, of digit]); sigmas may be any real (the likelihood
    is even in each). Each study's conditional modes are kept as the warm start of its next
    evaluation (``self.warm``); ``glmm_core`` keeps them too.
    """

    def __init__(self, design: CellDesign, Y: np.ndarray):
        Y = np.asarray(Y, dtype=float)
        S, P, D, C = Y.shape
        self.design = design
        self.Y = np.ascontiguousarray(Y.transpose(0, 3, 1, 2))
        self.m = np.asarray(design.trials, dtype=float).T[None, :, None, :]   # (1, C, 1, D)
        self.n_participants, self.n_digits = P, D
        self.warm = Warm.zeros(S, P + (D if design.digit_effect else 0), design.n_params)

    def subset(self, index: np.ndarray) -> BatchLaplace:
        """The studies ``index`` (their warm starts included) as a batch of their own."""
        out = BatchLaplace.__new__(BatchLaplace)
        out.design, out.m = self.design, self.m
        out.n_participants, out.n_digits = self.n_participants, self.n_digits
        out.Y = self.Y[index]
        out.warm = self.warm.take(index)
        return out

    # ------------------------------------------------------------------ pieces
    def _split(self, theta: np.ndarray):
        k = self.design.n_fixed
        beta, sp = theta[:, :k], theta[:, k]
        sd = theta[:, k + 1] if self.design.digit_effect else None
        return beta, sp, sd

    def _eta(self, offset, sp, sd, u):
        """``eta`` (S, C, P, D) from the condition offsets (S, C) and the modes."""
        P = self.n_participants
        eta = offset[:, :, None, None] + (sp[:, None] * u[:, :P])[:, None, :, None]
        if sd is not None:
            eta = eta + (sd[:, None] * u[:, P:])[:, None, None, :]
        return eta

    def _h(self, Y, offset, sp, sd, u) -> np.ndarray:
        """The conditional log density ``sum k - |u|^2 / 2`` per study."""
        eta = self._eta(offset, sp, sd, u)
        return kernel(Y, self.m, eta).sum(axis=(1, 2, 3)) - 0.5 * np.einsum("sq,sq->s", u, u)

    @staticmethod
    def _factor(w_pd, sp, sd, full: bool = False) -> _Schur:
        """``H`` from the weights summed over conditions, ``w_pd`` (S, P, D)."""
        A = sp[:, None] ** 2 * w_pd.sum(axis=2) + 1.0
        if sd is None:
            return _Schur(A, None, None)
        C = sd[:, None] ** 2 * w_pd.sum(axis=1) + 1.0
        return _Schur(A, (sp * sd)[:, None, None] * w_pd, C, full)

    def _score(self, r_pd, sp, sd, u):
        """The score in ``u``: ``Lambda Z' r - u`` as (participant part, digit part)."""
        P = self.n_participants
        gp = sp[:, None] * r_pd.sum(axis=2) - u[:, :P]
        gd = None if sd is None else sd[:, None] * r_pd.sum(axis=1) - u[:, P:]
        return gp, gd

    def _modes(self, offset, sp, sd, u0):
        """Penalised IRLS, each study stopped when its step is below ``INNER_TOL`` (frozen
        thereafter, so a study's answer never depends on its batch). A step longer than
        ``FULL_STEP`` in some coordinate is halved until the conditional density does not
        fall (as glmm_core); shorter steps, inside the region where Newton's method on this
        strongly concave function converges, are taken whole."""
        u = u0.copy()
        current = np.full(len(u), np.nan)           # h at u, computed when a step needs it
        active = np.ones(len(u), dtype=bool)
        for _ in range(INNER_MAXITER):
            a = np.flatnonzero(active)
            if not len(a):
                break
            o, s_p = offset[a], sp[a]
            s_d = None if sd is None else sd[a]
            ua, Y = u[a], self.Y[a]
            p = expit(self._eta(o, s_p, s_d, ua))
            mp = self.m * p
            r_pd = (Y - mp).sum(axis=1)
            w_pd = (mp * (1.0 - p)).sum(axis=1)
            gp, gd = self._score(r_pd, s_p, s_d, ua)
            xp, xd = self._factor(w_pd, s_p, s_d).solve(gp, gd)
            step = xp if xd is None else np.concatenate([xp, xd], axis=1)
            size = np.max(np.abs(step), axis=1)
            long = np.flatnonzero(size > FULL_STEP)
            t = np.ones(len(a))
            if len(long):
                t[long] = self._halve(Y[long], o[long], s_p[long],
                                      None if s_d is None else s_d[long], ua[long],
                                      step[long], current[a[long]])
            u[a] = ua + t[:, None] * step
            current[a] = np.nan
            if len(long):
                current[a[long]] = self._last_h
            done = np.max(np.abs(t[:, None] * step), axis=1) < INNER_TOL
            active[a[done]] = False
        return u

    def _halve(self, Y, offset, sp, sd, u, step, cur):
        """Step lengths halved until ``h`` does not fall (per study); sets ``_last_h``."""
        missing = ~np.isfinite(cur)
        if missing.any():
            cur = cur.copy()
            cur[missing] = self._h(Y[missing], offset[missing], sp[missing],
                                   None if sd is None else sd[missing], u[missing])
        t = np.ones(len(u))
        for _ in range(31):
            value = self._h(Y, offset, sp, sd, u + t[:, None] * step)
            worse = value < cur - 1e-12 * (1.0 + np.abs(cur))
            if not worse.any():
                break
            t = np.where(worse, 0.5 * t, t)
        self._last_h = value
        return t

    # ------------------------------------------------------------------ objective
    def evaluate(self, theta: np.ndarray, grad: bool = True):
        """``(value (S,), gradient (S, n) or None)`` at ``theta`` (S, n); updates ``warm``."""
        X = self.design.X
        beta, sp, sd = self._split(theta)
        offset = beta @ X.T                                              # (S, C)
        u = self._modes(offset, sp, sd, self.warm.start(theta))
        eta = self._eta(offset, sp, sd, u)
        p = expit(eta)
        w = self.m * p * (1.0 - p)
        schur = self._factor(w.sum(axis=1), sp, sd, full=True)
        value = (kernel(self.Y, self.m, eta).sum(axis=(1, 2, 3))
                 - 0.5 * np.einsum("sq,sq->s", u, u) - 0.5 * schur.logdet)
        self.warm.u, self.warm.theta = u, theta.copy()
        if not grad:
            return value, None
        g, J = self._gradient(theta, u, p, w, schur)
        self.warm.J = J
        return value, g

    def _gradient(self, theta, u, p, w, schur: _Schur):
        """The exact gradient (S, n) and ``du*/dtheta`` (S, q, n) (module docstring)."""
        X, P = self.design.X, self.n_participants
        beta, sp, sd = self._split(theta)
        r = self.Y - self.m * p                                           # (S, C, P, D)
        dw = w * (1.0 - 2.0 * p)
        Wpd = w.sum(axis=1)                                               # (S, P, D)
        Wp = Wpd.sum(axis=2)                                              # (S, P)
        r_pd = r.sum(axis=1)
        Zr_p = r_pd.sum(axis=2)
        Hpp, Hpd, Hdd = schur.inverse_blocks()
        # d_i = a_i' H^-1 a_i, a_i the row of Z Lambda of cell i
        if sd is None:
            d = (sp[:, None] ** 2 * Hpp)[:, :, None]                      # (S, P, 1)
        else:
            Hdd_diag = np.diagonal(Hdd, axis1=1, axis2=2)
            d = (sp[:, None, None] ** 2 * Hpp[:, :, None]
                 + 2.0 * (sp * sd)[:, None, None] * Hpd
                 + sd[:, None, None] ** 2 * Hdd_diag[:, None, :])         # (S, P, D)
        q = dw * d[:, None, :, :]                                          # (S, C, P, D)
        q_pd = q.sum(axis=1)
        q_p, q_d = q_pd.sum(axis=2), q_pd.sum(axis=1)

        def chain(dup, dud):
            """``sum_i q_i (Z Lambda du)_i``: the part of ``sum_i q_i deta_i`` through u*
            (``dup`` (S, P) or (S, P, k), ``dud`` likewise)."""
            scale = (slice(None),) + (None,) * (dup.ndim - 2)
            out = sp[scale] * np.einsum("sp,sp...->s...", q_p, dup)
            if sd is not None:
                out = out + sd[scale] * np.einsum("sd,sd...->s...", q_d, dud)
            return out

        # fixed effects: dg/dbeta = -Lambda Z'W X
        w_cp = w.sum(axis=3)                                              # (S, C, P)
        bp = -sp[:, None, None] * np.einsum("scp,ck->spk", w_cp, X)      # (S, P, k)
        bd = None if sd is None else -sd[:, None, None] * np.einsum(
            "scd,ck->sdk", w.sum(axis=2), X)
        dup_b, dud_b = schur.solve(bp, bd)
        g_beta = (r.sum(axis=(2, 3)) @ X
                  - 0.5 * (q.sum(axis=(2, 3)) @ X + chain(dup_b, dud_b)))
        grads, jac_p, jac_d = [g_beta], [dup_b], [dud_b]

        # participant sigma: dg/dsigma_p = E_p Z'r - Lambda Z'W Z_p u_p
        up = u[:, :P]
        trace = sp * np.einsum("sp,sp->s", Wp, Hpp)
        if sd is not None:
            trace = trace + sd * np.einsum("spd,spd->s", Wpd, Hpd)
        bp = Zr_p - sp[:, None] * Wp * up
        bd = None if sd is None else -sd[:, None] * np.einsum("spd,sp->sd", Wpd, up)
        dup, dud = schur.solve(bp, bd)
        grads.append(np.einsum("sp,sp->s", up, Zr_p) - trace
                     - 0.5 * (np.einsum("sp,sp->s", q_p, up) + chain(dup, dud)))
        jac_p.append(dup[:, :, None])
        jac_d.append(None if dud is None else dud[:, :, None])

        if sd is not None:       # digit sigma: dg/dsigma_d = E_d Z'r - Lambda Z'W Z_d u_d
            ud = u[:, P:]
            Wd = Wpd.sum(axis=1)
            Zr_d = r_pd.sum(axis=1)
            trace = sp * np.einsum("spd,spd->s", Wpd, Hpd) + sd * np.einsum(
                "sd,sd->s", Wd, np.diagonal(Hdd, axis1=1, axis2=2))
            bp = -sp[:, None] * np.einsum("spd,sd->sp", Wpd, ud)
            bd = Zr_d - sd[:, None] * Wd * ud
            dup, dud = schur.solve(bp, bd)
            grads.append(np.einsum("sd,sd->s", ud, Zr_d) - trace
                         - 0.5 * (np.einsum("sd,sd->s", q_d, ud) + chain(dup, dud)))
            jac_p.append(dup[:, :, None])
            jac_d.append(dud[:, :, None])
        g = np.concatenate([grads[0]] + [x[:, None] for x in grads[1:]], axis=1)
        J = np.concatenate(jac_p, axis=2)
        if sd is not None:
            J = np.concatenate([J, np.concatenate(jac_d, axis=2)], axis=1)
        return g, J
