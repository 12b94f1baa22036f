"""A damaged consent register: a torn last line is repaired, a withdrawal always goes through,
consent is never granted from a damaged register; a second consent for a label is a renewal
said out loud. Each case runs the ``crs-study`` command on a real register: the
reproductions as processes of their own, the rest through its ``main`` in the test's
process."""

from __future__ import annotations

import json
import stat
import subprocess
from pathlib import Path

import pytest
from _cli import crs_study as run_crs_study

FORM = "consent_form"


def crs_study(*args, register: Path, process: bool = False) -> subprocess.CompletedProcess:
    """``crs-study ARGS`` with ``register`` as the consent register: a process of its own
    when ``process`` (the reproductions), else in this one (:mod:`_cli`)."""
    return run_crs_study(*args, process=process, env={"CRS_STUDY_CONSENT_DIR": str(register)},
                         timeout=120)


def record(register: Path, label: str, *more: str, process: bool = False
           ) -> subprocess.CompletedProcess:
    return crs_study("consent", "record", "--form", FORM, "--experimenter", "AB",
                     "--participant", label, *more, register=register, process=process)


def session(register: Path, label: str, out: Path, process: bool = False
            ) -> subprocess.CompletedProcess:
    return crs_study("run", "pilot", "--participant", label, "--device", "sim://",
                     "--responder", "random", "--out", out, register=register,
                     process=process)


def one_error_line(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.fixture
def register(tmp_path) -> Path:
    folder = tmp_path / "register"
    assert record(folder, "p1").returncode == 0
    return folder


def test_a_torn_consent_line_fails_closed_then_any_consent_command_sets_it_aside(
        register, tmp_path):
    path = register / "register.jsonl"
    whole = path.read_bytes()
    torn = b'{"event": "consent", "experimenter": "AB", "form_pa'   # a power cut mid-append
    path.write_bytes(whole + torn)
    killed = register / ".register-torn-20260101T000000000000Z.bin.tmp"  # an earlier repair,
    killed.write_bytes(torn[:9])                                 # killed before its rename
    refused = session(register, "p1", tmp_path / "ds", process=True)
    assert "register.jsonl:2: not a consent register line" in one_error_line(refused)
    assert not (tmp_path / "ds").exists()                      # nothing ran, nothing written
    listed = crs_study("consent", "list", register=register, process=True)
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.split()[:2] == ["p1", "consented"]
    assert "repaired: " in listed.stderr and "register.jsonl:2: a torn last line" in \
        listed.stderr and "record it again" in listed.stderr
    assert path.read_bytes() == whole
    (backup,) = register.glob("register-torn-*.bin")
    assert backup.read_bytes() == torn
    assert not killed.exists()
    assert stat.S_IMODE(backup.stat().st_mode) == 0o600         # it may hold a name
    assert session(register, "p1", tmp_path / "ds").returncode == 0


def test_a_torn_withdrawal_is_completed_not_lost(register, tmp_path):
    path = register / "register.jsonl"
    path.write_bytes(path.read_bytes() + b'{"event": "withdrawal", "participant": "p1", "ti')
    again = record(register, "p2", process=True)      # the next append repairs first
    assert again.returncode == 0, again.stderr
    assert "it was the withdrawal of p1, now recorded whole" in again.stderr
    events = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(e["event"], e["participant"]) for e in events] == [
        ("consent", "p1"), ("withdrawal", "p1"), ("consent", "p2")]
    assert "withdrew consent" in one_error_line(session(register, "p1", tmp_path / "ds"))


def test_a_withdrawal_goes_past_an_unreadable_line_and_names_it(register, tmp_path):
    assert record(register, "p2").returncode == 0
    path = register / "register.jsonl"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], "not json {", lines[1]]) + "\n")
    dataset = tmp_path / "ds"
    dataset.mkdir()
    (dataset / "dataset_description.json").write_text("{}")
    (register / "audit.jsonl").write_bytes(b'{"event": "withdrawal", "partic')  # torn too
    for args in (["--register-only"], ["--dataset", dataset]):
        label = "p2" if args == ["--register-only"] else "p1"
        done = crs_study("consent", "withdraw", "--participant", label, *args,
                         register=register, process=True)
        assert done.returncode == 0, done.stderr
        assert "register.jsonl:2: not a consent register line" in done.stderr
        assert f"consent record of {label} marked withdrawn" in done.stdout
    listed = crs_study("consent", "list", register=register)
    assert listed.returncode == 0 and "Traceback" not in listed.stderr
    assert [line.split()[:2] for line in listed.stdout.splitlines()] == [
        ["p1", "withdrawn"], ["p2", "withdrawn"]]
    assert "register.jsonl:2" in listed.stderr
    # granting consent from a damaged register fails closed: a record, a session
    assert "register.jsonl:2" in one_error_line(record(register, "p3"))
    assert "register.jsonl:2" in one_error_line(session(register, "p3", tmp_path / "d2"))


def test_a_second_consent_for_a_label_needs_renew_and_keeps_the_first(register):
    first = (register / "register.jsonl").read_text()
    refused = one_error_line(record(register, "p1", "--name", "Ada Lovelace", process=True))
    assert "already consented" in refused and "--renew" in refused
    assert (register / "register.jsonl").read_text() == first        # nothing written
    renewed = record(register, "p1", "--name", "Ada King", "--renew")
    assert renewed.returncode == 0 and "renews the record of" in renewed.stdout
    listed = crs_study("consent", "list", "--show-names", register=register)
    rows = [line.split()[:2] for line in listed.stdout.splitlines()]
    assert rows == [["p1", "renewed"], ["p1", "consented"]] and "Ada King" in listed.stdout
    as_json = json.loads(crs_study("consent", "list", "--json", register=register).stdout)
    assert len(as_json["earlier"]) == 1 and "name" not in as_json["earlier"][0]


def test_run_help_says_a_person_needs_consent_on_sim_too(tmp_path):
    text = " ".join(crs_study("run", "--help", register=tmp_path, process=True).stdout.split())
    assert "real device (not sim://)" not in text
    assert "consent record first (crs-study consent record) on every device, sim:// " \
           "included" in text
