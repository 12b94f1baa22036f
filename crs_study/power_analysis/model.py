"""Where the effect comes from: the model the simulated studies are drawn from.

Every simulated trial of participant ``p`` on symbol ``d`` (a digit, a letter, any symbol of
the protocol's stimulus set) in condition ``c`` (at level ``l``)
is correct with probability ``expit(base[l, d, c] + sigma_p z_p + sigma_d z_d)``, ``z ~
N(0, 1)`` drawn per study (:mod:`crs_study.power_analysis.simulate`); or, where the model carries an
``ability`` table (the observer's own participants), ``expit(ability(z_p)[l, d, c] + sigma_d
z_d)``, the table interpolated linearly in ``z``. Three sources fill it:

* :func:`model_from_pilot` -- the primary GLMM fitted to a pilot dataset: ``base`` is the
  fixed effects (the same for every symbol and level), ``sigma_p`` and ``sigma_d`` its random
  intercepts' SDs; new participants and symbol effects are drawn for every study, as simr's
  ``extend`` + ``powerSim`` do (Green & MacLeod 2016, Methods Ecol. Evol. 7:493);
* :func:`crs_study.power_analysis.observer.model_from_observer` -- the simulated observer's
  predicted accuracy of every (level, symbol, condition) on the simulated device
  (``sigma_d = 0``: the symbols' differences are in ``base``), plus a between-participant SD;
* :func:`model_from_parameters` -- given numbers (recovery tests, closed forms).

``effect_scale`` multiplies every condition's difference from the reference, ``base[..., c]
- base[..., ref]``: for the pilot that is the condition coefficient (simr's
``fixef(model)["condition"] <- value``); pilot effects are optimistic.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.special import logit

from crs_study.analysis.glmm import GlmmFitError
from crs_study.analysis.glmm_simulate import psd_factor, slope_covariance
from crs_study.analysis.load import load_datasets, with_exclusions
from crs_study.analysis.plan import Exclusions
from crs_study.analysis.primary import fit_primary
from crs_study.analysis.sources import select_sources
from crs_study.dataset.schema import symbol_column
from crs_study.errors import CrsStudyError
from crs_study.power_analysis.design import PowerDesign, PowerError


@dataclass(frozen=True)
class GenerativeModel:
    """``base`` (L, D, C) log-odds of the typical participant and symbol; the SDs on the logit
    scale (``digit_sd``: the SD of the symbol's random intercept, whatever the set; it kept
    the name it had when every protocol showed digits, :attr:`symbol_sd` is the same);
    ``source`` and ``details`` say where the numbers come from.

    Random slopes: ``participant_cov`` (C, C), the covariance of a participant's effects
    (intercept, then the slope of each non-reference condition, treatment coding as the
    GLMM's), and ``symbol_cov`` likewise; None: a random intercept of ``participant_sd``
    (``digit_sd``) alone. ``ability`` (G, L, D, C), the observer's log-odds at decision
    noise ``T exp(ability_grid[g])`` (evenly spaced log-temperature offsets), is used instead
    when given: a participant's offset in condition ``c`` is ``ability_sd z + benefit_sd
    benefit_sides[c] w / 2`` (``z``, ``w`` ~ N(0, 1)), and ``participant_cov`` then only
    summarises it (reports, the fits' starts)."""

    base: np.ndarray = field(repr=False)
    participant_sd: float
    digit_sd: float = 0.0
    source: str = "parameters"
    details: dict = field(default_factory=dict, compare=False)
    ability: np.ndarray | None = field(default=None, repr=False)
    ability_grid: np.ndarray | None = field(default=None, repr=False)
    participant_cov: np.ndarray | None = field(default=None, repr=False)
    symbol_cov: np.ndarray | None = field(default=None, repr=False)
    ability_sd: float = 0.0
    benefit_sd: float = 0.0
    benefit_sides: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        base = np.asarray(self.base, dtype=float)
        if base.ndim != 3 or not np.all(np.isfinite(base)):
            raise PowerError(f"the model's log-odds must be finite, shape (levels, symbols, "
                             f"conditions); got shape {base.shape}")
        for name in ("participant_sd", "digit_sd"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise PowerError(f"--{name.replace('_', '-')}: expected a number >= 0, "
                                 f"got {value!r}")
        C = base.shape[2]
        for name in ("participant_cov", "symbol_cov"):
            cov = getattr(self, name)
            if cov is None:
                continue
            cov = np.asarray(cov, dtype=float)
            if cov.shape != (C, C) or not np.all(np.isfinite(cov)) or not np.allclose(
                    cov, cov.T) or np.linalg.eigvalsh(cov)[0] < -1e-9 * max(1.0, np.abs(
                        cov).max()):
                raise PowerError(f"the model's {name.replace('_', ' ')}ariance must be a "
                                 f"covariance matrix ({C} x {C}: intercept and a slope per "
                                 f"non-reference condition), got {cov.tolist()!r}")
            object.__setattr__(self, name, cov)
        object.__setattr__(self, "base", base)

    @property
    def symbol_sd(self) -> float:
        """The SD of the symbol's random intercept (:attr:`digit_sd`)."""
        return self.digit_sd

    def covariance(self, who: str) -> np.ndarray:
        """The covariance (C, C) of a participant's (``who = "participant"``) or a symbol's
        effects: intercept, then a slope per non-reference condition."""
        C = self.base.shape[2]
        given = self.participant_cov if who == "participant" else self.symbol_cov
        if given is not None:
            return given
        out = np.zeros((C, C))
        out[0, 0] = (self.participant_sd if who == "participant" else self.digit_sd) ** 2
        return out

    def with_sds(self, participant_sd: float | None = None,
                 participant_slope_sd: float | None = None) -> GenerativeModel:
        """The model with the participants' intercept SD and/or every slope's SD replaced
        (their correlations kept); None leaves a number as it is."""
        if participant_sd is None and participant_slope_sd is None:
            return self
        cov = self.covariance("participant")
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.nan_to_num(cov / np.outer(sd, sd))
        np.fill_diagonal(corr, 1.0)
        if participant_sd is not None:
            sd[0] = float(participant_sd)
        if participant_slope_sd is not None:
            sd[1:] = float(participant_slope_sd)
        return replace(self, participant_sd=float(sd[0]), participant_cov=corr * np.outer(sd, sd),
                       ability=None, ability_grid=None)

    def slope_sd(self, who: str = "participant") -> np.ndarray:
        """The SD of each non-reference condition's random slope (C - 1,)."""
        return np.sqrt(np.clip(np.diag(self.covariance(who))[1:], 0.0, None))

    def scaled(self, effect_scale: float) -> GenerativeModel:
        """Every condition's difference from the reference (condition 0) times the scale,
        for the typical participant and symbol; how participants and symbols differ in it
        (the slopes) stays as it is, as simr's ``fixef(model)["condition"] <- value``."""
        if not (np.isfinite(effect_scale) and effect_scale >= 0):
            raise PowerError(f"--effect-scale: expected a number >= 0, got {effect_scale!r}")
        ref = self.base[..., :1]
        base = ref + effect_scale * (self.base - ref)
        return replace(self, base=base,
                       ability=None if self.ability is None else
                       self.ability + (base - self.base)[None],
                       details={**self.details, "effect_scale": effect_scale})

    def without_effect(self, comparison: int) -> GenerativeModel:
        """The null of one comparison: condition ``comparison + 1`` as the reference for the
        typical participant and symbol (the other conditions as they are; how participants
        and symbols differ in it, the slopes, as it is)."""
        base = self.base.copy()
        base[..., comparison + 1] = base[..., 0]
        return replace(self, base=base,
                       ability=None if self.ability is None else
                       self.ability + (base - self.base)[None],
                       details={**self.details, "null_of": comparison})

    def participant_logits(self, z: float, w: np.ndarray | None = None) -> np.ndarray:
        """The log-odds (L, D, C) of a participant of ability ``z`` and slope draws ``w``
        (C - 1 standard normals; None: zeros), typical symbols."""
        C = self.base.shape[2]
        w = np.zeros(C - 1) if w is None else np.asarray(w, dtype=float)
        return self.participants_logits(np.array([z], dtype=float), w[None])[0]

    def participants_logits(self, z: np.ndarray, w: np.ndarray) -> np.ndarray:
        """:meth:`participant_logits` of ``P`` participants at once: ``z`` (P,), ``w`` (P,
        C - 1); (P, L, D, C)."""
        draws = np.column_stack([z, w])                                      # (P, C)
        if self.ability is None:
            effect = draws @ psd_factor(self.covariance("participant")).T     # (P, C)
            slopes = np.column_stack([np.zeros(len(z)), effect[:, 1:]])
            return (self.base[None] + effect[:, 0, None, None, None]) + slopes[:, None, None]
        sides = np.asarray(self.benefit_sides or (0.0,) * draws.shape[1])
        offsets = self.ability_sd * z[:, None] + 0.5 * self.benefit_sd * sides * draws[:, 1:2]
        grid = self.ability_grid
        step = grid[1] - grid[0]
        g = np.clip(np.floor((offsets - grid[0]) / step), 0, len(grid) - 2).astype(int)
        t = ((offsets - grid[g]) / step)[:, None, None, :]                  # (P, 1, 1, C)
        by_condition = np.moveaxis(self.ability, -1, 1)                      # (G, C, L, D)
        columns = np.arange(draws.shape[1])
        low = np.moveaxis(by_condition[g, columns], 1, -1)                  # (P, L, D, C)
        high = np.moveaxis(by_condition[g + 1, columns], 1, -1)
        return (1.0 - t) * low + t * high

    def start(self, design: PowerDesign) -> np.ndarray:
        """The fixed effects nearest this model (treatment-coded means over symbols and
        levels): a start for ``beta`` where a fit has no data of its own to start from (the
        validity bench's null fits)."""
        mean = self.base.mean(axis=(0, 1))
        return np.r_[mean[0], mean[1:] - mean[0]]

    def accuracy(self) -> np.ndarray:
        """P(correct) of the typical participant per condition (symbols and levels averaged,
        each at its own log-odds)."""
        from scipy.special import expit

        return expit(self.base).mean(axis=(0, 1))

    def to_dict(self, design: PowerDesign) -> dict[str, Any]:
        """The model as JSON: ``digit_sd`` (its name before stimulus sets) and ``symbol_sd``
        are the same number, the SD of the symbol's random intercept; ``participant_slope_sd``
        and ``symbol_slope_sd`` the SD of each non-reference condition's slope, and the
        covariances in full."""
        acc = self.accuracy()
        comparisons = design.conditions[1:]
        return {"source": self.source, "participant_sd": self.participant_sd,
                "participants": ("the observer's ability and benefit model (temperature T "
                                 "exp(ability_sd z +- benefit_sd w / 2))"
                                 if self.ability is not None else
                                 "random effects drawn from participant_covariance"),
                "digit_sd": self.digit_sd, "symbol_sd": self.digit_sd,
                "participant_slope_sd": dict(zip(comparisons,
                                                 self.slope_sd("participant").tolist(),
                                                 strict=True)),
                "symbol_slope_sd": dict(zip(comparisons, self.slope_sd("symbol").tolist(),
                                            strict=True)),
                "participant_covariance": self.covariance("participant").tolist(),
                "symbol_covariance": self.covariance("symbol").tolist(),
                "accuracy": {c: float(a) for c, a in zip(design.conditions, acc, strict=True)},
                "log_odds": self.base.tolist(), "details": self.details}


def model_from_parameters(design: PowerDesign, accuracy: dict[str, float] | None = None, *,
                          log_odds: dict[str, float] | None = None, participant_sd: float,
                          digit_sd: float = 0.0, source: str = "parameters",
                          symbol_sd: float | None = None, participant_slope_sd: float = 0.0,
                          participant_correlation: float = 0.0,
                          symbol_slope_sd: float = 0.0) -> GenerativeModel:
    """Every symbol and level alike: condition ``c`` correct with ``accuracy[c]`` (or
    ``expit(log_odds[c])``) for the typical participant and symbol; ``symbol_sd`` (the same
    as ``digit_sd``, which it replaces when given) the SD of the symbol's intercept;
    ``participant_slope_sd`` the SD of every non-reference condition's random slope by
    participant (correlated ``participant_correlation`` with the intercept), and
    ``symbol_slope_sd`` by symbol."""
    if symbol_sd is not None:
        digit_sd = symbol_sd
    for name, value in (("participant-slope-sd", participant_slope_sd),
                        ("symbol-slope-sd", symbol_slope_sd)):
        if not (np.isfinite(value) and value >= 0):
            raise PowerError(f"--{name}: expected a number >= 0, got {value!r}")
    if not (np.isfinite(participant_correlation) and -1 <= participant_correlation <= 1):
        raise PowerError(f"--participant-correlation: expected a number from -1 to 1, got "
                         f"{participant_correlation!r}")
    given = log_odds if log_odds is not None else {
        c: float(logit(a)) for c, a in (accuracy or {}).items()}
    missing = [c for c in design.conditions if c not in given]
    if missing:
        raise PowerError(f"the model needs every condition of the design, missing {missing!r}")
    per_condition = np.array([given[c] for c in design.conditions], dtype=float)
    base = np.broadcast_to(per_condition, (len(design.levels), len(design.symbols),
                                           len(design.conditions))).copy()
    slopes = len(design.conditions) - 1
    participant_cov = symbol_cov = None
    if participant_slope_sd:
        participant_cov = slope_covariance(float(participant_sd), [participant_slope_sd] * slopes,
                                           participant_correlation)
    if symbol_slope_sd:
        symbol_cov = slope_covariance(float(digit_sd), [symbol_slope_sd] * slopes)
    return GenerativeModel(base, float(participant_sd), float(digit_sd), source,
                           {"log_odds": dict(zip(design.conditions, per_condition.tolist(),
                                                 strict=True))},
                           participant_cov=participant_cov, symbol_cov=symbol_cov)


def model_from_pilot(design: PowerDesign, dataset: Any) -> GenerativeModel:
    """The primary GLMM fitted to a pilot dataset as ``analyze`` fits it: its sessions (not
    simulated and human ones together), the plan's exclusions (``design.exclusions``),
    :func:`fit_primary` with the plan's random effects and method. The pilot shows the
    design's kind of symbols (its symbol column is the design's: a digit pilot does not power
    a letter study); its symbol intercept's SD is that of the plan's symbol effect, whatever
    the plan calls it. Errors name ``--pilot``."""

    try:

        loaded, _, _ = select_sources(load_datasets([dataset]))
        loaded = with_exclusions(loaded, design.exclusions or Exclusions())
    except CrsStudyError as exc:
        raise PowerError(f"--pilot {dataset}: {exc}") from None
    trials = loaded.analysed
    column = symbol_column(trials.columns)
    if column != design.symbol_column:
        raise PowerError(f"--pilot {dataset}: the pilot's trials name the symbol shown in a "
                         f"{column!r} column, the protocol's in {design.symbol_column!r} "
                         f"({design.noun}s): the pilot must show the protocol's stimulus set")
    present = set(trials["condition"])
    missing = [c for c in design.conditions if c not in present]
    if missing:
        raise PowerError(f"--pilot {dataset}: no analysed trial of condition(s) {missing!r}; "
                         f"the pilot must have every condition of the design "
                         f"{list(design.conditions)!r} (it has {sorted(present)!r})")
    trials = trials.loc[trials["condition"].isin(design.conditions)]
    n_participants = trials["participant_id"].nunique()
    if n_participants < 2:
        raise PowerError(f"--pilot {dataset}: {n_participants} participant with analysed "
                         "trials; the participant variance needs at least two")
    try:
        fits = fit_primary(trials, list(design.conditions), design.reference,
                           design.random_effects, design.method, design.n_quadrature,
                           **design.model_options())
    except GlmmFitError as exc:
        raise PowerError(f"--pilot {dataset}: the primary GLMM could not be fitted ({exc})"
                         ) from None
    full = fits.full
    if full.separation is not None:
        raise PowerError(f"--pilot {dataset}: {list(full.separation.coefficients)!r} "
                         "separated (a condition at 0 % or 100 % correct): the pilot gives no "
                         "finite effect to power a study on")
    params = full.params
    columns = ["Intercept"] + [f"condition[{c}]" for c in design.comparisons]
    absent = [c for c in columns if c not in params.index]
    if absent:
        raise PowerError(f"--pilot {dataset}: the fit has no coefficient {absent[0]!r}")
    beta = params[columns].to_numpy(dtype=float)
    log_odds = np.r_[beta[0], beta[0] + beta[1:]]
    participant_cov = fitted_covariance(full, "participant_id", columns)
    symbol_cov = (fitted_covariance(full, column, columns) if design.symbol_effect
                  else np.zeros_like(participant_cov))
    participant_sd = float(np.sqrt(participant_cov[0, 0]))
    symbol_sd = float(np.sqrt(symbol_cov[0, 0]))
    model = model_from_parameters(design, log_odds=dict(zip(design.conditions, log_odds,
                                                              strict=True)),
                                  participant_sd=participant_sd, digit_sd=symbol_sd,
                                  source="pilot")
    details = {"dataset": str(dataset), "n_participants": int(n_participants),
               "n_trials": int(len(trials)), "fixed_effects": params.to_dict(),
               "std_errors": full.bse.to_dict(), "participant_sd": participant_sd,
               design.symbol_sd_name: symbol_sd, "symbol_column": column,
               "symbols": sorted(map(str, trials[column].unique())),
               "random": full.random_formula,
               "random_effects": full.random_effects().to_dict(orient="records"),
               "structure": fits.structure(),
               "converged": bool(full.converged),
               "warnings": list(full.warnings)}
    return replace(model, details=details, participant_cov=participant_cov,
                   symbol_cov=symbol_cov)


def fitted_covariance(fit, group: str, columns: list[str]) -> np.ndarray:
    """The covariance of a grouping factor's effects in a fit, over ``columns`` (the
    intercept and the condition contrasts, in the design's order); an effect the fit has no
    term for has variance 0."""
    out = np.zeros((len(columns), len(columns)))
    for term, sigma in zip(fit.terms, fit.covariances().values(), strict=True):
        if term.group != group:
            continue
        index = [columns.index(c) for c in term.columns]
        out[np.ix_(index, index)] = sigma.to_numpy()
    return out
