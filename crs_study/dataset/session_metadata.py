"""The session sidecar (``sub-<id>_ses-<n>_task-<task>_beh.json``) as typed, checked data.

:class:`SessionMetadata` is what the runner writes beside a session's trial file and reads
back to resume it: the protocol and device file (full text and sha256), the fingerprints a
resume must match, who and what ran the session, and its progress. :meth:`~SessionMetadata.
to_json` writes the JSON object crs-study has always written (same keys, same order, two-space
indent, a final newline), so a sidecar read and written again is byte for byte the same.

Reading is strict: a key the format does not have, a key it needs that is missing, or a value
of the wrong type is a one-line :class:`~crs_study.errors.DatasetError` naming the file and the
key. Two keys may be absent: ``StimulusSha256`` (sidecars begun by software older than the
stimulus fingerprint lack it; read as None, and the runner then records null: it cannot vouch
for trials drawn by older software). Two are written only when not empty: ``Interruptions``
(why the session stopped before its end: a sidecar of a session never interrupted, or written
by older software, has none) and ``AdaptiveStateSha256`` (only adaptive protocols have it,
read as None when absent: the fingerprint of the procedures' state after ``TrialsCompleted``
trials, :meth:`crs_study.adaptive.AdaptiveRun.fingerprint`; a resume replays the recorded
responses and must reach it). ``PlanLock`` and ``PlanLockSha256`` are written only for a
session begun while its protocol was locked (:mod:`crs_study.protocol.lock`): the lock's text
and the sha256 of its bytes.

The JSON keys are BIDS-style CamelCase; entries of ``Resumes`` have ``Time``, ``AtTrial``,
``DeviceURL``, ``SoftwareVersion``; entries of ``Faults`` ``trial``, ``time``, ``message``
(lower case, as written since the first version); entries of ``Interruptions`` ``Time``,
``AtTrial``, ``Cause``, ``Detail``, ``TrialCut``. Times are ISO 8601 with a UTC offset.
"""

from __future__ import annotations

import difflib
import json
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, ClassVar, Literal

from crs_study.errors import DatasetError

Status = Literal["running", "interrupted", "complete"]
ClockKind = Literal["real", "virtual"]
STATUSES: tuple[str, ...] = ("running", "interrupted", "complete")
CLOCKS: tuple[str, ...] = ("real", "virtual")
#: Keys a sidecar written by older software may lack (read as None).
OPTIONAL_KEYS = frozenset({"StimulusSha256", "AdaptiveStateSha256", "PlanLock",
                           "PlanLockSha256"})
#: Keys written only when not empty, read as ``()`` (or None, when optional) when absent
#: (sessions never interrupted, fixed protocols, and every sidecar older software wrote, have
#: none).
WHEN_PRESENT_KEYS = frozenset({"Interruptions", "AdaptiveStateSha256", "PlanLock",
                               "PlanLockSha256"})
#: Why a session stopped before its end (:class:`Interruption`): the experimenter's pause key,
#: a signal (SIGINT is Ctrl-C), a device fault, the participant's consent withdrawn, another
#: error (a full disk), or a crash found on resume (killed, power cut: the sidecar still said
#: ``running``).
CAUSES: tuple[str, ...] = ("pause-key", "signal", "device-fault", "consent-withdrawn", "error",
                           "crash")

_SHA256 = re.compile(r"[0-9a-f]{64}")
_LABEL = re.compile(r"[A-Za-z0-9]+")


def now_utc() -> datetime:
    """The current time in UTC, to the second (what the sidecar records)."""
    return datetime.now(UTC).replace(microsecond=0)


class _Invalid(Exception):
    """A value of the wrong type or range: the message says what was expected."""


class _Located(_Invalid):
    """A problem whose message already names its key path (inside Resumes or Faults)."""


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


# --- value readers: JSON value -> attribute (raising _Invalid) ---------------------------------

def _text(value: Any) -> str:
    if not isinstance(value, str):
        raise _Invalid(f"expected a string, got {_short(value)}")
    return value


