"""The exception tree of crs-study.

Every error a user can cause or meet derives from :class:`CrsStudyError`; the command line
prints such errors as one line and exits non-zero (``--debug`` shows the traceback).

::

    CrsStudyError
    ├── ConfigError            a device file, protocol or analysis plan is malformed
    │   ├── DeviceFileError    device (layout) TOML files
    │   ├── ProtocolError      protocol TOML files
    │   │   └── ProtocolProblems   every problem one reading of a protocol found
    │   └── PlanError          analysis plan TOML files
    ├── DisplayModelError      a display model cannot produce a surface
    │   └── CollapseError      the compressed beam collapses (Eq. 4 / critical load)
    ├── RenderError            a target cannot be rendered on the device
    ├── DeviceError            serial or simulated device failure, out-of-range setpoint
    ├── SessionError           runner and session state (locks, completed sessions, resume)
    ├── DatasetError           stored dataset is missing, malformed or tampered with
    ├── AnalysisError          an analysis cannot be carried out
    ├── MeasurementError       a surface measurement cannot be read, registered or compared
    └── ConsentError           consent missing, mismatched, malformed; withdrawal problems
"""

from __future__ import annotations


class CrsStudyError(Exception):
    """Root of every error crs-study raises on purpose."""


class ConfigError(CrsStudyError):
    """A configuration file (device, protocol, analysis plan, strokes file) is malformed.

    Raised with the bare ``reason`` and, where known, where it is: ``source`` (the file),
    ``line`` (1-based, in that file) and ``key_path`` (the key at fault, e.g.
    ``design.repetitions``, ``levels.values[2]``, or ``design.repetiton`` for a stray key).
    ``shown_path`` is the key path printed before the reason: the key path itself, or for a
    missing or unknown key the table holding it (``design: unknown key 'repetiton' ...``).
    The message reads ``SOURCE:LINE: SHOWN_PATH: REASON``, each part left out when unknown;
    a loader that learns the file or the line later sets the attribute (the message follows),
    so nothing ever parses them back out of the text. An error made from one message string
    alone (``ConfigError("crs2d.toml: beams: ...")``) keeps that string as its message.

    Attributes
    ----------
    reason : str
        What was expected and what was received, without the location.
    source : str or None
    line : int or None
    key_path : str or None
    shown_path : str or None
    """

    def __init__(self, reason: str, *, source: str | None = None, line: int | None = None,
                 key_path: str | None = None, shown_path: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.source = None if source is None else str(source)
        self.line = line
        self.key_path = key_path
        self.shown_path = key_path if shown_path is None else shown_path

    @property
    def detail(self) -> str:
        """The message without the file and line: ``SHOWN_PATH: REASON`` (or the reason)."""
        return f"{self.shown_path}: {self.reason}" if self.shown_path else self.reason

    def __str__(self) -> str:
        if self.source is None:
            return self.detail
        where = self.source if self.line is None else f"{self.source}:{self.line}"
        return f"{where}: {self.detail}"

    def __reduce__(self):  # keep the attributes through pickling (process pools, Dask)
        return (self.__class__, (self.reason,), self.__dict__)


class DeviceFileError(ConfigError):
    """A device (layout) file is malformed or describes an impossible device."""


class ProtocolError(ConfigError):
    """A protocol file is malformed or asks for something the device cannot do."""


class ProtocolProblems(ProtocolError):
    """Several problems of one protocol, found in one reading
    (:func:`crs_study.protocol.problems.protocol_problems`).

    ``problems`` holds each as a :class:`ProtocolError`, the first being the one loading the
    protocol raises (whose reason, file, line and key this error carries); the message is
    theirs, one a line.
    """

    def __init__(self, problems: tuple[ProtocolError, ...] | list[ProtocolError]) -> None:
        self.problems = tuple(problems)
        first = self.problems[0]
        super().__init__(first.reason, source=first.source, line=first.line,
                         key_path=first.key_path, shown_path=first.shown_path)

    def __str__(self) -> str:
        return "\n".join(str(p) for p in self.problems)

    def __reduce__(self):
        return (self.__class__, (self.problems,))


class PlanError(ConfigError):
    """An analysis plan file is malformed."""


class DisplayModelError(CrsStudyError):
    """A display model cannot produce the surface asked for."""


class CollapseError(DisplayModelError):
    """The compressed beam collapses: no stable shape exists (paper Eq. 4, critical load)."""


class RenderError(CrsStudyError):
    """A target cannot be rendered on the device."""


class DeviceError(CrsStudyError):
    """Serial or simulated device failure, or a setpoint outside calibrated limits."""


class SessionError(CrsStudyError):
    """Session state problem: a lock held, a completed session, a resume mismatch."""


class DatasetError(CrsStudyError):
    """The stored dataset is missing, malformed or fails its checksums."""


class AnalysisError(CrsStudyError):
    """An analysis cannot be carried out on the data given."""


class MeasurementError(CrsStudyError):
    """A surface measurement (a DIC export, its fiducials, a measurement folder) cannot be
    read, registered to the display or compared with the model."""


class ConsentError(CrsStudyError):
    """Consent is missing, mismatched or malformed, or a withdrawal failed."""


class CrsStudyWarning(UserWarning):
    """Something odd but not wrong, which the command line prints as one line."""
