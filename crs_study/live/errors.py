"""Errors of the live link, under the package's one root :class:`~crs_study.errors.CrsStudyError`.

::

    CrsStudyError
    └── LiveError          the live link cannot run: an address, a port, a recording file, a trace
        └── PacketError    one datagram is not a finger packet (counted and dropped, never raised
                           out of a running session)

They live here rather than in :mod:`crs_study.errors` only because this package was written
beside a reorganisation of the others; they belong in that tree.
"""

from __future__ import annotations

from crs_study.errors import CrsStudyError


class LiveError(CrsStudyError):
    """The live link cannot run: a bad address, a port in use, a recording or trace file."""


class PacketError(LiveError):
    """A datagram that is not a valid finger packet (the reason says what was wrong)."""