def _whole(minimum: int) -> Callable[[Any], int]:
    def read(value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise _Invalid(f"expected a whole number >= {minimum}, got {_short(value)}")
        return value
    return read


def _positive_number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not math.isfinite(value) or value <= 0:
        raise _Invalid(f"expected a number > 0, got {_short(value)}")
    return float(value)


def _sha256(value: Any) -> str:
    if not isinstance(value, str) or not _SHA256.fullmatch(value):
        raise _Invalid(f"expected a sha256 (64 lower-case hex digits), got {_short(value)}")
    return value


def _label(value: Any) -> str:
    if not isinstance(value, str) or not _LABEL.fullmatch(value):
        raise _Invalid(f"expected a label of letters and digits, got {_short(value)}")
    return value


def _time(value: Any) -> datetime:
    try:
        parsed = datetime.fromisoformat(value) if isinstance(value, str) else None
    except ValueError:
        parsed = None
    if parsed is None or parsed.tzinfo is None:
        raise _Invalid(f"expected an ISO 8601 time with a UTC offset, got {_short(value)}")
    return parsed


def _bool(value: Any) -> bool:
    if not isinstance(value, bool):
        raise _Invalid(f"expected true or false, got {_short(value)}")
    return value


def _choice(options: tuple[str, ...]) -> Callable[[Any], str]:
    def read(value: Any) -> str:
        if value not in options:
            raise _Invalid(f"expected one of {list(options)}, got {_short(value)}")
        return value
    return read


def _or_none(read: Callable[[Any], Any]) -> Callable[[Any], Any]:
    def read_optional(value: Any) -> Any:
        return None if value is None else read(value)
    return read_optional


def _dump(value: Any) -> Any:
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, tuple | list):
        return [item.to_dict() if isinstance(item, _Record) else item for item in value]
    return value


