"""Mode 2: the simulated observer's predicted accuracy of every stimulus, without sessions.

For each (level, symbol, condition) of a protocol (digits, letters, a set file's symbols) the
stimulus is rendered once and shown
once on a fresh simulated device, exactly as a session shows a test trial
(:class:`crs_study.session.trials.TrialFrames` for the frames, the runner's presentation for the
displayed setpoints a hand meets, the display neutral since the previous trial's offset, a
response and an inter-trial interval earlier; tests/test_power_observer.py checks the
displayed setpoints against a dry-run's). The perceptual observer
(:class:`crs_study.session.responders.observer.PerceptualObserver`) then senses it ``draws`` times,
each with fresh receptor noise, and its decision model gives the probability of naming the
right symbol among those the protocol shows (a session's choices,
:func:`crs_study.session.trials.symbol_choices`), ``p = (1 - lapse) softmax(-d / T) + lapse /
n`` over the template distances ``d``. The predicted accuracy of the typical participant
(``T`` the calibrated temperature, ability ``z = 0``) is the mean of that probability over
the draws: an integral over the sensing noise by Monte Carlo, with its standard error, never
a sampled response.

Participants differ as the observer's do: a simulated participant's temperature in
condition ``c`` is ``T exp(ability_sd z + benefit_sd s_c w / 2)``, ``z, w ~ N(0, 1)``,
``s_c`` -1 on the pixels alone and +1 with the skeleton
(:class:`~crs_study.session.responders.observer.PerceptualObserver`), and their accuracy of
every cell follows from the same draws' distances at that temperature, tabulated over the
log-temperature offset (the model's ``ability`` table, -3 to 3 in steps of 0.0125). So a
participant's condition effect varies with their ability and their benefit as in a dry-run:
a random slope that a random intercept alone leaves out. For reports and the fits' start,
the summary covariance is that of ``(f_0, f_c - f_0)``, ``f_c`` the mean over the cells of
condition ``c`` of ``logit P(correct | z, w)`` (Gauss-Hermite, 20 x 20 nodes). A
``participant_sd`` given instead makes participants a random intercept of that SD on the
logit scale (and ``participant_slope_sd`` a random slope).
Timeouts (a response more than the protocol's limit after the offset) are left out: the
observer's decision times are about 2 s against a 10 s limit.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.special import logit

from crs_study.analysis.glmm_simulate import slope_covariance
from crs_study.clock import VirtualClock
from crs_study.device import open_device
from crs_study.paths import resolve_protocol
from crs_study.power_analysis.backends import Backend
from crs_study.power_analysis.design import PowerDesign, PowerError
from crs_study.power_analysis.model import GenerativeModel
from crs_study.power_analysis.protocol_design import symbol_keys
from crs_study.protocol import load_protocol
from crs_study.session.responders.base import StimulusRecord
from crs_study.session.responders.observer import (
    ObserverOptions,
    PerceptualObserver,
    benefit_side,
)
from crs_study.session.runner import SETTLE_S
from crs_study.session.trials import present, symbol_choices, trial_frames
from crs_study.stimuli.strokes import Symbol

#: Noise draws per stimulus: the per-condition accuracy's Monte Carlo SE is about 0.3 /
#: sqrt(draws x symbols), under 0.01 for ten symbols.
DEFAULT_DRAWS = 200


@dataclass(frozen=True)
class ObserverPrediction:
    """``accuracy`` (L, D, C) predicted P(correct) of the typical participant, ``std_error``
    its Monte Carlo SE, ``distances`` (L, D, C, draws, choices) the template distances of
    every draw (NaN: too short a path, a guess), and the observer's decision constants."""

    accuracy: np.ndarray = field(repr=False)
    std_error: np.ndarray = field(repr=False)
    distances: np.ndarray = field(repr=False)
    correct_choice: np.ndarray = field(repr=False)
    temperature_mm: float
    ability_sd: float
    lapse: float
    benefit_sd: float = 0.0
    benefit_sides: tuple[float, ...] = ()

    def p_correct(self, temperature: float) -> np.ndarray:
        """P(correct) per cell for a participant of ``temperature`` (mean over draws)."""
        return _choice_probability(self.distances, self.correct_choice, temperature,
                                   self.lapse).mean(axis=-1)

    def logits_at(self, offset: float) -> np.ndarray:
        """Log-odds per cell (L, D, C) at log-temperature offset ``offset``."""
        return logit(np.clip(self.p_correct(self.temperature_mm * np.exp(offset)), 1e-6,
                             1 - 1e-6))

    def participant_covariance(self, nodes: int = 20) -> np.ndarray:
        """The covariance over participants of ``(f_0, f_c - f_0)`` (module docstring),
        (C, C), by Gauss-Hermite quadrature over ``z`` and ``w``."""
        C = self.accuracy.shape[2]
        if self.ability_sd == 0 and self.benefit_sd == 0:
            return np.zeros((C, C))
        x, weights = np.polynomial.hermite_e.hermegauss(nodes)
        weights = weights / weights.sum()
        sides = np.asarray(self.benefit_sides or (0.0,) * C)
        points, mass = [], []
        for zi, wz in zip(x, weights, strict=True):
            for wi, ww in zip(x if self.benefit_sd else [0.0], weights if self.benefit_sd
                              else [1.0], strict=True):
                offsets = self.ability_sd * zi + 0.5 * self.benefit_sd * sides * wi
                f = np.array([self.logits_at(o)[..., c].mean() for c, o in
                              enumerate(offsets)])
                points.append(np.r_[f[0], f[1:] - f[0]])
                mass.append(wz * ww)
        points, mass = np.array(points), np.array(mass)
        centred = points - mass @ points
        return (centred * mass[:, None]).T @ centred

    def participant_sd(self, nodes: int = 20) -> float:
        """SD over participants of the reference condition's mean cell log-odds."""
        return float(np.sqrt(self.participant_covariance(nodes)[0, 0]))


