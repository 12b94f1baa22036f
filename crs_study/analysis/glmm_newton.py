"""Newton's method for many maximisations at once, each study on its own.

:func:`newton` maximises an objective of ``S`` parameter vectors (a batch of studies, or one
fit) over the coordinates not held: the exact gradient, the Hessian by forward differences of
it (refreshed every ``REFRESH_EVERY`` iterations where the last step did not cut the
gradient by ``FAST``, BFGS updates between: Nocedal & Wright 2006, Numerical Optimization,
eq. 6.19), the Newton step made an ascent step where the
Hessian is not negative definite (eigenvalues reflected and floored) and no longer than
``MAX_STEP``, a step-halving line search; each study frozen once its gradient is below
``GRADIENT_TOL``, so its answer never depends on the others.

The objective provides ``evaluate(theta, grad) -> (value (S,), gradient (S, n))``,
``subset(index)``, ``normalised(theta)`` (the parameters of the same model it prefers: lme4's
non-negative diagonals), ``warm``, an array (S, ...) of per-study state (the conditional
modes) that is saved and restored around the trial points, and ``gradients(theta, rows)``
(K, n), the gradient at each ``theta[i]`` of study ``rows[i]`` from that study's warm start
(left as it was); optionally ``capped`` (the loading entries) and ``diagonals(held)`` (S,
n), the diagonal loadings whose zero is a boundary of the problem with ``held`` held
(:func:`_short_of_zero`).
"""

from __future__ import annotations

import numpy as np

#: A study's fit is done when no free coordinate of the gradient exceeds this.
GRADIENT_TOL = 1e-6
MAX_ITERATIONS = 40
#: The Hessian is taken afresh by differences every this many iterations (BFGS between):
#: near a boundary (l ~ a sigma^2 + b sigma^4) the secant updates alone converge slowly.
REFRESH_EVERY = 4
#: ... unless the last step cut the largest gradient entry to this share of itself or less:
#: the secant updates are then converging superlinearly, and a fresh matrix costs an
#: evaluation per parameter for nothing.
FAST = 0.1
#: Longest step in any coordinate (log-odds or SD units) in one iteration.
MAX_STEP = 1.0
#: Largest share of its size a diagonal loading may lose in one step (never its sign).
TO_ZERO = 0.9
#: Halvings of a step before the line search gives up (the study is then stalled): a
#: millionth of Newton's step that still does not rise lies where the objective's value is
#: rounding noise, and further halvings "succeed" on that noise for dozens of iterations
#: without moving.
MAX_HALVINGS = 20
#: Largest size of any entry of a loading ``T_k`` (SD units on the logit scale). Where a
#: term's random effects are separated (a level whose responses are all correct or all
#: wrong, with few levels) the likelihood rises without bound as its SD grows; the supremum
#: lies at infinity, approached ever more slowly (an optimiser crawls there for thousands of
#: evaluations). An SD of 10 logits spans probabilities from 1e-9 to 1 - 1e-9 across two
#: SDs: no human difference is near it, the largest of the lme4 corpora is 2.2. A fit that
#: reaches it says so (:func:`at_cap`).
THETA_CAP = 10.0