class _Record:
    """JSON object <-> frozen dataclass, strictly, by the class's ``_KEYS`` table."""

    #: (JSON key, attribute, reader) in the order the keys are written.
    _KEYS: ClassVar[tuple[tuple[str, str, Callable[[Any], Any]], ...]]

    def __post_init__(self) -> None:
        """Each attribute must be what reading its JSON value gives (type and range)."""
        for key, attribute, read in self._KEYS:
            value = getattr(self, attribute)
            try:
                parsed = read(_dump(value))
                if parsed != value or type(parsed) is not type(value):
                    raise _Invalid(f"expected a {type(parsed).__name__}, got {_short(value)}")
            except _Invalid as problem:
                raise DatasetError(f"{type(self).__name__}.{attribute} ({key}): "
                                   f"{problem}") from None

    def to_dict(self) -> dict[str, Any]:
        """The JSON object (plain types), keys in their written order (a key of
        :data:`WHEN_PRESENT_KEYS` only when not empty)."""
        return {key: _dump(getattr(self, attribute)) for key, attribute, _ in self._KEYS
                if key not in WHEN_PRESENT_KEYS or getattr(self, attribute)}

    @classmethod
    def _parse(cls, data: Any, path: str = "") -> Any:
        """The record from a JSON object; problems are :class:`_Invalid` naming the key."""
        prefix = f"{path}." if path else ""
        if not isinstance(data, Mapping):
            raise _Located(f"{path or 'the sidecar'}: expected a JSON object, got "
                           f"{_short(data)}")
        known = [key for key, _, _ in cls._KEYS]
        for key in data:
            if key not in known:
                close = difflib.get_close_matches(str(key), known, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise _Located(f"unknown key {prefix}{key}{hint}; expected only "
                               f"{', '.join(known)}")
        values = {}
        for key, attribute, read in cls._KEYS:
            if key not in data:
                if key in OPTIONAL_KEYS or key in WHEN_PRESENT_KEYS:
                    values[attribute] = None if key in OPTIONAL_KEYS else ()
                    continue
                raise _Located(f"missing key {prefix}{key}")
            try:
                values[attribute] = read(data[key])
            except _Located:
                raise
            except _Invalid as problem:
                raise _Located(f"{prefix}{key}: {problem}") from None
        return cls(**values)


def _entries(kind: type[_Record], key: str) -> Callable[[Any], tuple]:
    def read(value: Any) -> tuple:
        if not isinstance(value, list):
            raise _Invalid(f"expected a list, got {_short(value)}")
        return tuple(kind._parse(item, f"{key}[{i}]") for i, item in enumerate(value))
    return read


@dataclass(frozen=True)
class Resume(_Record):
    """One resume of the session: when, at which trial, on what device and software."""

    time: datetime
    at_trial: int
    device_url: str
    software_version: str

    _KEYS = (("Time", "time", _time), ("AtTrial", "at_trial", _whole(0)),
             ("DeviceURL", "device_url", _text),                  # the device the session began on
             ("SoftwareVersion", "software_version", _text))


@dataclass(frozen=True)
class Fault(_Record):
    """A device fault that interrupted trial ``trial`` (rerun on resume, ``device_fault=1``)."""

    trial: int
    time: datetime
    message: str

    _KEYS = (("trial", "trial", _whole(0)), ("time", "time", _time),
             ("message", "message", _text))


@dataclass(frozen=True)
class Interruption(_Record):
    """Why the session stopped before its end, and where (:data:`CAUSES`).

    ``at_trial`` is the number of trials stored when it happened (the trial it cut, or the
    next one); ``trial_cut`` is true when that trial's stimulus had begun, so the participant
    may have felt part of it: its rerun's row then says ``rerun = 1``. ``detail`` says more
    (the signal's name, the fault's message).
    """

    time: datetime
    at_trial: int
    cause: str
    detail: str
    trial_cut: bool

    _KEYS = (("Time", "time", _time), ("AtTrial", "at_trial", _whole(0)),
             ("Cause", "cause", _choice(CAUSES)), ("Detail", "detail", _text),
             ("TrialCut", "trial_cut", _bool))


@dataclass(frozen=True)
class SessionMetadata(_Record):
    """A session's sidecar. Build one with the fields, or read one with :meth:`from_json` or
    :meth:`read`; :meth:`to_json` is the file's text.

    The fingerprints a resume must match are ``protocol_sha256``, ``seed``,
    ``counterbalance``, ``plan_sha256``, ``device_file_sha256`` and ``stimulus_sha256``
    (:data:`FINGERPRINTS`); ``trials_sha256`` is the sha256 of the trial file's bytes when
    the sidecar was last written.
    """

    task_name: str
    task_description: str
    instructions: str
    protocol_text: str
    protocol_sha256: str
    protocol_path: str
    study_id: str
    study_version: str
    device_file_text: str
    device_file_sha256: str
    device_url: str
    software_version: str
    seed: int
    counterbalance: int
    plan_sha256: str
    stimulus_sha256: str | None
    participant: str
    session: int
    consent_form_version: str
    responder: str
    clock: ClockKind
    frame_rate_hz: float
    start_time: datetime
    end_time: datetime | None
    status: Status
    trials_planned: int
    trials_completed: int
    trials_sha256: str | None
    resumes: tuple[Resume, ...] = ()
    faults: tuple[Fault, ...] = ()
    interruptions: tuple[Interruption, ...] = ()
    adaptive_state_sha256: str | None = None
    plan_lock: str | None = None
    plan_lock_sha256: str | None = None

    _KEYS = (
        ("TaskName", "task_name", _label),
        ("TaskDescription", "task_description", _text),
        ("Instructions", "instructions", _text),
        ("Protocol", "protocol_text", _text),                # the protocol file's full text
        ("ProtocolSha256", "protocol_sha256", _sha256),
        ("ProtocolPath", "protocol_path", _text),            # as given (paths.recorded_path)
        ("StudyId", "study_id", _text),
        ("StudyVersion", "study_version", _text),
        ("DeviceFile", "device_file_text", _text),           # the device file's full text
        ("DeviceFileSha256", "device_file_sha256", _sha256),
        ("DeviceURL", "device_url", _text),                  # the device the session began on
        ("SoftwareVersion", "software_version", _text),
        ("Seed", "seed", _whole(0)),
        ("Counterbalance", "counterbalance", _whole(0)),     # the index the plan was made with
        ("PlanSha256", "plan_sha256", _sha256),              # the trial plan (checked on resume)
        ("StimulusSha256", "stimulus_sha256", _or_none(_sha256)),  # every bump path shown
        ("Participant", "participant", _label),
        ("Session", "session", _whole(1)),
        ("ConsentFormVersion", "consent_form_version", _text),
        ("Responder", "responder", _text),
        ("Clock", "clock", _choice(CLOCKS)),
        ("FrameRateHz", "frame_rate_hz", _positive_number),
        ("StartTime", "start_time", _time),
        ("EndTime", "end_time", _or_none(_time)),
        ("Status", "status", _choice(STATUSES)),
        ("TrialsPlanned", "trials_planned", _whole(0)),
        ("TrialsCompleted", "trials_completed", _whole(0)),
        ("TrialsSha256", "trials_sha256", _or_none(_sha256)),  # the _beh.tsv bytes, last write
        # the adaptive procedures' state after TrialsCompleted trials (adaptive protocols)
        ("AdaptiveStateSha256", "adaptive_state_sha256", _or_none(_sha256)),
        # the plan lock present when the session began (crs_study.protocol.lock): its text
        # and the sha256 of its bytes (sessions of a protocol never locked have neither)
        ("PlanLock", "plan_lock", _or_none(_text)),
        ("PlanLockSha256", "plan_lock_sha256", _or_none(_sha256)),
        ("Resumes", "resumes", _entries(Resume, "Resumes")),  # one per resume
        ("Faults", "faults", _entries(Fault, "Faults")),     # device faults during trials
        ("Interruptions", "interruptions",                   # why it stopped, when it did
         _entries(Interruption, "Interruptions")),
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.trials_completed > self.trials_planned:
            raise DatasetError(f"SessionMetadata: {self.trials_completed} trials completed of "
                               f"{self.trials_planned} planned")

    # --- reading and writing ---
    @classmethod
    def from_dict(cls, data: Any, source: str | Path = "session sidecar") -> SessionMetadata:
        """From the parsed JSON object; every problem names ``source`` and the key."""
        try:
            return cls._parse(data)
        except _Invalid as problem:
            raise DatasetError(f"{source}: {problem}") from None

    @classmethod
    def from_json(cls, text: str | bytes, source: str | Path = "session sidecar"
                  ) -> SessionMetadata:
        """From the sidecar's text; not JSON, or any key problem, is a one-line
        :class:`~crs_study.errors.DatasetError` naming ``source``."""
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise DatasetError(f"{source}: not a readable session sidecar: {exc}") from None
        except RecursionError:  # json recurses once per level of nesting
            raise DatasetError(f"{source}: not a readable session sidecar: arrays or objects "
                               "nested too deeply") from None
        return cls.from_dict(data, source)

    @classmethod
    def read(cls, path: str | Path) -> SessionMetadata:
        """Read the sidecar file at ``path``."""
        try:
            text = Path(path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: not a readable session sidecar: {exc}") from None
        return cls.from_json(text, path)

    def to_json(self) -> str:
        """The sidecar's text: the JSON object, two-space indent, UTF-8 as is, final newline."""
        return json.dumps(self.to_dict(), indent=2, ensure_ascii=False) + "\n"

    # --- what callers ask of a session ---
    @property
    def is_complete(self) -> bool:
        return self.status == "complete"

    @property
    def simulated_device(self) -> bool:
        """Recorded on the simulated device (``sim://``) rather than the real one."""
        return self.device_url.startswith("sim://")

    @property
    def virtual_clock(self) -> bool:
        return self.clock == "virtual"

    def fingerprints(self) -> dict[str, Any]:
        """The values a resume must match, by JSON key (:data:`FINGERPRINTS`)."""
        by_key = {key: attribute for key, attribute, _ in self._KEYS}
        return {key: getattr(self, by_key[key]) for key in FINGERPRINTS}

    def cut_trials(self) -> set[int]:
        """Trials an interruption cut after their stimulus began (rerun with ``rerun = 1``)."""
        return {i.at_trial for i in self.interruptions if i.trial_cut}

    def with_progress(self, status: Status, trials_completed: int, trials_sha256: str,
                      end_time: datetime | None, adaptive_state_sha256: str | None = None
                      ) -> SessionMetadata:
        """A copy with the session's progress updated (what each sidecar write changes)."""
        return replace(self, status=status, trials_completed=trials_completed,
                       trials_sha256=trials_sha256, end_time=end_time,
                       adaptive_state_sha256=adaptive_state_sha256)


#: What a stored session must match to be resumed: JSON key -> how a message names it.
FINGERPRINTS: dict[str, str] = {
    "ProtocolSha256": "protocol file",
    "Seed": "seed",
    "Counterbalance": "counterbalance",
    "PlanSha256": "trial plan",
    "DeviceFileSha256": "device file",
    "StimulusSha256": "stimulus (the bump paths this software draws)",
}

#: Every key every sidecar has, in written order (then those of :data:`WHEN_PRESENT_KEYS`).
SIDECAR_KEYS: tuple[str, ...] = tuple(key for key, _, _ in SessionMetadata._KEYS
                                      if key not in WHEN_PRESENT_KEYS)
