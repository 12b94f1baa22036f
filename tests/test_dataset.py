"""The BIDS dataset writer: top-level files, participants, durable rows, torn tails, the lock."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study._files import write_atomically
from crs_study.dataset import Dataset, SessionStore, format_value, read_frame_log, schema
from crs_study.errors import DatasetError, SessionError


def _row(index: int) -> dict:
    row = {name: "n/a" for name in schema.TRIAL_COLUMNS}
    row.update(trial_index=index, condition="crs", digit=index % 10, onset=0.5 * index)
    return row


@pytest.fixture
def store(tmp_path):
    dataset = Dataset(tmp_path / "ds")
    dataset.ensure()
    with SessionStore(dataset.session_paths("p01", 1)) as held:
        yield held


def test_top_level_files_are_bids(tmp_path):
    dataset = Dataset(tmp_path / "ds")
    dataset.ensure()
    description = json.loads((tmp_path / "ds/dataset_description.json").read_text())
    assert description["DatasetType"] == "raw"
    assert description["GeneratedBy"][0]["Name"] == "crs-study"
    assert "BIDSVersion" in description
    columns = json.loads((tmp_path / f"ds/task-{schema.TASK}_beh.json").read_text())
    assert set(schema.TRIAL_COLUMNS) <= set(columns)
    assert (tmp_path / "ds/participants.tsv").read_text() == "participant_id\tcounterbalance\n"
    assert (tmp_path / "ds/README.md").read_text().startswith("# crs-study dataset")
    # BIDS: Levels is an object (level -> meaning); labels carry no Units (numeric only)
    assert columns["trial_type"]["Levels"].keys() == {"practice", "test"}
    assert columns["correct"]["Levels"] == {"0": "no", "1": "yes"}
    assert "Units" not in columns["condition"] and columns["onset"]["Units"] == "s"


def test_ensure_never_rewrites(tmp_path):
    dataset = Dataset(tmp_path / "ds")
    dataset.ensure()
    path = tmp_path / "ds/dataset_description.json"
    path.write_text('{"Name": "mine", "BIDSVersion": "1.10.0"}')
    dataset.ensure()
    assert json.loads(path.read_text())["Name"] == "mine"


def test_participants_counterbalance_by_arrival(tmp_path):
    dataset = Dataset(tmp_path / "ds")
    assert dataset.register_participant("b1") == 0
    assert dataset.register_participant("a2") == 1
    assert dataset.register_participant("b1") == 0  # known participants keep their index
    assert dataset.register_participant("c3", counterbalance=7) == 7
    assert dataset.participants() == {"a2": 1, "b1": 0, "c3": 7}
    lines = (tmp_path / "ds/participants.tsv").read_text().splitlines()
    assert lines[1:] == ["sub-a2\t1", "sub-b1\t0", "sub-c3\t7"]
    with pytest.raises(SessionError, match="counterbalance 0 .*--counterbalance 3"):
        dataset.register_participant("b1", counterbalance=3)


@pytest.mark.parametrize("label", ["sub-1", "p_1", "", "Ã©"])
def test_labels_must_be_bids(tmp_path, label):
    with pytest.raises(SessionError, match="letters and digits"):
        Dataset(tmp_path).session_paths(label, 1)


def test_session_number_must_be_positive(tmp_path):
    with pytest.raises(SessionError, match="session must be"):
        Dataset(tmp_path).session_paths("p1", 0)


def test_rows_round_trip_and_hash(store):
    store.create()
    for k in range(3):
        store.append_row(_row(k))
    data = store.paths.tsv.read_bytes()
    assert store.trials_sha256 == hashlib.sha256(data).hexdigest()
    again = SessionStore(store.paths)
    rows = again.recover_rows()
    assert [r["trial_index"] for r in rows] == ["0", "1", "2"]
    assert rows[2]["onset"] == "1.000000"
    assert again.trials_sha256 == store.trials_sha256


@pytest.mark.parametrize("tail", [b"3\tpractice\t0", b"\x00\x00\x00\x00", b"3\tx\n"],
                         ids=["no-newline", "zeros", "too-few-fields"])
def test_torn_tail_is_cut_and_kept(store, tail):
    store.create()
    for k in range(3):
        store.append_row(_row(k))
    good = store.paths.tsv.read_bytes()
    with open(store.paths.tsv, "ab") as handle:
        handle.write(tail)
    rows = SessionStore(store.paths).recover_rows()
    assert len(rows) == 3
    assert store.paths.tsv.read_bytes() == good
    backups = list(store.paths.source_dir.glob("*_beh-torn-*.bin"))
    assert [b.read_bytes() for b in backups] == [tail]


def test_a_backup_killed_before_its_rename_is_cleared_by_the_next_cut(store):
    """A kill inside the backup's atomic write leaves ``.<backup>.tmp`` and cuts nothing; the
    backup names differ by time, so only the next cut of the same file can clear it."""
    store.create()
    store.append_row(_row(0))
    good = store.paths.tsv.read_bytes()
    tail = b"1\tpractice\t0"
    with open(store.paths.tsv, "ab") as handle:
        handle.write(tail)
    store.paths.source_dir.mkdir(parents=True)
    killed = store.paths.source_dir / f".{store.paths.torn_backup('beh', '1').name}.tmp"
    killed.write_bytes(tail[:4])
    other = store.paths.source_dir / f".{store.paths.torn_backup('frames', '1').name}.tmp"
    other.write_bytes(b"not this file's")
    assert len(SessionStore(store.paths).recover_rows()) == 1
    assert store.paths.tsv.read_bytes() == good
    (backup,) = store.paths.source_dir.glob("*_beh-torn-*.bin")
    assert backup.read_bytes() == tail
    assert sorted(p.name for p in store.paths.source_dir.glob(".*")) == [other.name]


def test_torn_header_starts_over(store):
    store.paths.beh_dir.mkdir(parents=True, exist_ok=True)
    store.paths.tsv.write_bytes(b"trial_index\ttri")
    fresh = SessionStore(store.paths)
    assert fresh.recover_rows() == []
    fresh.create()
    fresh.append_row(_row(0))
    assert len(SessionStore(store.paths).recover_rows()) == 1


def test_damage_in_the_middle_is_an_error(store):
    store.create()
    for k in range(3):
        store.append_row(_row(k))
    lines = store.paths.tsv.read_bytes().split(b"\n")
    lines[2] = b"broken"
    store.paths.tsv.write_bytes(b"\n".join(lines))
    with pytest.raises(DatasetError, match=r":3: expected \d+ fields, got 1"):
        SessionStore(store.paths).recover_rows()


def test_wrong_header_is_an_error(store):
    store.paths.beh_dir.mkdir(parents=True, exist_ok=True)
    store.paths.tsv.write_text("a\tb\n1\t2\n")
    with pytest.raises(DatasetError, match="unexpected header 'a\\\\tb'"):
        SessionStore(store.paths).recover_rows()


def test_second_runner_is_refused(store):
    with pytest.raises(SessionError, match="in use by another runner"):
        SessionStore(store.paths).acquire()


def test_lock_dies_with_its_process(tmp_path):
    dataset = Dataset(tmp_path / "ds")
    paths = dataset.session_paths("p01", 1)
    script = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from crs_study.dataset import Dataset, SessionStore
        held = SessionStore(Dataset(Path({str(tmp_path / 'ds')!r})).session_paths("p01", 1))
        held.acquire()
        print("locked", flush=True)
        time.sleep(60)
    """)
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(SessionError, match="in use"):
            SessionStore(paths).acquire()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
        with SessionStore(paths):  # the kernel released the dead runner's lock
            pass
    finally:
        child.kill()
        child.wait()
        child.stdout.close()


