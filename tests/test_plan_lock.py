"""The plan lock, as a lab meets it: `crs-study lock`, then dry-runs (the same runner as real
sessions) that record it, then `crs-study analyze` that reports "unchanged" or every deviation.

The workflow checked is the one of preregistration (Nosek, Ebersole, DeHaven & Mellor 2018,
"The preregistration revolution", PNAS 115(11):2600): the plan is fixed, and published, before
the first participant; a reader can tell whether the analysis is the one planned.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.analysis.plan_lock import check_plan_lock
from crs_study.analysis.study_data import load_dataset
from crs_study.cli import main
from crs_study.dataset.lock_file import LOCK_KEYS, PlanLock, lock_path
from crs_study.errors import ProtocolError


@pytest.fixture
def lab(tmp_path, monkeypatch):
    """A lab folder made by `crs-study init`, the current directory."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "lab"]) == 0
    monkeypatch.chdir(tmp_path / "lab")
    return tmp_path / "lab"


def _dry_run(participants: int, out: str = "ds") -> int:
    return main(["dry-run", "protocols/pilot.toml", "--participants", str(participants),
                 "--out", out])


def _sidecars(dataset: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(dataset.glob("sub-*/ses-*/beh/*.json"))]


def _set_structure(lab: Path, structure: str) -> None:
    plan = lab / "analysis" / "pilot.toml"
    text = plan.read_text()
    assert 'structure = "maximal"' in text or f'structure = "{structure}"' in text
    plan.write_text(text.replace('structure = "maximal"', f'structure = "{structure}"'))


def test_a_locked_plan_is_recorded_by_every_session_and_reported_unchanged(lab, capsys):
    assert main(["lock", "protocols/pilot.toml"]) == 0
    lock_file = lab / "protocols" / "pilot.lock.json"
    lock = PlanLock.read(lock_file)
    # the lock is the files' bytes (sha256 of each, computed here by hashlib)
    assert lock.protocol_sha256 == hashlib.sha256(
        (lab / "protocols" / "pilot.toml").read_bytes()).hexdigest()
    assert lock.plan_sha256 == hashlib.sha256(
        (lab / "analysis" / "pilot.toml").read_bytes()).hexdigest()
    assert lock.primary["structure"] == "maximal" and lock.primary["p_value"] == "chi2"
    assert lock.primary["random_effects"] == ["participant", "digit"]
    assert _dry_run(2) == 0
    sidecars = _sidecars(lab / "ds")
    assert len(sidecars) == 2
    for sidecar in sidecars:
        assert sidecar["PlanLockSha256"] == hashlib.sha256(lock_file.read_bytes()).hexdigest()
        assert sidecar["PlanLock"] == lock_file.read_text()
    capsys.readouterr()
    assert main(["analyze", "ds", "--include-simulated"]) == 0
    out = capsys.readouterr().out
    assert f"Plan locked on {lock.locked_at.date().isoformat()}" in out
    assert "unchanged" in out
    results = json.loads((lab / "ds" / "derivatives" / "crs-study" / "results.json").read_text())
    assert results["plan"]["lock"]["status"] == "unchanged"
    assert results["plan"]["lock"]["sha256"] == sidecars[0]["PlanLockSha256"]
    report = (lab / "ds" / "derivatives" / "crs-study" / "report.md").read_text()
    assert "unchanged" in report.split("## ")[0]  # beside the headline, before any section


def test_a_plan_changed_after_the_lock_refuses_sessions_and_is_named_by_the_analysis(lab,
                                                                                      capsys):
    assert main(["lock", "protocols/pilot.toml"]) == 0
    assert _dry_run(2) == 0
    _set_structure(lab, "intercepts")
    capsys.readouterr()
    # more data under a changed plan: refused in one line, nothing written
    before = sorted(p.relative_to(lab) for p in (lab / "ds").rglob("*"))
    assert _dry_run(3) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "analysis plan" in err and "--relock" in err
    assert sorted(p.relative_to(lab) for p in (lab / "ds").rglob("*")) == before
    # the analysis names the key that changed, as a deviation and a warning
    data = load_dataset(lab / "ds", include_simulated=True)
    check = check_plan_lock(data.plan, data.sessions)
    assert check.status == "changed"
    assert check.deviations == ("the primary test changed after the lock (primary.structure: "
                                "'maximal' when locked, now 'intercepts')",)
    # the plan itself reads with its new structure: the analysis runs what it is given
    assert data.plan.primary.structure == "intercepts"


