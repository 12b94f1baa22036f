"""A session that stopped before its end is reported as interrupted, never
as tampered with, and a sidecar that disagrees with its trial file in a way no interruption
explains stays a tampering alarm.

How an interruption leaves the files (crs_study.dataset.session_store's docstring, the
contract these tests hold the analysis to): rows are appended to the ``_beh.tsv`` one write
each, and the sidecar is rewritten after them, every trial in a real run but only every
``UNDURABLE_SIDECAR_EVERY`` (10) trials in a dry-run; a SIGKILL leaves the sidecar's status
``running``, its ``TrialsCompleted`` up to 10 rows behind the file (``TrialsSha256`` the hash
of the rows it counts), and possibly a torn last line. The first test makes that state with a
real SIGKILL of ``crs-study dry-run`` (as tests/test_resume_crash.py does); the others build
each state byte by byte from an uninterrupted session, so both sides of the line are tested
on the same data.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _cli import crs_study
from _session_helpers import quick_analysis_protocol, tiny_protocol
from analysis_fixtures import edit_sidecar

from crs_study._files import sha256_bytes
from crs_study.analysis.load import load_datasets
from crs_study.dataset import SessionPaths
from crs_study.errors import DatasetError
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec


def _kill_when_rows(command: list[str], tsv_glob: str, root: Path, rows: int) -> None:
    """Start ``command`` and SIGKILL it once a trial file under ``root`` holds ``rows``."""
    child = subprocess.Popen([sys.executable, "-m", "crs_study", *map(str, command)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and child.poll() is None:
            found = list(root.glob(tsv_glob))
            if found and found[0].read_bytes().count(b"\n") > rows:
                break
            time.sleep(0.005)
        assert child.poll() is None, "the dry-run ended before it could be killed"
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()


@pytest.mark.slow
def test_a_killed_dry_run_is_interrupted_not_tampered(tmp_path):
    # the GLMM is not read: the plan's random intercept per participant is enough
    protocol, dataset = quick_analysis_protocol(tmp_path, repetitions=30), tmp_path / "ds"
    command = ["dry-run", protocol, "--participants", 1, "--out", dataset,
               "--responder", "random"]
    _kill_when_rows(command, "sub-*/ses-*/beh/*_beh.tsv", dataset, 25)
    paths = SessionPaths(dataset, "sim01", 1)
    sidecar = json.loads(paths.sidecar.read_text())
    assert sidecar["Status"] == "running"  # killed: as a SIGKILL mid-session leaves it
    for strict in ([], ["--strict"]):
        analysed = crs_study("analyze", dataset, "--out", tmp_path / "out", *strict)
        assert analysed.returncode == 0, analysed.stderr
        assert "TAMPERED" not in analysed.stderr and "tampering" not in analysed.stderr
        assert "session status is 'running': the session stopped before its end" \
            in analysed.stderr
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert any("stopped before its end" in w for w in results["warnings"])
    assert "stopped before its end" in (tmp_path / "out" / "report.md").read_text()
    # the same command completes the session, and the analysis then has nothing to say of it
    again = crs_study(*command)
    assert again.returncode == 0, again.stderr
    analysed = crs_study("analyze", dataset, "--out", tmp_path / "out", "--strict")
    assert analysed.returncode == 0, analysed.stderr
    assert "stopped before its end" not in analysed.stderr
    assert "status is" not in analysed.stderr


@pytest.fixture(scope="module")
def complete_session(tmp_path_factory) -> tuple[bytes, dict]:
    """The trial file and sidecar of one uninterrupted dry-run-like session (virtual clock,
    no per-trial durability): 38 trials."""
    folder = tmp_path_factory.mktemp("complete")
    spec = SessionSpec(tiny_protocol(folder, repetitions=6), "sim01", folder / "ds", "sim://",
                       1, "random", "virtual", durable=False)
    run_session(spec)
    paths = SessionPaths(folder / "ds", "sim01", 1)
    return paths.tsv.read_bytes(), json.loads(paths.sidecar.read_text())


def _lines(data: bytes) -> list[bytes]:
    return data.splitlines(keepends=True)


def _stopped(tmp_path: Path, complete: tuple[bytes, dict], *, recorded: int, rows: int,
             torn: int = 0, **sidecar) -> SessionPaths:
    """A copy of ``complete`` as an interruption would leave it: ``rows`` whole rows (and
    ``torn`` bytes of the next), the sidecar ``running`` with ``recorded`` of them counted
    and hashed; ``sidecar`` then changes keys of it (to make states no kill makes)."""
    data, meta = complete
    lines = _lines(data)
    dataset = tmp_path / "ds"
    paths = SessionPaths(dataset, "sim01", 1)
    paths.beh_dir.mkdir(parents=True)
    paths.tsv.write_bytes(b"".join(lines[:rows + 1]) + lines[rows + 1][:torn])
    paths.sidecar.write_text(json.dumps(meta))
    edit_sidecar(paths.sidecar, **{"Status": "running", "EndTime": None,
                                   "TrialsCompleted": recorded,
                                   "TrialsSha256": sha256_bytes(b"".join(lines[:recorded + 1])),
                                   **sidecar})
    return paths


@pytest.mark.parametrize("recorded, rows, torn", [
    (20, 20, 0),     # killed just after a sidecar write
    (20, 27, 0),     # the sidecar lagging by 7 rows
    (20, 30, 0),     # ... by the most it can (10)
    (20, 26, 17),    # and a row torn by the kill
    (0, 9, 0),       # killed before the first sidecar write after the start
])
def test_what_an_interruption_leaves_is_analysed_as_interrupted(tmp_path, complete_session,
                                                                 recorded, rows, torn):
    _stopped(tmp_path, complete_session, recorded=recorded, rows=rows, torn=torn)
    for strict in (False, True):
        data = load_datasets(tmp_path / "ds", strict=strict)
        assert len(data.trials) == rows
        assert not [w for w in data.warnings if "TAMPERED" in w or "tampering" in w]
        note = [w for w in data.warnings if "stopped before its end" in w]
        assert len(note) == 1 and f"its {rows} of 38 trials are analysed" in note[0]
        assert ("torn last row" in note[0]) == bool(torn)
        assert (f"holds {rows - recorded} row(s) more" in note[0]) == (rows > recorded)


def _rewrite_row(paths: SessionPaths, row: int) -> None:
    lines = _lines(paths.tsv.read_bytes())
    cells = lines[row + 1].split(b"\t")
    cells[-1] = b"9\n" if cells[-1] != b"9\n" else b"8\n"   # a changed last cell
    lines[row + 1] = b"\t".join(cells)
    paths.tsv.write_bytes(b"".join(lines))


@pytest.mark.parametrize("how, recorded, rows, change, says", [
    ("more rows than the sidecar can lag by", 20, 31, {}, "TrialsCompleted is 20 but the file "
     "holds 31 trials"),
    ("a recorded row rewritten", 20, 27, {"rewrite": 5}, r"TAMPERED\? sha256"),
    ("fewer rows than recorded", 20, 17, {}, "TrialsCompleted is 20 but the file holds 17"),
    ("a complete session with fewer rows", 38, 35, {"Status": "complete"},
     r"TAMPERED\? sha256"),
    ("a real-clock session lagging by 2", 20, 22, {"Clock": "real"},
     "TrialsCompleted is 20 but the file holds 22"),
])
def test_what_no_interruption_explains_stays_a_tampering_alarm(tmp_path, complete_session,
                                                               how, recorded, rows, change,
                                                               says):
    rewrite = change.pop("rewrite", None)
    paths = _stopped(tmp_path, complete_session, recorded=recorded, rows=rows, **change)
    if change.get("Status") == "complete":   # as written at the end: the whole file hashed
        edit_sidecar(paths.sidecar, TrialsSha256=sha256_bytes(complete_session[0]))
        paths.tsv.write_bytes(b"".join(_lines(complete_session[0])[:rows + 1]))
    if rewrite is not None:
        _rewrite_row(paths, rewrite)
    data = load_datasets(tmp_path / "ds")
    assert any("TAMPERED" in w or "tampering" in w for w in data.warnings), how
    assert not [w for w in data.warnings if "stopped before its end" in w]
    assert any(re.search(says, w) for w in data.warnings), data.warnings
    with pytest.raises(DatasetError, match=r"TAMPERED\?|tampering"):
        load_datasets(tmp_path / "ds", strict=True)
