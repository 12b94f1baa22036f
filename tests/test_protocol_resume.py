"""Sessions written by older software resume under this one (the protocol package split).

The fixture (tests/fixtures/main_sessions, made by make_fixture.py there with crs-study at
commit 4c71d44, before protocol.py became a package) holds two interrupted sessions: 3 trials
answered of a 3-digit protocol, without and with ``[levels]``. The protocol file's sha256,
the trial plan's and the stimulus fingerprint (``StimulusSha256``, every bump path drawn) must
be what that software stored, and ``crs-study run`` must finish the sessions.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
from _session_helpers import record_consent

from crs_study.cli import main
from crs_study.geometry.layout import load_layout
from crs_study.protocol import load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.session.resume import plan_sha256, stimulus_sha256


@pytest.fixture(autouse=True)
def _consented():
    """p01: people's labels, gated by consent on every device, sim:// too."""
    record_consent("p01")


FIXTURE = Path(__file__).parent / "fixtures" / "main_sessions"
SIDECAR = "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.json"
TSV = "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.tsv"


def stored(name: str) -> dict:
    return json.loads((FIXTURE / "dataset" / name / SIDECAR).read_text(encoding="utf-8"))


@pytest.mark.parametrize("name", ["tiny", "tiny_levels"])
def test_fingerprints_are_those_the_older_software_stored(name):
    meta = stored(name)
    protocol = load_protocol(FIXTURE / f"{name}.toml")
    plan = make_plan(protocol, "p01", 1, meta["Counterbalance"])
    assert protocol.sha256 == meta["ProtocolSha256"]
    assert plan.seed == meta["Seed"]
    assert plan_sha256(plan) == meta["PlanSha256"]
    assert stimulus_sha256(protocol, load_layout(protocol.device)) == meta["StimulusSha256"]


@pytest.mark.parametrize("name", ["tiny", "tiny_levels"])
def test_an_interrupted_session_of_the_older_software_resumes(tmp_path, name, capsys):
    dataset = tmp_path / name
    shutil.copytree(FIXTURE / "dataset" / name, dataset)
    before = (dataset / TSV).read_text(encoding="utf-8").splitlines()
    planned = stored(name)["TrialsPlanned"]
    plan = make_plan(load_protocol(FIXTURE / f"{name}.toml"), "p01", 1, 0)
    script = tmp_path / "answers.txt"
    script.write_text("".join(f"{t.symbol}\n" for t in plan.trials), encoding="utf-8")
    status = main(["run", str(FIXTURE / f"{name}.toml"), "--participant", "p01",
                   "--device", "sim://", "--out", str(dataset),
                   "--responder", f"scripted:{script}", "--clock", "virtual"])
    assert status == 0, capsys.readouterr().err
    meta = json.loads((dataset / SIDECAR).read_text(encoding="utf-8"))
    assert meta["Status"] == "complete" and len(meta["Resumes"]) == 1
    assert meta["StimulusSha256"] == stored(name)["StimulusSha256"]
    after = (dataset / TSV).read_text(encoding="utf-8").splitlines()
    assert after[:len(before)] == before  # the older rows are kept as they were
    with open(dataset / TSV, newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    assert len(rows) == planned
    assert [int(r["digit"]) for r in rows] == [t.symbol for t in plan.trials]