def newton(objective, theta0: np.ndarray, held: np.ndarray,
            N0: np.ndarray | None = None, face_sd: float | None = None):
    """Maxima over the free coordinates (``~held``) of every study.

    The first step is Newton's with the Hessian by forward differences of the exact
    gradient; later steps update that matrix by BFGS (the secant pairs of the accepted
    steps, skipped where the curvature condition fails), so an iteration costs one
    evaluation of value and gradient when its full step is taken; ``N0`` (S, n, n), a
    negative Hessian known to be near (a related model's), replaces the first differences.
    Returns ``(theta, value, converged, iterations, N)`` with ``N`` each study's last
    matrix; ``objective.warm`` holds the conditional modes at ``theta``.

    ``face_sd``: a study whose step was shortened short of zero (:func:`_short_of_zero`) and
    left a diagonal loading below ``face_sd`` stops there, not converged. Its maximum is on
    that face or near it, which Newton's method approaches only geometrically (each step
    ``TO_ZERO`` of the way), every other coordinate's step shortened with it; the caller
    decides on the face, where the problem is regular.
    """
    S, n = theta0.shape
    free = ~held
    diagonals = getattr(objective, "diagonals", None)    # (S, n): zero is a boundary
    diagonal = None if diagonals is None else diagonals(held)
    capped = getattr(objective, "capped", None)   # (n,) True for the loading entries
    theta = theta0.copy() if capped is None else np.where(   # a held value stays as given
        capped & free, np.clip(theta0, -THETA_CAP, THETA_CAP), theta0)
    value, g = objective.evaluate(theta)
    g = np.where(free, g, 0.0)
    converged = np.zeros(S, dtype=bool)
    iterations = np.zeros(S, dtype=int)
    N = None if N0 is None else _held_out(N0.copy(), free)
    N_last = np.zeros((S, n, n))
    fast = np.zeros(S, dtype=bool)      # the last step cut the gradient by FAST or more
    active = np.arange(S)
    sub = objective.subset(active)
    for iteration in range(MAX_ITERATIONS):
        th, v, ga = theta[active], value[active], g[active]
        if capped is not None:     # at the cap, a gradient pushing outward is satisfied
            pinned = capped & (np.abs(th) >= THETA_CAP) & (th * ga > 0)
            if pinned.any():
                ga = np.where(pinned, 0.0, ga)
        else:
            pinned = np.zeros_like(held[active])
        largest = np.max(np.abs(ga), axis=1)     # NaN or inf where any entry is
        done = largest < GRADIENT_TOL
        bad = ~(np.isfinite(v) & np.isfinite(largest))
        converged[active[done & ~bad]] = True
        keep = ~done & ~bad
        if not keep.all():
            objective.warm[active[~keep]] = sub.warm[~keep]
            if N is not None:
                N_last[active[~keep]] = N[~keep]
            active, th, v, ga = active[keep], th[keep], v[keep], ga[keep]
            largest, pinned = largest[keep], pinned[keep]
            sub = sub.subset(np.flatnonzero(keep))
            N = None if N is None else N[keep]
        if not len(active):
            break
        iterations[active] += 1
        if N is None:
            N = _negative_hessian(sub, th, ga, free[active])
        elif iteration and iteration % REFRESH_EVERY == 0:
            rows = np.flatnonzero(~fast[active])     # the secant updates are not converging
            if len(rows):
                N[rows] = _negative_hessian(sub.subset(rows), th[rows], ga[rows],
                                            free[active][rows])
        elif iteration == 0:                # N0 given: differences only where it is unusable
            unusable = np.linalg.eigvalsh(N)[:, 0] <= 0
            if unusable.any():
                rows = np.flatnonzero(unusable)
                N[rows] = _negative_hessian(sub.subset(rows), th[rows], ga[rows],
                                            free[active][rows])
        free_a = free[active]
        moving = free_a & ~pinned
        # the step of the problem with the pinned loadings held (their rows and columns
        # out of N), not the full step clipped: clipping leaves a direction that is no
        # longer Newton's and the iteration crawls along the cap
        step = _solve(_held_out(N.copy(), moving) if pinned.any() else N, ga, moving)
        shortened = np.zeros(len(active), dtype=bool)
        diagonal_a = None if diagonal is None else diagonal[active]
        if diagonal_a is not None:
            step, shortened = _short_of_zero(step, th, diagonal_a)
        if capped is not None:
            step = np.where(capped & moving, np.clip(th + step, -THETA_CAP, THETA_CAP) - th,
                            step)
        th_new, v_new, g_new, ok = _line_search(sub, th, v, step)
        g_new = np.where(free_a, g_new, 0.0)
        N = _bfgs(N, th_new - th, ga - g_new, ok)
        if ok.all():
            theta[active], value[active], g[active] = th_new, v_new, g_new
        else:
            theta[active] = np.where(ok[:, None], th_new, th)
            value[active] = np.where(ok, v_new, v)
            g[active] = np.where(ok[:, None], g_new, ga)
        fast[active] = ok & (np.max(np.abs(g_new), axis=1) < FAST * largest)
        go_on = ok.copy()
        if face_sd is not None and diagonal_a is not None:
            go_on &= ~(shortened & (diagonal_a & (np.abs(th_new) < face_sd)).any(axis=1))
        if not go_on.all():                    # stalled, or stopped at a face
            objective.warm[active[~go_on]] = sub.warm[~go_on]
            N_last[active[~go_on]] = N[~go_on]
            active, N = active[go_on], N[go_on]
            sub = sub.subset(np.flatnonzero(go_on))
    else:
        objective.warm[active] = sub.warm
        if N is not None:
            N_last[active] = N
    return objective.normalised(theta), value, converged, iterations, N_last


def _held_out(N: np.ndarray, free: np.ndarray) -> np.ndarray:
    """``N`` with the held coordinates' rows and columns made the identity's."""
    mask = free[:, :, None] & free[:, None, :]
    N = np.where(mask, N, 0.0)
    idx = np.arange(N.shape[1])
    N[:, idx, idx] = np.where(free, N[:, idx, idx], 1.0)
    return N


def _negative_hessian(sub, theta, g, free) -> np.ndarray:
    """``-d2 l / dtheta2`` over the free coordinates by forward differences of the exact
    gradient (identity rows and columns for the held ones): the points of every study and
    coordinate in one call of ``sub.gradients``, each from its study's warm start."""
    S, n = theta.shape
    H = np.zeros((S, n, n))
    columns = [j for j in range(n) if free[:, j].any()]
    if columns:
        h = 1e-5 * np.maximum(1.0, np.abs(theta[:, columns]))            # (S, m)
        shifted = np.repeat(theta[None], len(columns), axis=0)             # (m, S, n)
        for k, j in enumerate(columns):
            shifted[k, :, j] += h[:, k]
        gj = sub.gradients(shifted.reshape(-1, n), np.tile(np.arange(S), len(columns)))
        gj = gj.reshape(len(columns), S, n)
        for k, j in enumerate(columns):
            H[:, :, j] = (gj[k] - g) / h[:, k, None]
    return _held_out(-0.5 * (H + np.swapaxes(H, 1, 2)), free)


