"""The dataset a dry-run writes passes the BIDS validator (bids-validator-deno) without errors.

Besides complete dry-run sessions, the dataset holds a session with time-outs (``n/a``
values) and a torn-tail backup under sourcedata/ (which the validator ignores), as real
datasets will.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from _cli import crs_study as run_crs_study
from _session_helpers import record_consent, tiny_letter_protocol, tiny_protocol


@pytest.fixture(autouse=True)
def _consented():
    """p7k2m9q: people's labels, gated by consent on every device, sim:// too."""
    record_consent("p7k2m9q")


def validator() -> str | None:
    beside = Path(sys.executable).with_name("bids-validator-deno")
    return str(beside) if beside.exists() else shutil.which("bids-validator-deno")


def valid_report(dataset) -> dict:
    """The validator's JSON report of ``dataset``, checked to hold no error (exit status 0)."""
    done = subprocess.run([validator(), str(dataset), "--format", "json"], capture_output=True,
                          text=True, timeout=300)
    report = json.loads(done.stdout)
    errors = [i for i in report["issues"]["issues"] if i.get("severity") == "error"]
    assert errors == [], errors
    assert done.returncode == 0
    return report


def crs_study(*args: str) -> subprocess.CompletedProcess:
    done = run_crs_study(*args)
    assert done.returncode == 0, done.stderr
    return done


@pytest.mark.slow
@pytest.mark.skipif(validator() is None, reason="bids-validator-deno is not installed "
                    "(pip install -e '.[test]')")
def test_dry_run_dataset_is_valid_bids(tmp_path):
    protocol = tiny_protocol(tmp_path)
    dataset = tmp_path / "rehearsal"
    responder = "observer" if importlib.util.find_spec("crs_study.session.responders.observer") \
        else "random"
    crs_study("dry-run", str(protocol), "--participants", "3", "--out", str(dataset),
              "--responder", responder, "--jobs", "2")
    script = tmp_path / "answers.txt"
    script.write_text("n/a\n4\t-0.2\n" + "7\n" * 6)
    crs_study("run", str(protocol), "--participant", "p7k2m9q", "--device", "sim://", "--out",
              str(dataset), "--responder", f"scripted:{script}")
    tsv = dataset / "sub-p7k2m9q/ses-1/beh/sub-p7k2m9q_ses-1_task-digitid_beh.tsv"
    assert "n/a" in tsv.read_text()
    source = dataset / "sourcedata/sub-p7k2m9q/ses-1"
    (source / "sub-p7k2m9q_ses-1_task-digitid_beh-torn-20260101T000000000000Z.bin").write_bytes(
        b"3\tte")
    report = valid_report(dataset)
    summary = report["summary"]
    assert sorted(summary["subjects"]) == ["p7k2m9q", "sim01", "sim02", "sim03"]
    assert summary["tasks"] == ["digitid"] and summary["dataTypes"] == ["beh"]


@pytest.mark.slow
@pytest.mark.skipif(validator() is None, reason="bids-validator-deno is not installed "
                    "(pip install -e '.[test]')")
def test_a_letter_dataset_is_valid_bids(tmp_path):
    """The second stimulus set: task-letterid files, the letter in the column `symbol`."""
    dataset = tmp_path / "letters"
    crs_study("dry-run", str(tiny_letter_protocol(tmp_path)), "--participants", "2", "--out",
              str(dataset), "--responder", "observer")
    report = valid_report(dataset)
    assert report["summary"]["tasks"] == ["letterid"]
