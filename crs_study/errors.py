"""The exception tree of crs-study.

Every error a user can cause or meet derives from :class:`CrsStudyError`; the command line
prints such errors as one line and exits non-zero (``--debug`` shows the traceback).

::

    CrsStudyError
    ├── ConfigError            a device file, protocol or analysis plan is malformed
    │   ├── DeviceFileError    device (layout) TOML files
    │   ├── ProtocolError      protocol TOML files
    │   └── PlanError          analysis plan TOML files
    ├── DisplayModelError      a display model cannot produce a surface
    │   └── CollapseError      the compressed beam collapses (Eq. 4 / critical load)
    ├── RenderError            a target cannot be rendered on the device
    ├── DeviceError            serial or simulated device failure, out-of-range setpoint
    ├── SessionError           runner and session state (locks, completed sessions, resume)
    ├── DatasetError           stored dataset is missing, malformed or tampered with
    ├── AnalysisError          an analysis cannot be carried out
    └── ConsentError           consent missing, mismatched, malformed; withdrawal problems
"""

from __future__ import annotations


class CrsStudyError(Exception):
    """Root of every error crs-study raises on purpose."""


class ConfigError(CrsStudyError):
    """A configuration file (device, protocol, analysis plan) is malformed."""


class DeviceFileError(ConfigError):
    """A device (layout) file is malformed or describes an impossible device."""


class ProtocolError(ConfigError):
    """A protocol file is malformed or asks for something the device cannot do."""


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


class ConsentError(CrsStudyError):
    """Consent is missing, mismatched or malformed, or a withdrawal failed."""


class CrsStudyWarning(UserWarning):
    """Something odd but not wrong, which the command line prints as one line."""
