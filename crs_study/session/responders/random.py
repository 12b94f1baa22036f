"""A simulated participant who guesses: a uniform symbol and a lognormal response time.

The baseline against which the perceptual observer is judged (chance = 1 / number of symbols).
Response time from stimulus offset is lognormal: ``rt_offset = median_s * exp(sigma * z)``,
z standard normal, so its median is ``median_s``; the time from onset adds the stimulus
duration. Draws come from ``default_rng([seed, trial.index])``: a resumed session repeats an
uninterrupted one exactly.
"""

from __future__ import annotations

from crs_study.clock import Clock
from crs_study.errors import ConfigError
from crs_study.protocol.plan import PlannedTrial
from crs_study.session.responders.base import (
    Responder,
    Response,
    StimulusRecord,
    respond_at,
    trial_rng,
)


class RandomResponder(Responder):
    """Uniform symbol among the choices, lognormal response time after the stimulus."""

    name = "random"

    def __init__(self, seed: int, median_s: float = 1.0, sigma: float = 0.4) -> None:
        if not median_s > 0:
            raise ConfigError(f"random responder: median_s must be > 0, got {median_s!r}")
        if not sigma >= 0:
            raise ConfigError(f"random responder: sigma must be >= 0, got {sigma!r}")
        self.seed = int(seed)
        self.median_s = float(median_s)
        self.sigma = float(sigma)

    def respond(self, trial: PlannedTrial, stimulus: StimulusRecord, clock: Clock,
                time_limit_s: float | None) -> Response:
        rng = trial_rng(self.seed, trial.index)
        choices = stimulus.symbol_choices
        symbol = choices[int(rng.choice(len(choices)))]  # the draw of rng.choice(choices)
        after_offset = self.median_s * float(rng.lognormal(0.0, self.sigma))
        return respond_at(clock, stimulus, stimulus.duration_s + after_offset, time_limit_s,
                          symbol)