def _solve(N: np.ndarray, g: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The ascent step ``N^-1 g``, ``N`` made positive definite where it is not (eigenvalues
    reflected and floored: the usual modified Newton step), shortened to ``MAX_STEP`` in its
    longest coordinate (a flat direction would otherwise send it far off, where every
    evaluation costs many inner iterations for nothing)."""
    lam, V = np.linalg.eigh(N)
    top = np.max(np.abs(lam), axis=1, keepdims=True)
    lam = np.maximum(np.abs(lam), 1e-8 * np.maximum(top, 1.0))
    step = np.where(free, np.einsum("sij,sj->si", V, np.einsum("sji,sj->si", V, g) / lam), 0.0)
    longest = np.max(np.abs(step), axis=1, keepdims=True)
    return step * np.minimum(1.0, MAX_STEP / np.maximum(longest, 1e-300))


def _short_of_zero(step: np.ndarray, theta: np.ndarray, diagonal: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``step`` shortened so that no diagonal loading loses more than ``TO_ZERO`` of its size
    or changes sign (the interior-point "fraction to the boundary" rule: Nocedal & Wright
    2006, eq. 16.66). The likelihood is even in a column's sign, so a diagonal that crosses
    0 lands on the mirror image of the same model, and at 0 itself its gradient vanishes:
    crossing costs iterations and gains nothing. A boundary optimum is still approached
    geometrically, and the boundary is decided on its face. Returns the step and where it
    was shortened. ``diagonal`` (S, n) marks the diagonals whose zero is a boundary."""
    toward = diagonal & (theta != 0.0) & (theta * step < 0.0)
    if not toward.any():
        return step, np.zeros(len(step), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(toward, TO_ZERO * np.abs(theta) / np.abs(step), np.inf)
    t = np.minimum(1.0, room.min(axis=1, initial=np.inf))
    return step * t[:, None], t < 1.0


def _bfgs(N: np.ndarray, s: np.ndarray, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """BFGS update of the negative Hessian ``N`` with step ``s`` and gradient change ``y =
    g_old - g_new`` (Nocedal & Wright 2006, eq. 6.19), where ``y's > 0``."""
    ys = np.einsum("si,si->s", y, s)
    Ns = np.einsum("sij,sj->si", N, s)
    sNs = np.einsum("si,si->s", s, Ns)
    good = ok & (ys > 1e-12 * np.sqrt(np.einsum("si,si->s", y, y) * np.einsum(
        "si,si->s", s, s))) & (sNs > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        update = (y[:, :, None] * y[:, None, :] / ys[:, None, None]
                  - Ns[:, :, None] * Ns[:, None, :] / sNs[:, None, None])
    return np.where(good[:, None, None], N + update, N)


def _line_search(sub, theta, value, step):
    """The full step where the objective does not fall there (value and gradient in one
    evaluation), else the step halved until it does (values only, then the gradient at the
    point taken). ``ok`` False where ``MAX_HALVINGS`` halvings found no such point."""
    S = len(theta)
    warm = sub.warm.copy()
    trial = theta + step
    v, g = sub.evaluate(trial)
    ok = _not_lower(v, value)
    if ok.all():         # every full step taken (the usual case): nothing to halve
        return trial, v, g, ok
    candidate = np.where(ok[:, None], trial, theta)
    new_value = np.where(ok, v, value)
    new_g = np.where(ok[:, None], g, 0.0)
    best = sub.warm
    best[~ok] = warm[~ok]
    pending = np.flatnonzero(~ok)
    t = np.ones(S)
    halved = np.zeros(S, dtype=bool)
    for _ in range(MAX_HALVINGS):
        if not len(pending):
            break
        t[pending] *= 0.5
        trial = theta[pending] + t[pending, None] * step[pending]
        part = sub.subset(pending)
        part.warm = warm[pending].copy()
        v, _ = part.evaluate(trial, grad=False)
        good = _not_lower(v, value[pending])
        accepted = pending[good]
        ok[accepted] = halved[accepted] = True
        candidate[accepted] = trial[good]
        new_value[accepted] = v[good]
        best[accepted] = part.warm[good]
        pending = pending[~good]
    if halved.any():
        rows = np.flatnonzero(halved)
        part = sub.subset(rows)
        part.warm = best[rows].copy()
        new_value[rows], new_g[rows] = part.evaluate(candidate[rows])
        best[rows] = part.warm
    sub.warm = best
    return candidate, new_value, new_g, ok


def _not_lower(v: np.ndarray, value: np.ndarray) -> np.ndarray:
    return np.isfinite(v) & (v >= value - 1e-12 * (1.0 + np.abs(value)))
