"""Lock a protocol's analysis plan before the first participant.

Writes PROTOCOL's lock file beside it (``<protocol>.lock.json``): the protocol's sha256, the
analysis plan's text and sha256, the primary test's full specification (every default filled
in), the software version and the time. Publish the file (a preregistration, OSF, a commit)
to timestamp it. While it is present, ``run`` and ``dry-run`` refuse a protocol or plan that
no longer matches it, every session records it, and ``analyze`` reports "plan locked on
DATE, unchanged" or lists every change since.

A changed plan is locked again with ``--relock`` (the old lock is kept as
``<protocol>.lock.<date>.json``): sessions recorded under the old lock keep it, and the
analysis reports both. A shipped protocol is not locked: copy it with ``crs-study init``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from crs_study import __version__
from crs_study._files import sha256_bytes
from crs_study.analysis.plan import AnalysisPlan, load_plan
from crs_study.dataset.lock_file import PlanLock, find_lock, lock_path
from crs_study.errors import ProtocolError
from crs_study.paths import resolve_protocol
from crs_study.protocol import analysis_plan_path, load_protocol
from crs_study.protocol.lock import is_shipped, kept_shipped_id


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", metavar="PROTOCOL", help="protocol file (TOML)")
    parser.add_argument("--plan", metavar="FILE", default=None,
                        help="the analysis plan to lock (default: the one the protocol names)")
    parser.add_argument("--relock", action="store_true",
                        help="replace an existing lock (the old one is kept beside it)")


def plain(value: Any) -> Any:
    """A plan's value as plain JSON (tuples as lists; dataclasses are given as dicts)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [plain(v) for v in value]
    return value


def primary_specification(plan: AnalysisPlan) -> dict:
    """The primary test as the software runs it: ``[primary]`` with every default, the
    level ``alpha`` and the ``conditions`` (plain JSON values)."""
    return {"alpha": plan.alpha, "conditions": plain(plan.conditions),
            **plain(dataclasses.asdict(plan.primary))}


def make_lock(protocol_source: str, plan_source: str | None = None) -> PlanLock:
    """The lock of a protocol file and its analysis plan (the protocol's own by default)."""
    protocol = load_protocol(protocol_source)
    if plan_source is None:
        plan_path, plan_name = analysis_plan_path(protocol), protocol.analysis_plan
        if plan_path is None:
            raise ProtocolError(f"{protocol.path}: its analysis plan {protocol.analysis_plan} "
                                "was not found; give one with --plan")
    else:
        plan_path = Path(plan_source)
        plan_name = str(plan_path.resolve())
    plan = load_plan(plan_path)  # a plan that does not read is never locked
    raw = plan_path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError(f"{plan_path}: not UTF-8 text") from None
    # to the microsecond: a relock within the second of the first lock is still the later one
    # (the analysis takes the latest lock the sessions recorded)
    return PlanLock(datetime.now(UTC), __version__, protocol.path.name, protocol.sha256, plan_name,
                    sha256_bytes(raw), primary_specification(plan), text)


def run(args: argparse.Namespace) -> int:
    protocol_path = resolve_protocol(args.protocol)
    if is_shipped(protocol_path):
        raise ProtocolError(f"{args.protocol} is a protocol shipped with crs-study: copy it "
                            "with crs-study init and lock the copy")
    lock = make_lock(args.protocol, args.plan)
    protocol = load_protocol(args.protocol)
    kept = kept_shipped_id(protocol)
    if kept is not None:
        print(f"crs-study lock: warning: study id {protocol.study_id!r} is the shipped {kept} "
              "protocol's: give the copy an id of its own ([study] id) before locking, since "
              "the id seeds every session's trial order", file=sys.stderr)
    target = lock_path(protocol_path)
    earlier = find_lock(protocol_path) if target.exists() or target.is_symlink() else None
    if earlier is not None:
        changed = earlier.mismatch(lock.protocol_sha256, lock.plan_text.encode("utf-8"))
        if changed is None and earlier.plan_name == lock.plan_name:
            print(f"{target}: already locked on "
                  f"{earlier.locked_at.isoformat(timespec='seconds')}, unchanged")
            return 0
        if not args.relock:
            raise ProtocolError(f"{target}: {changed or 'another plan file is named'}; lock "
                                "again with --relock (the old lock is kept)")
        kept = target.with_name(f"{protocol_path.stem}.lock."
                                f"{earlier.locked_at.strftime('%Y%m%dT%H%M%SZ')}.json")
        earlier.write(kept)
        print(f"the earlier lock is kept as {kept}")
    lock.write(target)
    spec = lock.primary
    print(f"locked {protocol_path.name} and its analysis plan {Path(lock.plan_name).name} on "
          f"{lock.locked_at.isoformat(timespec='seconds')}")
    print(f"  protocol sha256 {lock.protocol_sha256}")
    print(f"  plan sha256     {lock.plan_sha256}")
    print(f"  primary test    {spec['test']}, structure {spec['structure']}, random effects "
          f"{', '.join(spec['random_effects'])}, p {spec['p_value']}, alpha {spec['alpha']}")
    print(f"  lock sha256     {lock.sha256}")
    print(f"wrote {target}: publish it (a preregistration, OSF, a commit) to timestamp it")
    return 0
