"""Adaptive sessions: the procedure chooses each test trial's level, rows record its state,
and an interrupted session resumes exactly (replay checked against the sidecar's
fingerprint)."""

from __future__ import annotations

import csv
import gzip
import hashlib
import json
from pathlib import Path

import pytest
from _session_helpers import PauseAt, adaptive_protocol, assert_same_but_reruns

from crs_study.adaptive import AdaptiveRun
from crs_study.dataset.schema import ADAPTIVE_COLUMNS
from crs_study.errors import SessionError
from crs_study.protocol import load_protocol
from crs_study.protocol.plan import make_plan
from crs_study.session.adaptive import rebuild
from crs_study.session.responders import make_responder
from crs_study.session.runner import run_session
from crs_study.session.spec import SessionSpec

WALL_CLOCK = {"StartTime", "EndTime", "Resumes", "Interruptions"}


def spec(protocol: Path, out: Path, responder: str = "observer") -> SessionSpec:
    return SessionSpec(protocol, "sim01", out, responder=responder, clock="virtual",
                       durable=False)


def files(out: Path) -> tuple[Path, Path, Path]:
    beh = out / "sub-sim01/ses-1/beh/sub-sim01_ses-1_task-digitid_beh"
    return (beh.with_suffix(".tsv"), beh.with_suffix(".json"),
            out / "sourcedata/sub-sim01/ses-1/sub-sim01_ses-1_task-digitid_frames.tsv.gz")