def test_a_relock_keeps_the_old_lock_and_the_analysis_tells_the_sessions_apart(lab, capsys):
    assert _dry_run(1) == 0                          # sub-sim01 before any lock
    assert main(["lock", "protocols/pilot.toml"]) == 0
    assert _dry_run(2) == 0                          # sub-sim02 under the first lock
    _set_structure(lab, "intercepts")
    capsys.readouterr()
    assert main(["lock", "protocols/pilot.toml"]) == 2  # a change needs --relock
    assert "--relock" in capsys.readouterr().err
    assert main(["lock", "protocols/pilot.toml", "--relock"]) == 0
    kept = sorted((lab / "protocols").glob("pilot.lock.*.json"))
    assert len(kept) == 1 and PlanLock.read(kept[0]).primary["structure"] == "maximal"
    assert _dry_run(3) == 0                          # sub-sim03 under the second lock
    data = load_dataset(lab / "ds", include_simulated=True)
    check = check_plan_lock(data.plan, data.sessions)
    assert check.lock.primary["structure"] == "intercepts"   # the latest lock
    assert check.deviations == (
        "1 of 3 session(s) began before any lock (sub-sim01 ses-1)",
        "1 session(s) were recorded under another lock (sub-sim02 ses-1)")
    # a reviewer checks against the lock published first
    check = check_plan_lock(data.plan, data.sessions, PlanLock.read(kept[0]))
    assert check.deviations[0].startswith("the primary test changed after the lock "
                                          "(primary.structure: 'maximal' when locked")


def test_a_protocol_changed_after_the_lock_is_refused_too(lab, capsys):
    assert main(["lock", "protocols/pilot.toml"]) == 0
    protocol = lab / "protocols" / "pilot.toml"
    protocol.write_text(protocol.read_text() + "\n# a comment is a change of the file\n")
    capsys.readouterr()
    assert _dry_run(1) == 2
    assert "the protocol (pilot.toml) changed since the plan was locked" in \
        capsys.readouterr().err
    assert not (lab / "ds").exists()


def test_unlocked_sessions_say_so_and_shipped_protocols_are_not_locked(lab, capsys):
    assert _dry_run(1) == 0
    data = load_dataset(lab / "ds", include_simulated=True)
    check = check_plan_lock(data.plan, data.sessions)
    assert check.status == "not locked" and check.lock is None
    assert "Plan not locked" in check.sentence()
    os.chdir(lab.parent)  # the name then means the shipped protocol
    capsys.readouterr()
    assert main(["lock", "pilot"]) == 2
    err = capsys.readouterr().err
    assert "shipped with crs-study" in err and "crs-study init" in err


def test_a_lock_edited_by_hand_is_refused_in_one_line(lab, capsys):
    assert main(["lock", "protocols/pilot.toml"]) == 0
    path = lock_path(lab / "protocols" / "pilot.toml")
    data = json.loads(path.read_text())
    data["PlanText"] = data["PlanText"].replace("maximal", "intercepts")
    path.write_text(json.dumps(data))
    capsys.readouterr()
    assert _dry_run(1) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "PlanSha256 is not the sha256 of PlanText" in err


@given(st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=3)
                    | st.dictionaries(st.sampled_from(LOCK_KEYS) | st.text(max_size=4), inner,
                                      max_size=10)))
def test_any_json_that_is_not_a_lock_is_a_one_line_error(value):
    try:
        PlanLock.from_json(json.dumps(value), "x.lock.json")
    except ProtocolError as error:
        assert "\n" not in str(error) and str(error).startswith("x.lock.json: ")
