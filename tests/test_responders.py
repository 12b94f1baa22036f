"""Responders: the factory, scripted files, the random participant, the keypad's refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from crs_study.clock import VirtualClock
from crs_study.errors import ConfigError, SessionError
from crs_study.session.responders import make_responder
from crs_study.session.responders.base import Response, StimulusRecord, respond_at, trial_rng
from crs_study.session.responders.keypad import KeypadResponder
from crs_study.session.responders.random import RandomResponder
from crs_study.session.responders.scripted import ScriptedResponder, parse_script


class Trial:
    def __init__(self, index, digit=4):
        self.index, self.symbol = index, digit


def record(duration=2.0, onset=10.0, choices=tuple(range(10))):
    return StimulusRecord(None, "crs", np.arange(3) / 15, np.zeros((3, 37)), choices,
                          onset, onset + duration)


def test_factory_builds_each_kind(tmp_path):
    script = tmp_path / "s.txt"
    script.write_text("3\n")
    assert isinstance(make_responder("keypad", seed=1), KeypadResponder)
    assert isinstance(make_responder(f"scripted:{script}", seed=1), ScriptedResponder)
    assert isinstance(make_responder("random", seed=1), RandomResponder)
    for bad in ("guess", "scripted:", "Random"):
        with pytest.raises(ConfigError, match=f"unknown responder {bad!r}; expected one of"):
            make_responder(bad, seed=1)


def test_the_observer_without_a_protocol_and_layout_is_one_line():
    # it senses the displayed surface of the protocol's digits (an AttributeError before)
    with pytest.raises(ConfigError, match="the observer responder senses the displayed "
                       "surface: it needs the protocol and the device's layout"):
        make_responder("observer", seed=1)


def test_script_formats():
    text = "# a comment\ndigit\trt\n7\n\n3\t1.25\nn/a\n2 -0.5\n"
    assert parse_script(text) == [(7, 0.5), (3, 1.25), (None, 0.5), (2, -0.5)]


@pytest.mark.parametrize("text, message", [
    ("x\n", r"f:1: expected a digit 0-9 or n/a, got 'x'"),
    ("1\n12\n", r"f:2: expected a digit 0-9 or n/a, got '12'"),
    ("1\t2\t3\n", r"f:1: expected 'digit' or 'digit<TAB>rt'"),
    ("1\tsoon\n", r"f:1: expected a response time in seconds, got 'soon'"),
    ("1\tnan\n", r"f:1: response time must be finite"),
])
def test_script_errors_name_line_and_value(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_script(text, "f")


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.none(), st.integers(0, 9)),
                          st.floats(-5, 30, allow_nan=False).map(lambda x: round(x, 3)))))
def test_script_round_trip(entries):
    text = "".join(f"{'n/a' if d is None else d}\t{rt!r}\n" for d, rt in entries)
    assert parse_script(text) == entries


def test_scripted_answers_by_trial_index(tmp_path):
    path = tmp_path / "answers.tsv"
    path.write_text("5\t0.25\n6\n")
    responder = ScriptedResponder(path)
    clock = VirtualClock(12.0)
    answer = responder.respond(Trial(0), record(), clock, 10.0)
    assert answer == Response(5, 2.25) and clock.now() == pytest.approx(12.25)
    assert responder.respond(Trial(1), record(), VirtualClock(12.0), None) == Response(6, 2.5)
    with pytest.raises(SessionError, match="have 2 entries; trial 2 needs one more"):
        responder.respond(Trial(2), record(), VirtualClock(12.0), None)
    with pytest.raises(SessionError, match=r"answers 5, not one of \(1, 2\)"):
        responder.respond(Trial(0), record(choices=(1, 2)), VirtualClock(12.0), None)
    with pytest.raises(ConfigError, match="no such file"):
        ScriptedResponder(tmp_path / "missing.txt")


def test_random_is_uniform_and_lognormal():
    """Digits uniform (chi-square, 5000 draws), offset RT lognormal with the set median."""
    responder = RandomResponder(seed=11, median_s=1.5, sigma=0.4)
    answers = [responder.respond(Trial(k), record(), VirtualClock(10.0), None)
               for k in range(5000)]
    counts = np.bincount([a.symbol for a in answers], minlength=10)
    assert stats.chisquare(counts).pvalue > 0.001
    after = np.array([a.response_time_s - 2.0 for a in answers])
    assert np.median(after) == pytest.approx(1.5, rel=0.05)
    # log RT ~ N(log 1.5, 0.4): Kolmogorov-Smirnov against scipy's normal
    assert stats.kstest(np.log(after), "norm", args=(np.log(1.5), 0.4)).pvalue > 0.001


def test_random_depends_on_seed_and_trial_only():
    one = RandomResponder(seed=3).respond(Trial(7), record(), VirtualClock(10.0), None)
    # other trials in between do not change trial 7's answer (resume safety)
    other = RandomResponder(seed=3)
    for k in range(7):
        other.respond(Trial(k), record(), VirtualClock(10.0), None)
    assert other.respond(Trial(7), record(), VirtualClock(10.0), None) == one
    assert RandomResponder(seed=4).respond(Trial(7), record(), VirtualClock(10.0), None) != one
    assert trial_rng(3, 7).random() == np.random.default_rng([3, 7]).random()


def test_random_times_out_at_the_limit():
    clock = VirtualClock(10.0)
    answer = RandomResponder(seed=1, median_s=50.0, sigma=0.0).respond(
        Trial(0), record(), clock, 10.0)
    assert answer == Response(None, 12.0) and answer.timed_out
    assert clock.now() == 22.0


def test_random_rejects_bad_options():
    with pytest.raises(ConfigError, match="median_s must be > 0, got -1"):
        RandomResponder(seed=1, median_s=-1)
    with pytest.raises(ConfigError, match="sigma must be >= 0"):
        RandomResponder(seed=1, sigma=-0.1)


def test_respond_at_never_goes_back():
    clock = VirtualClock(15.0)
    assert respond_at(clock, record(), 1.0, None, 3) == Response(3, 1.0)
    assert clock.now() == 15.0  # a response during the stimulus keeps the clock where it is


def test_keypad_refuses_pause_key_as_answer():
    with pytest.raises(ConfigError, match="response key 'q' is also a pause key"):
        KeypadResponder(keys={"q": 1})


def test_keypad_needs_a_terminal(tmp_path):
    with open(tmp_path / "f", "w") as handle:
        keypad = KeypadResponder(fd=handle.fileno())
        with pytest.raises(SessionError, match="needs a terminal on stdin"):
            keypad.open()
