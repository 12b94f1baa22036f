"""Random-effects terms of the GLMM: what varies by participant and by symbol, and how.

A term is lme4's ``(1 + condition | participant)``: for every level of a grouping factor a
vector of random effects, one per column of the term's design (the intercept and a slope per
condition contrast), with a covariance matrix ``Sigma`` of its own. lme4 parameterises
``Sigma = T T'`` by its lower-triangular Cholesky factor ``T`` and calls the entries of ``T``,
column by column, theta (Bates, Maechler, Bolker & Walker 2015, "Fitting linear mixed-effects
models using lme4", J. Stat. Softw. 67(1), sec. 2.2 and 3.1); so does this package. An
uncorrelated term, lme4's ``(1 + condition || participant)``, has a diagonal ``T``: one SD per
column, no correlation. A term of one column is a random intercept, its theta the SD.

:class:`RandomTerm` is one term (grouping column, design columns, correlated or not),
:func:`parse_random` reads lme4's notation for a whole random part, and the helpers below move
between theta, ``T``, ``Sigma`` and the SDs and correlations a report shows.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from crs_study.errors import AnalysisError

#: The name of the intercept column of a design, as patsy and the primary test write it.
INTERCEPT = "Intercept"


@dataclass(frozen=True)
class RandomTerm:
    """``(columns | group)`` (``correlated``) or ``(columns || group)``.

    ``group`` is the grouping column of the data; ``columns`` name the term's design columns
    (``"Intercept"`` for the random intercept, then e.g. ``"condition[crs]"``); ``design`` is
    how to build them: a patsy right-hand side (``"1 + condition"``), or None when the caller
    hands the design columns to the fit itself.
    """

    group: str
    columns: tuple[str, ...] = (INTERCEPT,)
    correlated: bool = True
    design: str | None = None

    def __post_init__(self) -> None:
        if not self.columns:
            raise AnalysisError(f"random term of {self.group!r} has no columns")
        if len(set(self.columns)) != len(self.columns):
            raise AnalysisError(f"random term of {self.group!r} repeats a column: "
                                f"{list(self.columns)!r}")

    @property
    def size(self) -> int:
        """Random effects per level (the order of ``Sigma``)."""
        return len(self.columns)

    @property
    def is_intercept(self) -> bool:
        """A random intercept alone."""
        return self.columns == (INTERCEPT,)

    @property
    def slopes(self) -> tuple[str, ...]:
        """The columns other than the intercept."""
        return tuple(c for c in self.columns if c != INTERCEPT)

    @property
    def entries(self) -> tuple[tuple[int, int], ...]:
        """The ``(row, column)`` of ``T`` of each theta, in lme4's order: the lower triangle
        column by column when correlated, the diagonal when not."""
        r = self.size
        if not self.correlated or r == 1:
            return tuple((j, j) for j in range(r))
        return tuple((i, j) for j in range(r) for i in range(j, r))

    @property
    def n_theta(self) -> int:
        return len(self.entries)

    def shown_group(self) -> str:
        """The group as a report names it (``participant``, not ``participant_id``)."""
        return self.group.removesuffix("_id")

    def label(self) -> str:
        """lme4's notation: ``(1 + condition | participant)``, ``(1 || symbol)``..."""
        parts = ["1" if c == INTERCEPT else _column_label(c) for c in self.columns]
        if INTERCEPT not in self.columns:
            parts.insert(0, "0")
        bar = "|" if self.correlated or self.size == 1 else "||"
        return f"({' + '.join(dict.fromkeys(parts))} {bar} {self.shown_group()})"

    def without(self, column: str) -> RandomTerm | None:
        """The term without ``column`` (None when nothing is left)."""
        rest = tuple(c for c in self.columns if c != column)
        if not rest:
            return None
        return RandomTerm(self.group, rest, self.correlated, self.design)

    def uncorrelated(self) -> RandomTerm:
        return RandomTerm(self.group, self.columns, False, self.design)

    def theta_names(self) -> list[str]:
        """A name per theta: ``sd participant (Intercept)`` for a diagonal entry of a
        diagonal ``T``; lme4's ``participant.condition[crs].(Intercept)`` style otherwise."""
        names = []
        for i, j in self.entries:
            if i == j and (not self.correlated or self.size == 1):
                names.append(f"sd {self.shown_group()} {_effect_label(self.columns[i])}")
            else:
                names.append(f"T {self.shown_group()} {_effect_label(self.columns[i])}."
                             f"{_effect_label(self.columns[j])}")
        return names


def _column_label(column: str) -> str:
    """``condition[crs]`` -> ``condition`` (the factor behind a contrast column)."""
    return column.split("[", 1)[0] if "[" in column else column


def _effect_label(column: str) -> str:
    return "(Intercept)" if column == INTERCEPT else column


def structure_label(terms: Sequence[RandomTerm]) -> str:
    """The random part in lme4's notation: ``(1 + condition | participant) + (1 | digit)``."""
    return " + ".join(t.label() for t in terms) if terms else "none"


