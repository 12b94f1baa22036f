"""A forged adaptive estimate is found by replay: the estimate, its interval and the reversals
are derived from the levels and responses, so an edit to them (with ``TrialsSha256``
recomputed to match) is refused by a resume and by ``analyze --strict``, and flagged (naming
the row) and recomputed by a plain analysis."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from _cli import crs_study
from _session_helpers import adaptive_protocol

from crs_study.analysis.load import load_datasets

STEM = "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh"


@pytest.fixture(scope="module", params=["quest-plus", "staircase"])
def recorded(request, tmp_path_factory):
    """A dry-run of a simulated participant of a tiny adaptive protocol."""
    folder = tmp_path_factory.mktemp(request.param)
    protocol = adaptive_protocol(folder, procedure=request.param, trials=8)
    done = crs_study("dry-run", protocol, "--participants", 1, "--out", folder / "ds",
                     "--responder", "random")
    assert done.returncode == 0, done.stderr
    return protocol, folder / "ds"


def one_error(stderr: str) -> bool:
    """One error line, the last (the protocol's odd-value warnings may come before it)."""
    errors = [line for line in stderr.splitlines() if ": error: " in line]
    return "Traceback" not in stderr and len(errors) == 1 and \
        stderr.strip().splitlines()[-1] == errors[0]


def forge(dataset: Path, column: str) -> tuple[int, str]:
    """Change ``column`` in the last test row that has an estimate, and recompute the
    sidecar's ``TrialsSha256`` so the file hashes as recorded; (line number, old value)."""
    tsv, sidecar = dataset / f"{STEM}.tsv", dataset / f"{STEM}.json"
    lines = tsv.read_text(encoding="utf-8").split("\n")
    at = lines[0].split("\t").index(column)
    estimate = lines[0].split("\t").index("adaptive_estimate")
    line = max(k for k in range(1, len(lines))
               if lines[k] and lines[k].split("\t")[estimate] != "n/a")
    cells = lines[line].split("\t")
    old = cells[at]
    if column == "adaptive_reversal":
        cells[at] = "1" if old == "0" else "0"
    elif column == "adaptive_reversals":
        cells[at] = str(int(old) + 3)
    else:
        cells[at] = "0.300000"
    lines[line] = "\t".join(cells)
    tsv.write_text("\n".join(lines), encoding="utf-8")
    data = json.loads(sidecar.read_text(encoding="utf-8"))
    data["TrialsSha256"] = hashlib.sha256(tsv.read_bytes()).hexdigest()
    sidecar.write_text(json.dumps(data, indent=2), encoding="utf-8")
    return line + 1, old


def test_the_untouched_dataset_replays_without_a_word(recorded):
    loaded = load_datasets(recorded[1], strict=True)
    assert not [w for w in loaded.warnings if "replay" in w]
    assert loaded.trials["adaptive_estimate"].notna().any()


@pytest.mark.parametrize("column", ["adaptive_estimate", "adaptive_ci_low",
                                    "adaptive_ci_high", "adaptive_reversal",
                                    "adaptive_reversals"])
def test_a_forged_derived_column_is_flagged_recomputed_and_refused_by_strict(
        recorded, tmp_path, column):
    dataset = tmp_path / "ds"
    shutil.copytree(recorded[1], dataset)
    original = load_datasets(recorded[1]).trials
    line, old = forge(dataset, column)
    loaded = load_datasets(dataset)
    (flag,) = [w for w in loaded.warnings if "replaying the recorded levels" in w]
    assert f"{STEM}.tsv: row {line}: {column}" in flag and "possible tampering" in flag
    columns = ["adaptive_estimate", "adaptive_ci_low", "adaptive_ci_high",
               "adaptive_reversal", "adaptive_reversals"]
    assert loaded.trials[columns].equals(original[columns])      # the replayed values
    if column == "adaptive_estimate":  # as the user meets it: analyze --strict refuses
        done = crs_study("analyze", dataset, "--strict", "--out", tmp_path / "out")
        assert done.returncode == 2 and one_error(done.stderr), done.stderr
        assert f"row {line}: adaptive_estimate '0.300000' stored" not in done.stderr
        assert f"row {line}: adaptive_estimate 0.3 stored, but replaying" in done.stderr
        assert not (tmp_path / "out").exists()


def test_a_resume_refuses_a_forged_estimate(recorded, tmp_path):
    protocol, source = recorded
    dataset = tmp_path / "ds"
    shutil.copytree(source, dataset)
    line, _ = forge(dataset, "adaptive_estimate")
    before = (dataset / f"{STEM}.tsv").read_bytes()
    done = crs_study("run", protocol, "--participant", "sim01", "--device", "sim://",
                     "--responder", "random", "--out", dataset)
    assert done.returncode == 2 and one_error(done.stderr), done.stderr
    assert f"row {line - 1}: adaptive_estimate '0.300000' stored, but replaying the " \
           "recorded levels and responses gives" in done.stderr
    assert (dataset / f"{STEM}.tsv").read_bytes() == before
