"""The plan lock as the runner meets it: find the lock of a protocol and refuse a protocol or
plan that no longer matches it (:func:`current_lock`).

While a lock is present (:mod:`crs_study.dataset.lock_file`), ``run`` and ``dry-run`` refuse
to collect more data under a changed protocol or analysis plan: restore the locked files, or
record the change with ``crs-study lock --relock`` first, so that the change is dated before
the data it concerns.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from crs_study.dataset.lock_file import PlanLock, find_lock, lock_path
from crs_study.errors import ProtocolError
from crs_study.paths import data_dir, shipped_protocols
from crs_study.protocol.model import Protocol, analysis_plan_path


def is_shipped(path: str | Path) -> bool:
    """True for a file of the package's own data (a shipped protocol is never locked: a lab
    locks its copy, made by ``crs-study init``)."""
    try:
        Path(path).resolve().relative_to(data_dir().resolve())
    except ValueError:
        return False
    return True


def locked_plan_path(lock: PlanLock, protocol: Protocol) -> Path | None:
    """The plan file the lock names, found as the protocol finds its own plan (beside the
    protocol, else the current folder, else shipped); None when it is gone."""
    if lock.plan_name == protocol.analysis_plan:
        return analysis_plan_path(protocol)
    path = Path(lock.plan_name)
    return path if path.is_file() else None


def current_lock(protocol: Protocol) -> PlanLock | None:
    """The lock of ``protocol``'s file, checked: None when it has none; a
    :class:`~crs_study.errors.ProtocolError` when the protocol or the plan no longer match
    it (``run`` refuses: lock again to record the change before more data)."""
    lock = find_lock(protocol.path)
    if lock is None:
        return None
    plan_path = locked_plan_path(lock, protocol)
    try:
        plan_bytes = None if plan_path is None else plan_path.read_bytes()
    except OSError:
        plan_bytes = None
    changed = lock.mismatch(protocol.sha256, plan_bytes)
    if changed is not None:
        raise ProtocolError(f"{lock_path(protocol.path)}: {changed}; restore the locked files, "
                            "or record the change with crs-study lock --relock before more "
                            "data")
    return lock


def kept_shipped_id(protocol: Protocol) -> str | None:
    """The name of the shipped protocol whose study id a copied protocol still has (None
    for a shipped protocol itself, or an id of its own). The id seeds every session's trial
    order and names the study in its datasets: a copy that keeps it shares both with every
    other lab that ran the shipped protocol."""
    if is_shipped(protocol.path):
        return None
    for name, path in shipped_protocols().items():
        try:
            shipped = tomllib.loads(path.read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError):
            continue
        if shipped.get("study", {}).get("id") == protocol.study_id:
            return name
    return None