def _choice_probability(distances: np.ndarray, correct: np.ndarray, temperature: float,
                        lapse: float) -> np.ndarray:
    """The observer's Luce choice rule with lapses (``PerceptualObserver.
    choice_probabilities``) for the right symbol, per draw: ``(L, D, C, draws)``."""
    n = distances.shape[-1]
    guess = ~np.isfinite(distances).all(axis=-1)
    d = np.where(np.isfinite(distances), distances, 0.0)
    logits = -(d - d.min(axis=-1, keepdims=True)) / temperature
    p = np.exp(logits)
    p /= p.sum(axis=-1, keepdims=True)
    p = (1.0 - lapse) * p + lapse / n
    right = np.take_along_axis(p, correct[..., None, None].repeat(p.shape[-2], axis=-2),
                               axis=-1)[..., 0]
    return np.where(guess, 1.0 / n, right)


def predict(protocol: Any, draws: int = DEFAULT_DRAWS, seed: int = 0, backend: Any = None,
            **observer_options: Any) -> ObserverPrediction:
    """The observer's predictions for every stimulus of ``protocol`` (module docstring).

    The noise of draw ``j`` of cell (level ``l``, symbol ``d``, condition ``c``) comes from
    ``default_rng([seed, l, k, c, j])``, ``k`` the symbol's position in its stimulus set
    (:func:`~crs_study.power_analysis.protocol_design.symbol_keys`: the digit itself for the digit
    set), so the answer is the same on any backend: the (level, symbol) pairs are mapped like
    the studies (``backend``: an open
    :class:`~crs_study.power_analysis.backends.Backend`; None: in this process).
    """

    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 2:
        raise PowerError(f"--draws: expected a whole number >= 2, got {draws!r}")
    if not hasattr(protocol, "design"):
        protocol = load_protocol(resolve_protocol(protocol))
    options = ObserverOptions(**observer_options)
    levels, symbols, conditions = protocol.level_values, protocol.symbols, protocol.conditions
    tasks = [(str(protocol.path), li, key, draws, seed, observer_options)
             for li in range(len(levels)) for key in symbol_keys(protocol)]
    cells = (backend or Backend()).map(_cell_distances, tasks)
    shape = (len(levels), len(symbols), len(conditions))
    distances = np.stack(cells).reshape(shape + cells[0].shape[1:])
    choices = symbol_choices(protocol)
    correct = np.broadcast_to(np.array([choices.index(s) for s in symbols])[None, :, None],
                              shape).copy()
    per_draw = _choice_probability(distances, correct, options.temperature_mm, options.lapse)
    return ObserverPrediction(per_draw.mean(axis=-1),
                              per_draw.std(axis=-1, ddof=1) / np.sqrt(draws), distances,
                              correct, options.temperature_mm, options.ability_sd,
                              options.lapse, options.benefit_sd,
                              tuple(benefit_side(c) for c in conditions))


def _cell_distances(task: tuple) -> np.ndarray:
    """Template distances (C, draws, choices) of one (level, symbol) in every condition; the
    symbol is named by its position ``key`` in the protocol's stimulus set."""

    path, li, key, draws, seed, options = task
    protocol = load_protocol(path)
    symbol = protocol.symbol_set.symbols[key]
    layout = protocol.layout()
    level = protocol.level_values[li]
    observer = PerceptualObserver(layout, protocol, 0, **options)
    observer.temperature_mm = observer.options.temperature_mm        # ability z = 0
    choices = symbol_choices(protocol)
    out = np.full((len(protocol.conditions), draws, len(choices)), np.nan)
    for ci, condition in enumerate(protocol.conditions):
        record = shown_stimulus(protocol, layout, symbol, condition, level)
        for j in range(draws):
            path_ = observer.peak_path(record, np.random.default_rng([seed, li, key, ci, j]))
            out[ci, j] = observer.choice_probabilities(path_, choices, level)[1]
    return out