# ----------------------------------------------------------------------------- parsing
_TERM = re.compile(r"\(\s*([^()|]*?)\s*(\|\|?)\s*([A-Za-z_][A-Za-z0-9_.]*)\s*\)")


def parse_random(text: str) -> list[tuple[str, str, bool]]:
    """lme4's random part (``"(1 + condition | participant) + (1 | digit)"``) as a list of
    ``(design, group, correlated)``, ``design`` a patsy right-hand side (``"1 + condition"``).

    ``x`` alone means ``1 + x`` (lme4 adds the intercept unless ``0 +`` or ``- 1`` removes
    it); ``||`` makes the term's effects uncorrelated. Anything else (nested bars,
    interactions of groups, a term outside parentheses) is an :class:`AnalysisError` naming
    the part it could not read.
    """
    if not isinstance(text, str) or not text.strip():
        raise AnalysisError(f"random effects: expected lme4 terms such as "
                            f"'(1 + condition | participant)', got {text!r}")
    terms = []
    position = 0
    stripped = text.strip()
    for match in _TERM.finditer(stripped):
        between = stripped[position:match.start()].strip()
        if between not in ("", "+") or (terms and between != "+"):
            raise AnalysisError(f"random effects {text!r}: cannot read {between!r}; expected "
                                f"terms such as '(1 + condition | participant)' joined by +")
        lhs, bar, group = match.groups()
        if not lhs:
            raise AnalysisError(f"random effects {text!r}: the term of {group!r} has nothing "
                                f"before the bar; write '(1 | {group})'")
        terms.append((lhs, group, bar == "|"))
        position = match.end()
    rest = stripped[position:].strip()
    if rest or not terms:
        raise AnalysisError(f"random effects {text!r}: cannot read {rest or text!r}; expected "
                            f"terms such as '(1 + condition | participant)' joined by +")
    groups = [g for _, g, _ in terms]
    if len(set(groups)) != len(groups):
        raise AnalysisError(f"random effects {text!r}: a grouping factor appears twice; give "
                            f"each one term")
    return terms


# ----------------------------------------------------------------------------- numbers
def loading(term: RandomTerm, theta: np.ndarray) -> np.ndarray:
    """``T`` (..., r, r) of ``term`` from its theta (..., n_theta)."""
    theta = np.asarray(theta, dtype=float)
    T = np.zeros(theta.shape[:-1] + (term.size, term.size))
    rows, cols = zip(*term.entries, strict=True)
    T[..., list(rows), list(cols)] = theta
    return T


def theta_of(term: RandomTerm, T: np.ndarray) -> np.ndarray:
    """The theta of ``term`` read off ``T`` (..., r, r)."""
    rows, cols = zip(*term.entries, strict=True)
    return np.asarray(T)[..., list(rows), list(cols)]


