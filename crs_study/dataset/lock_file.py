"""The plan lock file: what a lab fixed before its first participant (:class:`PlanLock`).

``crs-study lock PROTOCOL`` writes ``<protocol>.lock.json`` beside the protocol file: the
protocol's sha256, the analysis plan's full text and sha256, the primary test's full
specification as the software reads it (every default filled in), the software version and the
time. The file is small and plain JSON so that a lab can timestamp it by publishing it (a
preregistration, OSF, a commit): a confirmatory test is confirmatory only if its plan was
fixed before the data (Nosek, Ebersole, DeHaven & Mellor 2018, "The preregistration
revolution", PNAS 115(11):2600).

Every session begun under a lock records its text and the sha256 of its bytes in the sidecar
(``PlanLock``, ``PlanLockSha256``): the lock is part of the stored dataset, read by the runner
(:mod:`crs_study.protocol.lock` refuses a protocol or plan that no longer matches it) and by
the analysis (:mod:`crs_study.analysis.plan_lock` compares the plan it runs with it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from crs_study._files import sha256_bytes, write_atomically
from crs_study.errors import ProtocolError

#: The lock file's format (written as ``LockFormat``; a reader refuses another).
LOCK_FORMAT = 1
#: ``digit_identification.toml`` is locked by ``digit_identification.lock.json`` beside it.
LOCK_SUFFIX = ".lock.json"
#: The keys of a lock file, in the order they are written.
LOCK_KEYS = ("LockFormat", "LockedAt", "SoftwareVersion", "Protocol", "ProtocolSha256",
             "Plan", "PlanSha256", "PrimaryTest", "PlanText")


@dataclass(frozen=True)
class PlanLock:
    """A lock file's content (:data:`LOCK_KEYS`).

    Attributes
    ----------
    locked_at : datetime
        When the lock was written (UTC, to the second).
    software_version : str
        The crs-study version that wrote it.
    protocol_name, plan_name : str
        The protocol and plan files' names (as found when locking).
    protocol_sha256, plan_sha256 : str
        sha256 of the protocol and plan files' bytes.
    primary : dict
        The primary test's full specification (the plan's ``[primary]`` with every default,
        plus ``alpha`` and ``conditions``), as plain JSON values.
    plan_text : str
        The plan file's full text, so that a later change can be listed key by key.
    """

    locked_at: datetime
    software_version: str
    protocol_name: str
    protocol_sha256: str
    plan_name: str
    plan_sha256: str
    primary: dict
    plan_text: str

    def to_json(self) -> str:
        """The lock file's text: a JSON object of :data:`LOCK_KEYS`, two-space indent."""
        values = (LOCK_FORMAT, self.locked_at.isoformat(), self.software_version,
                  self.protocol_name, self.protocol_sha256, self.plan_name, self.plan_sha256,
                  self.primary, self.plan_text)
        return json.dumps(dict(zip(LOCK_KEYS, values, strict=True)), indent=2,
                          ensure_ascii=False) + "\n"

    @property
    def sha256(self) -> str:
        """sha256 of :meth:`to_json`'s bytes (what a session records as ``PlanLockSha256``)."""
        return sha256_bytes(self.to_json().encode("utf-8"))

    @classmethod
    def from_json(cls, text: str, source: str | Path = "plan lock") -> PlanLock:
        """Read a lock's text; anything but a lock this software writes is a one-line
        :class:`~crs_study.errors.ProtocolError` naming ``source`` and the key."""
        try:
            data = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise ProtocolError(f"{source}: not a plan lock (not JSON: {exc})") from None
        if not isinstance(data, dict) or set(data) != set(LOCK_KEYS):
            keys = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ProtocolError(f"{source}: not a plan lock: expected the keys "
                                f"{', '.join(LOCK_KEYS)}, got {keys}")
        if data["LockFormat"] != LOCK_FORMAT:
            raise ProtocolError(f"{source}: LockFormat {data['LockFormat']!r}: this version "
                                f"reads format {LOCK_FORMAT}")
        for key in ("SoftwareVersion", "Protocol", "ProtocolSha256", "Plan", "PlanSha256",
                    "PlanText", "LockedAt"):
            if not isinstance(data[key], str):
                raise ProtocolError(f"{source}: {key}: expected a string, got "
                                    f"{type(data[key]).__name__}")
        if not isinstance(data["PrimaryTest"], dict):
            raise ProtocolError(f"{source}: PrimaryTest: expected a JSON object")
        try:
            locked_at = datetime.fromisoformat(data["LockedAt"])
        except ValueError:
            locked_at = None
        if locked_at is None or locked_at.tzinfo is None:
            raise ProtocolError(f"{source}: LockedAt: expected an ISO 8601 time with a UTC "
                                f"offset, got {data['LockedAt']!r}")
        if sha256_bytes(data["PlanText"].encode("utf-8")) != data["PlanSha256"]:
            raise ProtocolError(f"{source}: PlanSha256 is not the sha256 of PlanText: the "
                                "lock was edited by hand")
        return cls(locked_at, data["SoftwareVersion"], data["Protocol"],
                   data["ProtocolSha256"], data["Plan"], data["PlanSha256"],
                   data["PrimaryTest"], data["PlanText"])

    @classmethod
    def read(cls, path: str | Path) -> PlanLock:
        """Read the lock file at ``path``."""
        try:
            text = Path(path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ProtocolError(f"{path}: not a readable plan lock: {exc}") from None
        return cls.from_json(text, path)

    def write(self, path: str | Path) -> None:
        """Write the lock file durably (a crash leaves the old file or the new, never half)."""
        write_atomically(path, self.to_json())

    def mismatch(self, protocol_sha256: str, plan_bytes: bytes | None) -> str | None:
        """What no longer matches the lock (None when the protocol's and plan's bytes are
        the ones locked)."""
        changed = []
        if protocol_sha256 != self.protocol_sha256:
            changed.append(f"the protocol ({self.protocol_name})")
        if plan_bytes is None or sha256_bytes(plan_bytes) != self.plan_sha256:
            changed.append(f"the analysis plan ({self.plan_name})")
        if not changed:
            return None
        return (f"{' and '.join(changed)} changed since the plan was locked on "
                f"{self.locked_at.date().isoformat()}")


def lock_path(protocol_path: str | Path) -> Path:
    """Where the lock of the protocol file ``protocol_path`` is: beside it, ``<stem>``
    :data:`LOCK_SUFFIX`."""
    path = Path(protocol_path)
    return path.with_name(path.stem + LOCK_SUFFIX)


def find_lock(protocol_path: str | Path) -> PlanLock | None:
    """The lock beside the protocol file, or None when it has none."""
    path = lock_path(protocol_path)
    if not path.exists() and not path.is_symlink():
        return None
    return PlanLock.read(path)
