"""Sessions recorded by the previous code (commit 4c71d44, tests/fixtures/sessions_4c71d44)
are resumed by this code exactly as if this code had recorded them, and completed ones are
left alone. The fixture's make_fixture.py says how each session was recorded."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
from _session_helpers import PauseAt

from crs_study.dataset.session_metadata import SessionMetadata
from crs_study.errors import DeviceError
from crs_study.protocol.plan import plan_seed
from crs_study.session.runner import run_session, seed_check
from crs_study.session.spec import SessionSpec

FIXTURES = Path(__file__).parent / "fixtures" / "sessions_4c71d44"
#: What differs between two runs of one history: wall-clock times and where the protocol was.
WALL_CLOCK_KEYS = ("StartTime", "EndTime", "ProtocolPath")


@pytest.fixture(autouse=True)
def _consented():
    """The previous code ran these people's labels on sim:// without consent; this code gates
    a person's label on every device, so the register records their consent."""
    from crs_study.consent import Register, read_form
    from crs_study.paths import shipped_file

    form = read_form(shipped_file("consent/consent_form.md"))
    for label in ("p01", "p02", "p03", "p04"):
        Register(None).record(form, "AB", label)


@pytest.fixture
def recorded(tmp_path) -> Path:
    """A copy of the dataset the previous code wrote, with its protocol beside it."""
    shutil.copy(FIXTURES / "tiny.toml", tmp_path / "tiny.toml")
    return Path(shutil.copytree(FIXTURES / "dataset", tmp_path / "recorded"))


def spec(dataset: Path, participant: str, url: str = "sim://",
         clock: str = "virtual") -> SessionSpec:
    return SessionSpec(dataset.parent / "tiny.toml", participant, dataset, url, 1, "random",
                       clock)


def _without_column(text: str, column: str) -> str:
    lines = [line.split("\t") for line in text.splitlines()]
    drop = lines[0].index(column)
    return "".join("\t".join(c for i, c in enumerate(cells) if i != drop) + "\n"
                   for cells in lines)


def _comparable(meta: SessionMetadata) -> dict:
    data = meta.to_dict()
    for key in WALL_CLOCK_KEYS:
        data.pop(key)
    # the old code recorded no causes of interruptions and hashed the file it wrote
    data.pop("Interruptions", None)
    data.pop("TrialsSha256")
    data["Resumes"] = [(r["AtTrial"], r["DeviceURL"]) for r in data["Resumes"]]
    data["Faults"] = [(f["trial"], f["message"]) for f in data["Faults"]]
    return data


def test_a_session_begun_by_the_previous_code_finishes_as_if_this_code_began_it(recorded):
    # p01: a device fault in trial 3, resumed, paused at trial 5; 4 of 8 trials stored.
    assert seed_check(spec(recorded, "p01"))["stored"] == "interrupted (4/8 trials), matches"
    finished = run_session(spec(recorded, "p01"))
    assert (finished.status, finished.trials_run, finished.trials_completed) == \
        ("complete", 4, 8)

    # The same history, every step by this code.
    reference = recorded.parent / "reference"
    with pytest.raises(DeviceError, match=r"^device fault at trial 3/8: .*port vanished"):
        run_session(spec(reference, "p01", "sim://?disconnect_at=5"))
    paused = run_session(spec(reference, "p01"),
                         responder=PauseAt(plan_seed("tiny", "1.0.0", "p01", 1), 4))
    assert (paused.status, paused.trials_completed) == ("interrupted", 4)
    whole = run_session(spec(reference, "p01"))

    # The old session keeps the columns it began with (no ``rerun``); this
    # code's file, without that column, is the same byte for byte.
    assert finished.tsv.read_text() == _without_column(whole.tsv.read_text(), "rerun")
    assert "rerun" not in finished.tsv.read_text().splitlines()[0].split("\t")
    frames = "sourcedata/sub-p01/ses-1/sub-p01_ses-1_task-digitid_frames.tsv.gz"
    assert (recorded / frames).read_bytes() == (reference / frames).read_bytes()
    ours, theirs = SessionMetadata.read(whole.sidecar), SessionMetadata.read(finished.sidecar)
    assert _comparable(theirs) == _comparable(ours)
    assert [r.at_trial for r in theirs.resumes] == [2, 4]
    assert [f.trial for f in theirs.faults] == [2]
    assert [(i.at_trial, i.cause, i.trial_cut) for i in ours.interruptions] == \
        [(2, "device-fault", True), (4, "signal", True)]  # PauseAt raises KeyboardInterrupt
    assert theirs.trials_sha256 == hashlib.sha256(finished.tsv.read_bytes()).hexdigest()


@pytest.mark.parametrize("participant, clock", [("p02", "virtual"), ("p03", "virtual"),
                                                ("p04", "real")])
def test_sessions_the_previous_code_completed_are_left_alone(recorded, participant, clock):
    before = {p: p.read_bytes() for p in recorded.rglob("*") if p.is_file()}
    result = run_session(spec(recorded, participant, clock=clock))
    assert result.status == "already-complete" and result.trials_completed == 8
    assert {p: p.read_bytes() for p in recorded.rglob("*") if p.is_file()} == before