def normalised(term: RandomTerm, theta: np.ndarray) -> np.ndarray:
    """The same ``Sigma``, ``T`` with a non-negative diagonal (lme4's convention).

    The likelihood depends on ``T`` only through ``T T'``, which a change of sign of a whole
    column leaves alone; an unconstrained optimiser may end anywhere on that orbit.
    """
    T = loading(term, theta)
    signs = np.where(np.diagonal(T, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    return theta_of(term, T * signs[..., None, :])


def covariance(term: RandomTerm, theta: np.ndarray) -> np.ndarray:
    """``Sigma = T T'`` (..., r, r)."""
    T = loading(term, theta)
    return T @ np.swapaxes(T, -1, -2)


def sd_and_correlation(sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The SDs (r,) and the correlation matrix (r, r) of a covariance matrix; a correlation
    with a variable of SD 0 is NaN (undefined), the diagonal 1."""
    sigma = np.asarray(sigma, dtype=float)
    sd = np.sqrt(np.clip(np.diag(sigma), 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = sigma / np.outer(sd, sd)
    corr = np.clip(corr, -1.0, 1.0)
    np.fill_diagonal(corr, 1.0)
    return sd, corr


def rank_deficient_loading(T: np.ndarray, deficiency: int) -> np.ndarray:
    """The lower-triangular ``T_b`` with its last ``deficiency`` columns zero whose ``T_b
    T_b'`` is the nearest matrix of rank ``r - deficiency`` to ``T T'`` (its smallest
    eigenvalues set to 0).

    Every positive semi-definite matrix of rank ``k`` is ``L L'`` with ``L`` an ``r x k``
    lower-trapezoidal matrix (from the QR decomposition of ``M'`` for any ``M`` with ``M M' =
    Sigma``), so the rank-deficient face of the cone is exactly "the last columns of ``T``
    are 0" (Golub & Van Loan 2013, Matrix Computations, sec. 5.2).
    """
    r = T.shape[0]
    keep = r - deficiency
    if keep <= 0:
        return np.zeros_like(T)
    values, vectors = np.linalg.eigh(T @ T.T)
    M = vectors[:, -keep:] * np.sqrt(np.clip(values[-keep:], 0.0, None))
    _, R = np.linalg.qr(M.T)              # M' = Q R  ->  M M' = R' R, R' lower trapezoidal
    L = R.T
    L = L * np.where(np.diag(L) < 0, -1.0, 1.0)[None, :]
    out = np.zeros_like(T)
    out[:, :keep] = L
    return out


@dataclass(frozen=True)
class Block:
    """A part of theta whose boundary is decided as one: a standard deviation (a random
    intercept, or one column of an uncorrelated term) or a whole correlated term, whose
    boundary is its covariance matrix losing rank (a variance at 0 or a correlation at
    +-1)."""

    term: int
    indices: tuple[int, ...]      # positions in the full parameter vector
    matrix: bool


class ThetaLayout:
    """Where each term's theta sits in the parameter vector ``(beta, theta_1, theta_2...)``
    and how it becomes the loadings ``T_k`` the likelihood takes."""

    def __init__(self, n_fixed: int, terms: Sequence[RandomTerm]):
        self.n_fixed = n_fixed
        self.terms = tuple(terms)
        self.slices = []
        start = n_fixed
        blocks = []
        for k, term in enumerate(self.terms):
            self.slices.append(slice(start, start + term.n_theta))
            indices = tuple(range(start, start + term.n_theta))
            if term.correlated and term.size > 1:
                blocks.append(Block(k, indices, True))
            else:
                blocks += [Block(k, (i,), False) for i in indices]
            start += term.n_theta
        self.size = start
        self.blocks = tuple(blocks)
        self.intercepts = all(term.size == 1 for term in self.terms)

    @property
    def n_theta(self) -> int:
        return self.size - self.n_fixed

    @property
    def diagonal(self) -> np.ndarray:
        """(size,) True where the parameter is a diagonal entry of some ``T_k``."""
        out = np.zeros(self.size, dtype=bool)
        for term, cut in zip(self.terms, self.slices, strict=True):
            out[cut] = [row == col for row, col in term.entries]
        return out

    def diagonals(self, held: np.ndarray) -> np.ndarray:
        """(S, size): the diagonal entries whose zero is a boundary of the problem with
        ``held`` (S, size) held: all but those of a correlated term on a face (some entry
        held). On a face the term's loading has its last columns at 0, and its covariance is
        ``L L'`` of the free columns ``L``; a diagonal of ``L`` at 0 is an ordinary point of
        that face (a rank-one ``v v'`` with ``v = (0, b)`` is the intercept's SD at 0 and the
        slope's at ``|b|``, and ``v`` crossing it turns the correlation from +1 to -1), so a
        step may cross it."""
        out = np.broadcast_to(self.diagonal, held.shape).copy()
        for block in self.blocks:
            if block.matrix:
                columns = list(block.indices)
                on_face = held[:, columns].any(axis=1)
                out[np.ix_(on_face, columns)] = False
        return out

    def loadings(self, theta: np.ndarray) -> list[np.ndarray]:
        """``T_k`` (S, r_k, r_k) for parameter vectors ``theta`` (S, size)."""
        if self.intercepts:      # each T_k is its one theta entry
            return [theta[:, s, None, None].astype(float) for s in range(self.n_fixed, self.size)]
        return [loading(t, theta[:, s]) for t, s in zip(self.terms, self.slices, strict=True)]

    def gradient(self, beta_gradient: np.ndarray, loading_gradients: list[np.ndarray]
                 ) -> np.ndarray:
        """The gradient over the whole parameter vector (S, size): ``dl/dbeta`` (S, p), then
        from each ``dl/dT_k`` (S, r_k, r_k) the entries theta sets."""
        if self.intercepts:
            return np.concatenate([beta_gradient, *(g[:, :, 0] for g in loading_gradients)],
                                  axis=1)
        parts = [theta_of(t, g) for t, g in zip(self.terms, loading_gradients, strict=True)]
        return np.concatenate([beta_gradient, *parts], axis=1)

    def start(self) -> np.ndarray:
        """lme4's start: every ``T_k`` the identity (SDs 1, correlations 0)."""
        return np.concatenate([theta_of(t, np.eye(t.size)) for t in self.terms]) \
            if self.terms else np.zeros(0)

    def normalised(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` (..., size) with every ``T_k``'s diagonal made non-negative."""
        out = np.asarray(theta, dtype=float).copy()
        if self.intercepts:       # each T_k is its one entry: its sign alone
            out[..., self.n_fixed:] = np.abs(out[..., self.n_fixed:])
            return out
        for term, cut in zip(self.terms, self.slices, strict=True):
            out[..., cut] = normalised(term, out[..., cut])
        return out

    def covariances(self, theta: np.ndarray) -> list[np.ndarray]:
        """``Sigma_k`` (r_k, r_k) of each term at ``theta`` (size,)."""
        return [covariance(t, theta[s]) for t, s in zip(self.terms, self.slices, strict=True)]
