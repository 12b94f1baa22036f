"""Is the plan analysed the plan that was locked? (:func:`check_plan_lock`)

A lab locks its protocol and analysis plan before the first participant
(:mod:`crs_study.protocol.lock`); every session begun under the lock records it in its sidecar.
The analysis compares the plan it runs with that lock (or with a lock file a reviewer gives,
``analyze --lock``), key by key: the locked plan's text is in the lock, so a change is named
("primary.structure: 'maximal' when locked, now 'intercepts'"), not only detected by a hash.
It also says which sessions began before the lock, were recorded under an earlier lock, or ran
a protocol other than the locked one. What it finds is ``results.json``'s ``plan.lock`` and a
line of the report under the headline; a deviation is also a warning.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from typing import Any

import pandas as pd

from crs_study.analysis.plan import AnalysisPlan
from crs_study.dataset.lock_file import PlanLock
from crs_study.errors import CrsStudyError

#: What the check concludes: no lock recorded, the lock's plan unchanged, or deviations.
STATUSES = ("not locked", "unchanged", "changed")


@dataclass(frozen=True)
class LockCheck:
    """The plan analysed against its lock.

    Attributes
    ----------
    status : str
        One of :data:`STATUSES`.
    lock : PlanLock or None
        The lock compared with (the latest the sessions recorded, or the one given).
    deviations : tuple of str
        Every difference, one sentence each (empty when unchanged).
    """

    status: str
    lock: PlanLock | None = None
    deviations: tuple[str, ...] = ()

    def sentence(self) -> str:
        """One line for the report and the command's output."""
        if self.lock is None:
            return ("Plan not locked: no session recorded a plan lock (crs-study lock writes "
                    "one before the first participant).")
        when = self.lock.locked_at.date().isoformat()
        if not self.deviations:
            return (f"Plan locked on {when} (lock sha256 {self.lock.sha256[:12]}...), "
                    "unchanged.")
        return (f"Plan locked on {when} (lock sha256 {self.lock.sha256[:12]}...), with "
                f"{len(self.deviations)} deviation(s): " + "; ".join(self.deviations) + ".")

    def to_dict(self) -> dict[str, Any]:
        """``results.json``'s ``plan.lock``."""
        return {"status": self.status,
                "locked_at": None if self.lock is None else self.lock.locked_at.isoformat(),
                "sha256": None if self.lock is None else self.lock.sha256,
                "deviations": list(self.deviations)}


def check_plan_lock(plan: AnalysisPlan, sessions: pd.DataFrame,
                    given: PlanLock | None = None) -> LockCheck:
    """Compare ``plan`` (the one analysed) and the ``sessions`` (rows of
    :attr:`~crs_study.analysis.study_data.StudyData.sessions`: ``StartTime``,
    ``ProtocolSha256``, ``PlanLock``, ``PlanLockSha256``) with the lock ``given``, else the
    latest lock the sessions recorded."""
    recorded = _recorded_locks(sessions)
    lock = given if given is not None else max(recorded.values(), default=None,
                                               key=lambda lock: lock.locked_at)
    if lock is None:
        return LockCheck("not locked")
    deviations = _plan_changes(lock, plan)
    deviations += _session_deviations(lock, sessions)
    return LockCheck("changed" if deviations else "unchanged", lock, tuple(deviations))


def _recorded_locks(sessions: pd.DataFrame) -> dict[str, PlanLock]:
    """The locks the sessions recorded, by sha256 (a lock that does not read is skipped: the
    sidecar's integrity is checked by the loader)."""
    locks = {}
    if "PlanLock" not in sessions:
        return locks
    for text, sha in zip(sessions["PlanLock"], sessions["PlanLockSha256"], strict=True):
        if isinstance(text, str) and sha not in locks:
            try:
                locks[sha] = PlanLock.from_json(text)
            except CrsStudyError:
                continue
    return locks


def _plan_changes(lock: PlanLock, plan: AnalysisPlan) -> list[str]:
    """Every key of the plan whose value differs from the locked plan's."""
    try:
        locked = AnalysisPlan.from_dict(tomllib.loads(lock.plan_text), lock.plan_name)
    except (tomllib.TOMLDecodeError, CrsStudyError) as exc:
        return [f"the locked plan no longer reads with this software ({exc})"]
    then = _flatten(dataclasses.asdict(locked))
    now = _flatten(dataclasses.asdict(plan))
    changes = [f"{key}: {then.get(key)!r} when locked, now {now.get(key)!r}"
               for key in sorted(set(then) | set(now))
               if key != "source" and then.get(key) != now.get(key)]
    primary = [c for c in changes if c.startswith("primary.") or c.startswith("alpha")]
    others = [c for c in changes if c not in primary]
    sentences = []
    if primary:
        sentences.append("the primary test changed after the lock (" + ", ".join(primary) + ")")
    if others:
        sentences.append("the plan changed after the lock (" + ", ".join(others) + ")")
    return sentences


def _flatten(values: dict, prefix: str = "") -> dict[str, Any]:
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = list(value) if isinstance(value, tuple) else value
    return flat


def _session_deviations(lock: PlanLock, sessions: pd.DataFrame) -> list[str]:
    """Sessions begun before the lock, under another lock, or on another protocol."""
    sentences = []
    shas = sessions.get("PlanLockSha256", pd.Series([None] * len(sessions)))
    unlocked = [_name(row) for (_, row), sha in zip(sessions.iterrows(), shas, strict=True)
                if not isinstance(sha, str)]
    if unlocked:
        sentences.append(f"{len(unlocked)} of {len(sessions)} session(s) began before any lock "
                         f"({_some(unlocked)})")
    other = [_name(row) for (_, row), sha in zip(sessions.iterrows(), shas, strict=True)
             if isinstance(sha, str) and sha != lock.sha256]
    if other:
        sentences.append(f"{len(other)} session(s) were recorded under another lock "
                         f"({_some(other)})")
    protocols = [_name(row) for _, row in sessions.iterrows()
                 if isinstance(row.get("ProtocolSha256"), str)
                 and row["ProtocolSha256"] != lock.protocol_sha256]
    if protocols:
        sentences.append(f"{len(protocols)} session(s) ran a protocol other than the locked "
                         f"{lock.protocol_name} ({_some(protocols)})")
    return sentences


def _name(row: pd.Series) -> str:
    return f"sub-{row['participant']} ses-{row['session']}"


def _some(names: list[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more"
                                       if len(names) > shown else "")
