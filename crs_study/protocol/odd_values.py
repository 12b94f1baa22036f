"""Odd but legal values of a protocol: each a warning that names the key, the value and why.

STYLE rule 5: wrong values raise, odd ones warn (protocols/README.md, "Warnings"). The
thresholds (``WARN_*``) and what each warning says:

* ``design.repetitions``: the session is expected to last over 1.5 h
  (:func:`crs_study.protocol.plan.expected_duration_s`, what ``validate`` prints);
* ``design.break_every``: a block runs over 20 min without a break;
* ``responses.time_limit_s``: over 60 s;
* ``design.inter_trial_interval_s``: under 0.1 s (0 included);
* ``stimulus.stroke_speed_mm_s`` (or ``levels.values[i]`` when varied): so slow that a symbol's
  stimulus lasts over 15 s, or so fast that the device's 75 ms latency lags the bump by over a
  quarter of the symbol's height.

The expected durations come from the trial plan of an example participant (durations do not
depend on who or which session), so this module sits above :mod:`crs_study.protocol.plan`.
"""

from __future__ import annotations

import warnings

from crs_study._toml_lines import find_line
from crs_study.errors import CrsStudyWarning
from crs_study.protocol.feasibility import Finding, level_key
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import make_plan, trial_seconds
from crs_study.stimuli.stimulus import make_stimulus

#: A session expected to last longer than this (s):
WARN_SESSION_S = 90 * 60.0
#: ... a stretch of a block longer than this without a break (s):
WARN_UNBROKEN_S = 20 * 60.0
#: ... a time limit longer than this (s, from stimulus offset):
WARN_TIME_LIMIT_S = 60.0
#: ... an inter-trial interval shorter than this (s; about a simple reaction time):
WARN_ITI_S = 0.1
#: ... a symbol's stimulus lasting longer than this (s; the shipped 20 mm/s: 2 to 5 s):
WARN_DRAWING_S = 15.0
#: ... a stroke speed at which the device's latency lags the bump by more than this fraction
#: of the symbol's height; the latency is the paper's device's (75 ms: Wang, Meng & Chen 2025,
#: Methods).
WARN_LAG_FRACTION = 0.25
PAPER_LATENCY_S = 0.075


def warning_findings(protocol: Protocol) -> tuple[Finding, ...]:
    """The odd values of a checked protocol (module docstring), as ``"warning"`` findings
    with the line of their key."""
    found = _session_warnings(protocol) + _stroke_speed_warnings(protocol)
    return tuple(Finding("warning", key, message, values, find_line(protocol.text, key))
                 for key, message, values in found)


def protocol_warnings(protocol: Protocol) -> tuple[str, ...]:
    """Odd but legal values of a checked protocol, one line each: ``FILE:LINE: key: ...``."""
    return tuple(f.describe(str(protocol.path)) for f in warning_findings(protocol))


def emit_warnings(protocol: Protocol) -> None:
    """Issue each of ``protocol.warnings`` as a :class:`~crs_study.errors.CrsStudyWarning`
    (the command line prints ``crs-study COMMAND: warning: ...``)."""
    for message in protocol.warnings:
        warnings.warn(message, CrsStudyWarning, stacklevel=2)


_Found = list[tuple[str, str, dict]]  # (key path, message, values)


def _session_warnings(protocol: Protocol) -> _Found:
    layout = protocol.layout()
    found: _Found = []
    noun = protocol.symbol_set.noun
    plan = make_plan(protocol, "example", 1, 0)  # durations do not depend on who or which
    seconds = trial_seconds(protocol, plan, layout)
    total = sum(seconds)
    if total > WARN_SESSION_S:
        found.append(("design.repetitions", f"the session is expected to take "
                      f"{total / 3600:.1f} h ({len(plan)} trials at repetitions = "
                      f"{protocol.design.repetitions}; crs-study validate's estimate), over "
                      f"{WARN_SESSION_S / 3600:g} h: attention and touch sensitivity fade; fewer "
                      "repetitions, or the study split over sessions (--session N)",
                      {"expected_duration_s": total, "trials": len(plan)}))
    stretch, longest, block = 0.0, (0.0, 0), None
    for trial, s in zip(plan.trials, seconds, strict=True):
        if trial.block != block or trial.break_before:
            stretch, block = 0.0, trial.block
        stretch += s
        if stretch > longest[0]:
            longest = (stretch, trial.block)
    if longest[0] > WARN_UNBROKEN_S:
        every = protocol.design.break_every
        found.append(("design.break_every", f"block {longest[1] + 1} runs "
                      f"{longest[0] / 60:.0f} min without a break ("
                      + ("break_every = 0: no breaks" if not every else
                         f"a break every {every} trials") + f"), over "
                      f"{WARN_UNBROKEN_S / 60:g} min; expected a rest at least that often",
                      {"longest_unbroken_s": longest[0], "block": longest[1] + 1}))
    limit = protocol.responses.time_limit_s
    if limit is not None and limit > WARN_TIME_LIMIT_S:
        found.append(("responses.time_limit_s", f"{limit!r} s is a long time limit (over "
                      f"{WARN_TIME_LIMIT_S:g} s): a missed {noun} holds the session that "
                      "long; the shipped protocols use 10 s", {"time_limit_s": limit}))
    iti = protocol.inter_trial_interval_s
    if iti < WARN_ITI_S:
        found.append(("design.inter_trial_interval_s", f"{iti!r} s: the next {noun} starts "
                      f"less than {WARN_ITI_S:g} s (about a reaction time) after the answer, "
                      "before the hand is back at rest; the shipped protocols use 1 s",
                      {"inter_trial_interval_s": iti}))
    return found


def _stroke_speed_warnings(protocol: Protocol) -> _Found:
    layout = protocol.layout()
    found: _Found = []
    for i, level in enumerate(protocol.level_values):
        spec = protocol.stimulus_at(level)
        key = "stimulus.stroke_speed_mm_s"
        if protocol.levels is not None and protocol.levels.parameter == "stroke_speed_mm_s":
            key = level_key(protocol, i, level)
        at = "" if level is None else f"at {protocol.levels.parameter} = {level:g}: "
        speed = spec.stroke_speed_mm_s
        drawing = max(make_stimulus(protocol, layout, d, level).duration_s
                      for d in protocol.symbols)
        height_mm = spec.symbol_height_pitch * layout.pitch_mm
        noun = protocol.symbol_set.noun
        lag = speed * PAPER_LATENCY_S
        values = {"stroke_speed_mm_s": speed, "longest_drawing_s": drawing, "lag_mm": lag}
        if drawing > WARN_DRAWING_S:
            found.append((key, f"{at}{speed!r} mm/s is slow: the longest {noun} takes "
                          f"{drawing:.0f} s to draw, holds included (over {WARN_DRAWING_S:g} s; "
                          "the shipped 20 mm/s: 2 to 5 s)", values))
        elif lag > WARN_LAG_FRACTION * height_mm:
            found.append((key, f"{at}{speed!r} mm/s is fast: the device's "
                          f"{PAPER_LATENCY_S * 1e3:g} ms latency (the paper's) lags the bump by "
                          f"{lag:.1f} mm, over a quarter of the {noun}'s {height_mm:.1f} mm "
                          "height (the shipped 20 mm/s: 1.5 mm)", values))
    return found
