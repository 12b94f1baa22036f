"""Protocols: what a digit-identification study runs, read strictly and checked on the device.

The stage, in the order its modules build on each other:

* :mod:`~crs_study.protocol.model`: the frozen dataclasses (:class:`Protocol` and its
  tables), their closed choices and the checks of their fields;
* :mod:`~crs_study.protocol.plan`: a protocol, a participant and a session expanded into the
  fixed list of trials;
* :mod:`~crs_study.protocol.feasibility`: every check of a protocol against its device,
  as structured findings (:class:`Finding`);
* :mod:`~crs_study.protocol.odd_values`: odd but legal values, as warnings;
* :mod:`~crs_study.protocol.wire`: the protocol's stimuli on the wire (``validate``,
  ``device check``);
* :mod:`~crs_study.protocol.writer`: the model back to TOML, for a protocol changed in Python;
* :mod:`~crs_study.protocol.loader`: TOML to the model, strictly; :func:`load_protocol` (a
  file, a shipped protocol's name, or a protocol changed in Python).

Errors are one-line :class:`~crs_study.errors.ProtocolError` s carrying the file, the line and
the key path as attributes; the line locator is :mod:`crs_study._toml_lines`.
"""

from crs_study._toml_lines import find_line, toml_syntax_message
from crs_study.protocol.feasibility import (
    Feasibility,
    Finding,
    check_feasibility,
    check_on_device,
    collapse_delta,
)
from crs_study.protocol.loader import (
    as_protocol_error,
    load_protocol,
    protocol_from_dict,
    protocol_from_text,
)
from crs_study.protocol.model import (
    COUNTERBALANCING,
    FEEDBACK,
    LEVEL_PARAMETERS,
    MAX_LEVELS,
    MIN_FRAME_RATE_HZ,
    MIN_STROKE_SPEED_MM_S,
    OPTIONAL_KEYS,
    ORDERINGS,
    PAUSE_KEYS,
    PLACEMENTS,
    PRACTICE_IN,
    TABLE_KEYS,
    DesignSpec,
    LevelSpec,
    Protocol,
    ResponseSpec,
    StimulusSpec,
    analysis_plan_path,
    consent_form_path,
)
from crs_study.protocol.odd_values import (
    PAPER_LATENCY_S,
    WARN_DRAWING_S,
    WARN_ITI_S,
    WARN_LAG_FRACTION,
    WARN_SESSION_S,
    WARN_TIME_LIMIT_S,
    WARN_UNBROKEN_S,
    emit_warnings,
    protocol_warnings,
    warning_findings,
)
from crs_study.protocol.plan import PlannedTrial, TrialPlan, make_plan
from crs_study.protocol.wire import ConditionWire, WireBudget, wire_budget
from crs_study.protocol.writer import protocol_to_toml

__all__ = [
    "COUNTERBALANCING", "FEEDBACK", "LEVEL_PARAMETERS", "MAX_LEVELS", "MIN_FRAME_RATE_HZ",
    "MIN_STROKE_SPEED_MM_S", "OPTIONAL_KEYS", "ORDERINGS", "PAPER_LATENCY_S", "PAUSE_KEYS",
    "PLACEMENTS", "PRACTICE_IN", "TABLE_KEYS", "WARN_DRAWING_S", "WARN_ITI_S",
    "WARN_LAG_FRACTION", "WARN_SESSION_S", "WARN_TIME_LIMIT_S", "WARN_UNBROKEN_S",
    "ConditionWire", "DesignSpec", "Feasibility", "Finding", "LevelSpec", "PlannedTrial",
    "Protocol", "ResponseSpec", "StimulusSpec", "TrialPlan", "WireBudget",
    "analysis_plan_path", "as_protocol_error", "check_feasibility", "check_on_device",
    "collapse_delta", "consent_form_path", "emit_warnings", "find_line", "load_protocol",
    "make_plan", "protocol_from_dict", "protocol_from_text", "protocol_to_toml",
    "protocol_warnings", "toml_syntax_message",
    "warning_findings", "wire_budget",
]