def test_lock_file_is_hidden_and_named_for_withdrawal(store):
    # consent.withdraw looks for '*.lock' under sub-<id>/ to refuse a running session.
    assert store.paths.lock.name.startswith(".") and store.paths.lock.suffix == ".lock"
    assert store.paths.lock.parent.parent.name == "sub-p01"


def test_sidecar_atomic(store):
    store.write_sidecar({"Status": "running"})
    assert json.loads(store.paths.sidecar.read_text()) == {"Status": "running"}
    assert not list(store.paths.beh_dir.glob(".*.tmp"))


def test_frame_log_is_one_gzip_table(store):
    store.append_frames(0, ("frame", "due"), [(0, 0.0), (1, 1 / 15)])
    store.append_frames(1, ("frame", "due"), [(0, 2.0)])
    path = store.paths.frame_log
    assert path.is_relative_to(store.paths.root / "sourcedata")
    assert path.name == "sub-p01_ses-1_task-digitid_frames.tsv.gz"
    assert read_frame_log(path) == [{"trial": "0", "frame": "0", "due": "0.000000"},
                                    {"trial": "0", "frame": "1", "due": "0.066667"},
                                    {"trial": "1", "frame": "0", "due": "2.000000"}]


@pytest.mark.parametrize("damage", ["member-without-row", "torn-member"])
def test_frame_log_recovery(store, damage):
    store.create()
    for k in range(2):
        store.append_frames(k, ("frame",), [(0,), (1,)])
        store.append_row(_row(k))
    good = store.paths.frame_log.read_bytes()
    store.append_frames(2, ("frame",), [(0,)])  # killed before the row of trial 2
    if damage == "torn-member":
        data = store.paths.frame_log.read_bytes()
        store.paths.frame_log.write_bytes(data[:-5])
    fresh = SessionStore(store.paths)
    assert len(fresh.recover_rows()) == 2
    assert store.paths.frame_log.read_bytes() == good
    assert list(store.paths.source_dir.glob("*_frames-torn-*.bin"))
    fresh.append_frames(2, ("frame",), [(0,)])
    assert [r["trial"] for r in read_frame_log(store.paths.frame_log)] == ["0", "0", "1", "1",
                                                                           "2"]


def test_frame_log_missing_trials_is_an_error(store):
    store.create()
    store.append_frames(0, ("frame",), [(0,)])
    for k in range(2):
        store.append_row(_row(k))
    with pytest.raises(DatasetError, match="frame log holds trials up to 0, the trial file "
                                           "has 2 rows"):
        SessionStore(store.paths).recover_rows()


def test_write_atomically_replaces_whole(tmp_path):
    target = tmp_path / "x.json"
    write_atomically(target, "one")
    write_atomically(target, b"two")
    assert target.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]


def test_values_with_tabs_are_refused():
    with pytest.raises(DatasetError, match="tabs or newlines"):
        format_value("a\tb")


@pytest.mark.parametrize("value, text", [(None, "n/a"), (float("nan"), "n/a"), (True, "1"),
                                         (False, "0"), (-0.0, "0.000000"), (3, "3")])
def test_format_value_cases(value, text):
    assert format_value(value) == text


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=-1e6, max_value=1e6, allow_nan=False))
def test_floats_keep_microseconds(value):
    assert abs(float(format_value(value)) - value) <= 5e-7 + 1e-12 * abs(value)
