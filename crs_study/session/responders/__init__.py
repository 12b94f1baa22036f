"""Responders: who answers a trial. Chosen on the command line by a spec string:

``keypad``
    a person at the terminal, one keypress per answer (:mod:`.keypad`);
``scripted:FILE``
    answers read from a file, line k for trial k (:mod:`.scripted`);
``random``
    a guessing simulated participant (:mod:`.random`);
``observer``
    a perceptual observer that senses the displayed surface (:mod:`.observer`).
"""

from __future__ import annotations

from typing import Any

from crs_study.errors import ConfigError
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.session.responders.base import Responder, Response, StimulusRecord, trial_rng
from crs_study.session.responders.keypad import KeypadResponder
from crs_study.session.responders.observer import PerceptualObserver
from crs_study.session.responders.random import RandomResponder
from crs_study.session.responders.scripted import ScriptedResponder

SPECS = ("keypad", "scripted:FILE", "random", "observer")

__all__ = ["SPECS", "Responder", "Response", "StimulusRecord", "make_responder", "trial_rng"]


def make_responder(spec: str, *, seed: int, layout: Layout | None = None,
                   protocol: Protocol | None = None, **options: Any) -> Responder:
    """The responder for ``spec`` (see the module docstring); simulated ones use ``seed``."""
    if spec == "keypad":
        if protocol is not None and "keys" not in options:
            options["keys"] = {protocol.key_for(s): s for s in protocol.symbols}
        if protocol is not None and "instruction" not in options:
            options["instruction"] = protocol.symbol_set.instructions  # what the screen shows
        if protocol is not None and "texts" not in options:
            options["texts"] = protocol.symbol_set.screens  # in the set's language
        return KeypadResponder(**options)
    if spec.startswith("scripted:") and len(spec) > len("scripted:"):
        return ScriptedResponder(spec[len("scripted:"):],
                                 protocol.symbol_set if protocol is not None else None)
    if spec == "random":
        return RandomResponder(seed, **options)
    if spec == "observer":
        if layout is None or protocol is None:
            raise ConfigError("the observer responder senses the displayed surface: it needs "
                              "the protocol and the device's layout")
        return PerceptualObserver(layout, protocol, seed, **options)
    raise ConfigError(f"unknown responder {spec!r}; expected one of: {', '.join(SPECS)}")