def shown_stimulus(protocol: Any, layout: Any, symbol: Symbol, condition: str,
                   level: float | None):
    """What a hand meets when one stimulus is shown on a fresh simulated device: the
    runner's frames and presentation (its ``StimulusRecord``)."""

    frame_times, frames = trial_frames(protocol, layout).get(symbol, condition, level)
    period = 1.0 / float(protocol.frame_rate_hz)
    # As between a session's trials: the display went neutral at the last offset, then the
    # response and the inter-trial interval passed. The gap matters: a write that starts a
    # refresh interval (1 s) or more after the last full one carries every channel, which
    # the wire takes a full frame's time to deliver (crs_study.device.schedule); a test
    # trial's first frame always does.
    gap = max(SETTLE_S, float(protocol.responses.expected_response_s)
              + float(protocol.inter_trial_interval_s))
    clock = VirtualClock(start=-gap)
    with open_device("sim://", layout, clock) as device:
        device.neutral()
        clock.sleep_until(0.0)
        shown = present(device, clock, frame_times, frames, period)
    return StimulusRecord(layout, condition, frame_times + period, shown.displayed,
                          symbol_choices(protocol), shown.onset, shown.offset)


def model_from_observer(design: PowerDesign, protocol: Any, participant_sd: float | None = None,
                        draws: int = DEFAULT_DRAWS, prediction: ObserverPrediction | None = None,
                        participant_slope_sd: float | None = None) -> GenerativeModel:
    """The generating model of mode 2: ``logit`` of the predicted accuracy per (level,
    symbol, condition) in the design's condition order, and the participant SD (given, else
    the observer's calibration). ``details`` hold the accuracy per symbol as
    ``accuracy_by_symbol`` (condition -> symbol -> accuracy) and, for the digit set, the same
    under its name before stimulus sets, ``accuracy_by_digit``."""
    if prediction is None:
        prediction = predict(protocol, draws)
    if not hasattr(protocol, "design"):

        protocol = load_protocol(resolve_protocol(protocol))
    order = [list(protocol.conditions).index(c) for c in design.conditions]
    accuracy = prediction.accuracy[:, :, order]
    base = logit(np.clip(accuracy, 1e-6, 1 - 1e-6))
    sides = tuple(prediction.benefit_sides[k] for k in order) if prediction.benefit_sides \
        else ()
    ordered = replace(prediction, accuracy=accuracy, std_error=prediction.std_error[:, :, order],
                      distances=prediction.distances[:, :, order],
                      correct_choice=prediction.correct_choice[:, :, order],
                      benefit_sides=sides)
    derived = ordered.participant_covariance()
    given = participant_sd is not None or participant_slope_sd is not None
    grid = ability = None
    if given:
        sd = float(np.sqrt(derived[0, 0])) if participant_sd is None else float(participant_sd)
        slopes = len(design.conditions) - 1
        cov = slope_covariance(sd, [0.0 if participant_slope_sd is None
                                    else float(participant_slope_sd)] * slopes)
    else:
        cov = derived
        grid = np.round(np.arange(-3.0, 3.0 + 1e-9, 0.0125), 10)
        ability = np.stack([ordered.logits_at(w) for w in grid])
    se = ordered.std_error
    by_symbol = {c: dict(zip(map(str, design.symbols), accuracy[:, :, k].mean(axis=0).tolist(),
                             strict=True)) for k, c in enumerate(design.conditions)}
    slope_sd = np.sqrt(np.clip(np.diag(derived)[1:], 0.0, None))
    details = {"draws": int(prediction.distances.shape[3]),
               "accuracy_by_condition": {c: float(a) for c, a in zip(
                   design.conditions, accuracy.mean(axis=(0, 1)), strict=True)},
               "accuracy_std_error_by_condition": {c: float(np.sqrt((s ** 2).sum()) / s.size)
                                                   for c, s in zip(design.conditions,
                                                                   np.moveaxis(se, 2, 0),
                                                                   strict=True)},
               **({"accuracy_by_digit": by_symbol} if design.symbol_column == "digit"
                  else {}),
               "accuracy_by_symbol": by_symbol,
               "participant_sd_from_calibration": float(np.sqrt(derived[0, 0])),
               "participant_slope_sd_from_calibration": dict(zip(
                   design.comparisons, slope_sd.tolist(), strict=True)),
               "participant_sd_given": participant_sd is not None,
               "participant_slope_sd_given": participant_slope_sd is not None,
               "participants": ("the observer's: temperature T exp(ability_sd z +- benefit_sd "
                                "w / 2), z, w ~ N(0, 1)" if not given else
                                f"random effects, intercept SD {np.sqrt(cov[0, 0]):g}, slope "
                                f"SD {np.sqrt(cov[1, 1]):g} (given)"),
               "temperature_mm": prediction.temperature_mm,
               "ability_sd": prediction.ability_sd, "benefit_sd": prediction.benefit_sd,
               "lapse": prediction.lapse}
    return GenerativeModel(base, float(np.sqrt(cov[0, 0])), 0.0, "observer", details,
                           ability, grid, participant_cov=cov,
                           ability_sd=prediction.ability_sd, benefit_sd=prediction.benefit_sd,
                           benefit_sides=sides or None)