def rows_of(tsv: Path) -> list[dict[str, str]]:
    with open(tsv, newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


@pytest.fixture(scope="module")
def quest(tmp_path_factory):
    folder = tmp_path_factory.mktemp("quest")
    protocol = adaptive_protocol(folder, procedure="quest-plus", trials=8)
    result = run_session(spec(protocol, folder / "whole"))
    assert result.status == "complete"
    return protocol, folder / "whole"


@pytest.fixture(scope="module")
def stair(tmp_path_factory):
    """A staircase stopped by its reversals: some planned trials are skipped."""
    folder = tmp_path_factory.mktemp("stair")
    protocol = adaptive_protocol(folder, procedure="staircase", trials=20, stop_reversals=2)
    result = run_session(spec(protocol, folder / "whole", "random"))
    assert result.status == "complete"
    return protocol, folder / "whole"


def test_rows_record_the_level_and_the_procedure_state(quest):
    protocol, out = quest
    loaded = load_protocol(protocol)
    rows = rows_of(files(out)[0])
    grid = loaded.adaptive.grid()
    test = [r for r in rows if r["trial_type"] == "test"]
    assert len(test) == 2 * 8 and set(ADAPTIVE_COLUMNS) <= set(rows[0])
    assert {float(r["digit_height"]) for r in test} <= set(grid)
    practice = [r for r in rows if r["trial_type"] == "practice"]
    assert {r["digit_height"] for r in practice} == {"1.200000"}  # the easiest level
    assert {r["adaptive_estimate"] for r in practice} == {"n/a"}
    for r in test:
        assert float(r["adaptive_ci_low"]) <= float(r["adaptive_estimate"]) \
            <= float(r["adaptive_ci_high"])
    # the first test trial of each block is QUEST+'s first choice: both blocks start afresh
    firsts = [next(r for r in test if r["block"] == b) for b in ("0", "1")]
    assert firsts[0]["digit_height"] == firsts[1]["digit_height"]


def test_the_sidecar_fingerprint_is_the_replayed_state(quest):
    protocol, out = quest
    tsv, sidecar, _ = files(out)
    meta = json.loads(sidecar.read_text())
    loaded = load_protocol(protocol)
    plan = make_plan(loaded, "sim01", 1, 0)
    run = rebuild(loaded, plan, rows_of(tsv), None, tsv, sidecar, complete=True)
    assert isinstance(run, AdaptiveRun)
    assert meta["AdaptiveStateSha256"] == run.fingerprint()


def test_a_finished_staircase_skips_the_rest_of_its_block(stair):
    protocol, out = stair
    rows = rows_of(files(out)[0])
    meta = json.loads(files(out)[1].read_text())
    test = [r for r in rows if r["trial_type"] == "test"]
    indices = [int(r["trial_index"]) for r in rows]
    assert indices == sorted(indices) and len(rows) < meta["TrialsPlanned"]
    assert meta["TrialsCompleted"] == len(rows) and meta["Status"] == "complete"
    for block in ("0", "1"):
        track = [r for r in test if r["block"] == block]
        assert int(track[-1]["adaptive_reversals"]) == 2 or len(track) == 20


@pytest.mark.parametrize("kind", ["quest", "stair"])
@pytest.mark.parametrize("at", [3, 7, 12])
def test_interrupted_then_resumed_is_identical_to_uninterrupted(kind, at, request, tmp_path):
    protocol, whole = request.getfixturevalue(kind)
    responder = "observer" if kind == "quest" else "random"
    out = tmp_path / "cut"
    seed_spec = spec(protocol, out, responder)
    seed = make_plan(load_protocol(protocol), "sim01", 1, 0).seed
    pausing = PauseAt(seed, at) if responder == "random" else observer_pausing_at(protocol, at)
    first = run_session(seed_spec, responder=pausing)
    assert first.status == "interrupted"
    second = run_session(seed_spec)
    assert second.status == "complete"
    tsv, sidecar, frames = files(out)
    whole_tsv, whole_sidecar, whole_frames = files(whole)
    # the trial the pause cut after its stimulus began is rerun (rerun = 1: partly felt);
    # everything else is what the uninterrupted run wrote
    assert_same_but_reruns(tsv, whole_tsv, {at})
    assert gzip.decompress(frames.read_bytes()) == gzip.decompress(whole_frames.read_bytes())
    a, b = json.loads(sidecar.read_text()), json.loads(whole_sidecar.read_text())
    assert a["TrialsSha256"] == hashlib.sha256(tsv.read_bytes()).hexdigest()
    ignored = WALL_CLOCK | {"TrialsSha256"}  # (the rerun mark)
    assert {k: v for k, v in a.items() if k not in ignored} == \
        {k: v for k, v in b.items() if k not in ignored}


def observer_pausing_at(protocol, at):
    """The perceptual observer, pressing Ctrl-C when trial ``at`` asks for an answer."""
    loaded = load_protocol(protocol)
    plan = make_plan(loaded, "sim01", 1, 0)
    observer = make_responder("observer", seed=int(plan.seed), layout=loaded.layout(),
                              protocol=loaded)
    real = observer.respond

    def respond(trial, stimulus, clock, time_limit_s):
        if trial.index == at:
            raise KeyboardInterrupt
        return real(trial, stimulus, clock, time_limit_s)

    observer.respond = respond
    return observer


def _interrupted(protocol, out, at=6):
    loaded = load_protocol(protocol)
    pause = PauseAt(make_plan(loaded, "sim01", 1, 0).seed, at)
    assert run_session(spec(protocol, out, "random"), responder=pause).status == "interrupted"
    return files(out)


def test_an_altered_level_is_refused_on_resume(tmp_path):
    protocol = adaptive_protocol(tmp_path, procedure="staircase", trials=10)
    tsv, sidecar, _ = _interrupted(protocol, tmp_path / "d")
    lines = tsv.read_text().splitlines(keepends=True)
    header = lines[0].rstrip("\n").split("\t")
    column = header.index("digit_height")
    last = lines[-1].split("\t")
    assert last[1] == "test"
    last[column] = "0.400000" if last[column] != "0.400000" else "1.200000"
    lines[-1] = "\t".join(last)
    tsv.write_text("".join(lines))
    # as other software would have written it (the file's checksum agrees): replay catches it
    meta = json.loads(sidecar.read_text())
    meta["TrialsSha256"] = hashlib.sha256(tsv.read_bytes()).hexdigest()
    sidecar.write_text(json.dumps(meta, indent=2) + "\n")
    with pytest.raises(SessionError, match=r"level .* stored, but replaying the recorded "
                                           r"responses the staircase chooses"):
        run_session(spec(protocol, tmp_path / "d", "random"))


def test_another_state_fingerprint_is_refused_on_resume(tmp_path):
    protocol = adaptive_protocol(tmp_path, procedure="staircase", trials=10)
    _, sidecar, _ = _interrupted(protocol, tmp_path / "d")
    meta = json.loads(sidecar.read_text())
    assert meta["AdaptiveStateSha256"]
    meta["AdaptiveStateSha256"] = "0" * 64
    sidecar.write_text(json.dumps(meta, indent=2) + "\n")
    with pytest.raises(SessionError, match=r"cannot resume: the adaptive procedures' state "
                                           r"after \d+ trials differs"):
        run_session(spec(protocol, tmp_path / "d", "random"))


def test_an_adaptive_stroke_speed_runs_with_the_observer(tmp_path):
    """A staircase on the stroke speed: correct answers make the strokes faster, and the
    observer answers from what the display showed at that speed."""
    protocol = adaptive_protocol(tmp_path, procedure="staircase", trials=8)
    text = protocol.read_text()
    text = text.replace('parameter = "digit_height_pitch"\nwidth_to_height = 0.605\n',
                        'parameter = "stroke_speed_mm_s"\n')
    text = text.replace("min = 0.4\nmax = 1.2", "min = 20.0\nmax = 80.0")
    text = text.replace("start = 1.2", "start = 20.0")
    text = text.replace("stroke_speed_mm_s = 60.0\n", "digit_height_pitch = 0.81\n"
                        "digit_width_pitch = 0.49\n")
    protocol.write_text(text)
    loaded = load_protocol(protocol)
    assert loaded.adaptive.grid()[0] == 80.0  # the hardest level first: the fastest
    result = run_session(spec(protocol, tmp_path / "d"))
    assert result.status == "complete"
    rows = [r for r in rows_of(files(tmp_path / "d")[0]) if r["trial_type"] == "test"]
    speeds = [float(r["stroke_speed"]) for r in rows if r["block"] == "0"]
    first_correct = rows[0]["correct"] == "1"
    assert speeds[0] == 20.0 and (speeds[1] > 20.0) == first_correct
