"""A session that is missing or cannot be read is never dropped silently.

Before: ``rm -rf ds/sub-sim02`` (or ``chmod 000`` on it) and ``crs-study analyze ds`` exited 0
with 2 of 3 participants and no word. Now each session the dataset shows existed (its row in
participants.tsv, its sidecar, its sourcedata, the record of analysis outputs: the reasons are
in crs_study/dataset/evidence.py) but that is not read is a warning naming the participant,
in the printed output, results.json and the report, and an error under ``--strict``; a
withdrawal, which removes every trace, is not.

Root ignores ``chmod 000``, so unreadability is made in ways root meets too: a folder or a
named pipe in place of the trial file, bytes that are not UTF-8; the permission case runs
only as another user.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest
from _cli import crs_study
from _session_helpers import quick_analysis_protocol

from crs_study.analysis.load import load_datasets
from crs_study.dataset import SessionPaths
from crs_study.errors import DatasetError


@pytest.fixture(scope="module")
def three(tmp_path_factory) -> Path:
    """A dry-run of three simulated participants, sim01..sim03 (copied by :func:`dataset`),
    whose protocol names a plan with a random intercept per participant: these tests read
    which sessions the analysis took and what it says of the others, never the GLMM."""
    folder = tmp_path_factory.mktemp("three")
    done = crs_study("dry-run", quick_analysis_protocol(folder), "--participants", 3, "--out",
                     folder / "ds", "--responder", "random")
    assert done.returncode == 0, done.stderr
    return folder / "ds"


@pytest.fixture
def dataset(three, tmp_path) -> Path:
    shutil.copytree(three, tmp_path / "ds", symlinks=True)
    return tmp_path / "ds"


def _sim02(dataset: Path) -> SessionPaths:
    return SessionPaths(dataset, "sim02", 1)


def _remove_participant_row(dataset: Path, label: str) -> None:
    table = dataset / "participants.tsv"
    lines = table.read_text().splitlines(keepends=True)
    table.write_text("".join(line for line in lines if not line.startswith(f"sub-{label}\t")))


def test_a_deleted_session_is_named_in_every_output_and_refused_under_strict(dataset,
                                                                            tmp_path):
    shutil.rmtree(dataset / "sub-sim02")
    out = tmp_path / "out"
    done = crs_study("analyze", dataset, "--out", out)
    assert done.returncode == 0, done.stderr
    loud = [line for line in done.stderr.splitlines() if "sub-sim02 ses-1" in line]
    assert len(loud) == 1 and loud[0].startswith("crs-study analyze: WARNING:")
    assert "possible tampering" in loud[0] and "sourcedata/sub-sim02/ses-1" in loud[0]
    results = json.loads((out / "results.json").read_text())
    assert results["n_participants"] == 2
    assert [w for w in results["warnings"] if "sub-sim02 ses-1 has no trial file" in w]
    assert "sub-sim02 ses-1 has no trial file" in (out / "report.md").read_text()
    refused = crs_study("analyze", dataset, "--out", out, "--strict")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1
    assert "error:" in refused.stderr and "sub-sim02 ses-1" in refused.stderr


def _folder(paths: SessionPaths) -> None:
    paths.tsv.unlink()
    paths.tsv.mkdir()


def _fifo(paths: SessionPaths) -> None:
    paths.tsv.unlink()
    os.mkfifo(paths.tsv)


def _latin1(paths: SessionPaths) -> None:
    data = paths.tsv.read_bytes()
    paths.tsv.write_bytes(data.replace(b"random", "rändom".encode("latin-1"), 1))


@pytest.mark.parametrize("damage, says", [
    (_folder, "a folder, not a file"),
    (_fifo, "a named pipe, not a file"),
    (_latin1, "not UTF-8 text (byte 0xe4 at offset"),
])
def test_an_unreadable_trial_file_is_a_warning_naming_the_participant(dataset, damage, says):
    damage(_sim02(dataset))
    data = load_datasets(dataset)   # a named pipe must not block the read
    assert sorted(data.trials["participant"].unique()) == ["sim01", "sim03"]
    named = [w for w in data.warnings if "sim02" in w]
    assert len(named) == 1, data.warnings
    assert says in named[0] and "participant 'sim02'" in named[0]
    with pytest.raises(DatasetError, match=re.escape(says)):
        load_datasets(dataset, strict=True)


def test_an_unreadable_session_is_reported_by_the_command_too(dataset, tmp_path):
    _fifo(_sim02(dataset))
    done = crs_study("analyze", dataset, "--out", tmp_path / "out", process=True,
                     timeout=60)
    assert done.returncode == 0, done.stderr
    assert "named pipe" in done.stderr and "participant 'sim02'" in done.stderr


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a folder whatever its mode")
def test_a_folder_without_permission_is_reported(dataset):
    folder = dataset / "sub-sim02"
    folder.chmod(0)
    try:
        data = load_datasets(dataset)
        assert [w for w in data.warnings if "participant 'sim02'" in w]
        with pytest.raises(DatasetError, match="sim02"):
            load_datasets(dataset, strict=True)
    finally:
        folder.chmod(0o755)


@pytest.mark.parametrize("traces_left, says", [
    ("sidecar", "sub-sim02/ses-1/beh/sub-sim02_ses-1_task-digitid_beh.json show(s)"),
    ("participants.tsv", "participant 'sim02' is listed in participants.tsv"),
    ("outputs record", "listed in the record of analysis outputs"),
])
def test_each_trace_of_a_deleted_session_is_enough(dataset, tmp_path, traces_left, says):
    if traces_left == "outputs record":   # an earlier analysis held sim02's trials
        assert crs_study("analyze", dataset, "--out", tmp_path / "out").returncode == 0
    paths = _sim02(dataset)
    paths.tsv.unlink()
    if traces_left != "sidecar":
        shutil.rmtree(dataset / "sub-sim02")
    shutil.rmtree(dataset / "sourcedata" / "sub-sim02")
    if traces_left != "participants.tsv":
        _remove_participant_row(dataset, "sim02")
    data = load_datasets(dataset)
    named = [w for w in data.warnings if "sim02" in w]
    assert len(named) == 1 and says in named[0] and "possible tampering" in named[0], named
    with pytest.raises(DatasetError, match="sim02"):
        load_datasets(dataset, strict=True)


def test_a_withdrawal_is_not_a_missing_session(dataset, tmp_path):
    assert crs_study("analyze", dataset, "--out", tmp_path / "out").returncode == 0
    withdrawn = crs_study("consent", "withdraw", "--participant", "sim02", "--dataset", dataset)
    assert withdrawn.returncode == 0, withdrawn.stderr
    data = load_datasets(dataset, strict=True)
    assert sorted(data.trials["participant"].unique()) == ["sim01", "sim03"]
    assert not [w for w in data.warnings if "sim02" in w]


def test_when_no_session_is_readable_the_error_says_why(dataset):
    for label in ("sim01", "sim02", "sim03"):
        _folder(SessionPaths(dataset, label, 1))
    with pytest.raises(DatasetError, match=r"no readable session in .*: .*a folder, not a "
                       r"file") as refused:
        load_datasets(dataset)
    assert "\n" not in str(refused.value)


def test_a_named_pipe_for_the_outputs_record_is_one_line_not_a_hang(dataset, tmp_path):
    # the record is read by every analysis and every withdrawal: a named pipe in its place
    # would wait for a writer for ever (the subprocess timeout fails the test if it does)
    from crs_study.dataset.outputs import registry_path
    record = registry_path(dataset)
    record.unlink(missing_ok=True)
    os.mkfifo(record)
    done = crs_study("analyze", dataset, "--out", tmp_path / "out", process=True,
                     timeout=60)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "record of analysis outputs (a named pipe, not a file)" in done.stderr
    withdraw = crs_study("consent", "withdraw", "--participant", "sim02", "--dataset", dataset,
                         "--dry-run", process=True, timeout=60)
    assert withdraw.returncode == 2 and "a named pipe, not a file" in withdraw.stderr


def test_a_named_pipe_for_the_dataset_description_leaves_the_folder_name(dataset):
    description = dataset / "dataset_description.json"
    description.unlink()
    os.mkfifo(description)
    data = load_datasets(dataset)   # must not wait on the pipe
    assert sorted(data.trials["participant"].unique()) == ["sim01", "sim02", "sim03"]
    assert dataset.name in data.trials["dataset"].unique().tolist()
