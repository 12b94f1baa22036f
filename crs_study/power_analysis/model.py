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
    ``ability`` (G, L, D, C) the log-odds of a participant of ability ``z =
    ability_grid[g]`` (evenly spaced), used instead of ``base + participant_sd z`` when given
    (``participant_sd`` then only summarises it and starts the fits); ``source`` and
    ``details`` say where the numbers come from."""

    base: np.ndarray = field(repr=False)
    participant_sd: float
    digit_sd: float = 0.0
    source: str = "parameters"
    details: dict = field(default_factory=dict, compare=False)
    ability: np.ndarray | None = field(default=None, repr=False)
    ability_grid: np.ndarray | None = field(default=None, repr=False)

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
        object.__setattr__(self, "base", base)

    @property
    def symbol_sd(self) -> float:
        """The SD of the symbol's random intercept (:attr:`digit_sd`)."""
        return self.digit_sd

    def scaled(self, effect_scale: float) -> GenerativeModel:
        """Every condition's difference from the reference (condition 0) times the scale."""
        if not (np.isfinite(effect_scale) and effect_scale >= 0):
            raise PowerError(f"--effect-scale: expected a number >= 0, got {effect_scale!r}")
        def scale(logits):
            ref = logits[..., :1]
            return ref + effect_scale * (logits - ref)

        return replace(self, base=scale(self.base),
                       ability=None if self.ability is None else scale(self.ability),
                       details={**self.details, "effect_scale": effect_scale})

    def participant_logits(self, z: float) -> np.ndarray:
        """The log-odds (L, D, C) of a participant of ability ``z``, typical symbols."""
        if self.ability is None:
            return self.base + self.participant_sd * z
        grid = self.ability_grid
        step = grid[1] - grid[0]
        g = int(np.clip(np.floor((z - grid[0]) / step), 0, len(grid) - 2))
        w = (z - grid[g]) / step
        return (1.0 - w) * self.ability[g] + w * self.ability[g + 1]

    def start(self, design: PowerDesign) -> np.ndarray:
        """Warm start of the full model's fit: the GLMM parameters nearest this model
        (treatment-coded means over symbols and levels; the SDs, the symbols' spread when the
        symbols are fixed)."""
        mean = self.base.mean(axis=(0, 1))
        beta = np.r_[mean[0], mean[1:] - mean[0]]
        sigmas = [self.participant_sd]
        if design.symbol_effect:
            spread = float(np.std(self.base.mean(axis=(0, 2)))) if self.digit_sd == 0 else \
                self.digit_sd
            sigmas.append(spread)
        return np.r_[beta, sigmas]

    def accuracy(self) -> np.ndarray:
        """P(correct) of the typical participant per condition (symbols and levels averaged,
        each at its own log-odds)."""
        from scipy.special import expit

        return expit(self.base).mean(axis=(0, 1))

    def to_dict(self, design: PowerDesign) -> dict[str, Any]:
        """The model as JSON: ``digit_sd`` (its name before stimulus sets) and ``symbol_sd``
        are the same number, the SD of the symbol's random intercept."""
        acc = self.accuracy()
        return {"source": self.source, "participant_sd": self.participant_sd,
                "participants": ("the observer's ability model (temperature T exp(ability_sd "
                                 "z))" if self.ability is not None else
                                 "a random intercept with participant_sd"),
                "digit_sd": self.digit_sd, "symbol_sd": self.digit_sd,
                "accuracy": {c: float(a) for c, a in zip(design.conditions, acc, strict=True)},
                "log_odds": self.base.tolist(), "details": self.details}


def model_from_parameters(design: PowerDesign, accuracy: dict[str, float] | None = None, *,
                          log_odds: dict[str, float] | None = None, participant_sd: float,
                          digit_sd: float = 0.0, source: str = "parameters",
                          symbol_sd: float | None = None) -> GenerativeModel:
    """Every symbol and level alike: condition ``c`` correct with ``accuracy[c]`` (or
    ``expit(log_odds[c])``) for the typical participant and symbol; ``symbol_sd`` (the same
    as ``digit_sd``, which it replaces when given) the SD of the symbol's intercept."""
    if symbol_sd is not None:
        digit_sd = symbol_sd
    given = log_odds if log_odds is not None else {
        c: float(logit(a)) for c, a in (accuracy or {}).items()}
    missing = [c for c in design.conditions if c not in given]
    if missing:
        raise PowerError(f"the model needs every condition of the design, missing {missing!r}")
    per_condition = np.array([given[c] for c in design.conditions], dtype=float)
    base = np.broadcast_to(per_condition, (len(design.levels), len(design.symbols),
                                           len(design.conditions))).copy()
    return GenerativeModel(base, float(participant_sd), float(digit_sd), source,
                           {"log_odds": dict(zip(design.conditions, per_condition.tolist(),
                                                 strict=True))})


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
                           design.random_effects, design.method, design.n_quadrature)
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
    variances = full.variance_components
    participant_sd = float(np.sqrt(variances.get("participant_id", 0.0)))
    symbol_sd = float(np.sqrt(variances.get(column, 0.0))) if design.symbol_effect else 0.0
    model = model_from_parameters(design, log_odds=dict(zip(design.conditions, log_odds,
                                                              strict=True)),
                                  participant_sd=participant_sd, digit_sd=symbol_sd,
                                  source="pilot")
    details = {"dataset": str(dataset), "n_participants": int(n_participants),
               "n_trials": int(len(trials)), "fixed_effects": params.to_dict(),
               "std_errors": full.bse.to_dict(), "participant_sd": participant_sd,
               design.symbol_sd_name: symbol_sd, "symbol_column": column,
               "symbols": sorted(map(str, trials[column].unique())),
               "converged": bool(full.converged),
               "warnings": list(full.warnings)}
    return replace(model, details=details)
