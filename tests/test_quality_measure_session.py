"""The measurement session (crs_study.session.measurement): what was shown when, durable and
resumable on the session store, on the simulated device with the DIC stand-in too."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from crs_study.dataset.session_store import SessionStore, read_frame_log
from crs_study.errors import DeviceError, MeasurementError, SessionError
from crs_study.quality.manifest import MANIFEST_COLUMNS, MeasurementRecord, read_manifest
from crs_study.quality.measurement_protocol import resolve_measurement_protocol
from crs_study.session.measurement import MeasurementPaths, MeasurementSpec, run_measurement


def small_protocol(directory: Path, shapes: int = 3, settle: float = 0.5, hold: float = 1.0,
                   seed: int = 29, device: str = "crs1d") -> Path:
    """The shipped protocol of ``device`` made small: one diameter, a few shapes."""
    text = resolve_measurement_protocol(device).read_text()
    text = (text.replace("shapes = 15", f"shapes = {shapes}")
                .replace("seed = 29", f"seed = {seed}")
                .replace("settle_s = 1.0", f"settle_s = {settle}")
                .replace("hold_s = 2.0", f"hold_s = {hold}"))
    text = text.replace("[90.0, 150.0]", "[90.0]").replace("[90.0, 120.0]", "[90.0]")
    path = directory / f"small-{device}.toml"
    path.write_text(text)
    return path


def test_a_timed_measurement_on_the_simulated_device(tmp_path):
    protocol = small_protocol(tmp_path)
    out = tmp_path / "meas"
    run = run_measurement(MeasurementSpec(protocol, out, "sim://", "timed"), prompt=print)
    assert (run.status, run.captures_planned, run.captures_completed) == ("complete", 8, 8)
    assert run.missing == tuple(f"shape-{k:04d}" for k in range(1, 7))  # the lab's exports
    record = MeasurementRecord.read(out / "measurement.json")
    assert record.status == "complete" and record.clock == "virtual"
    lines = (out / "manifest.tsv").read_text().splitlines()
    assert tuple(lines[0].split("\t")) == MANIFEST_COLUMNS
    entries = read_manifest(out / "manifest.tsv", 7)
    assert [e.capture for e in entries][:2] == ["ref-pixel-only", "shape-0001"]
    for entry in entries:  # sent, settled 0.5 s, held 1 s (and the heartbeat's answer)
        assert entry.capture_start == pytest.approx(entry.sent_at + 0.5)
        assert 1.0 <= entry.capture_end - entry.capture_start < 1.05
        assert entry.capture_utc == "n/a"  # a virtual clock has no wall time
    assert [e.sent_at for e in entries[1:]] == pytest.approx([e.capture_end
                                                              for e in entries[:-1]])
    reference = entries[0]
    assert reference.kind == "reference" and not reference.setpoints_mm.any()
    crs = [e for e in entries if e.condition == "crs" and e.kind == "shape"]
    assert all(e.setpoints_mm[5:].sum() > 0 for e in crs)  # the beam is fed
    frames = read_frame_log(out / "sourcedata" / "frames.tsv.gz")
    assert [int(f["trial"]) for f in frames] == list(range(8))
    assert record.manifest_sha256 == hashlib.sha256((out / "manifest.tsv").read_bytes()
                                                    ).hexdigest()
    again = run_measurement(MeasurementSpec(protocol, out, "sim://", "timed"), prompt=print)
    assert again.status == "already-complete" and again.captures_run == 0


def test_a_resumed_measurement_writes_what_an_uninterrupted_one_writes(tmp_path):
    """A device fault at the 4th capture; the same command again resumes and the manifest
    and the stand-in's captures are byte for byte those of a run never interrupted."""
    protocol = small_protocol(tmp_path)
    faulty, clean = tmp_path / "faulty", tmp_path / "clean"
    url = "sim://?disconnect_at=6"
    with pytest.raises(DeviceError, match=r"device fault at capture 4/8: .* run the same "
                                          r"command to resume"):
        run_measurement(MeasurementSpec(protocol, faulty, url, "synthetic"))
    record = MeasurementRecord.read(faulty / "measurement.json")
    assert (record.status, record.captures_completed) == ("interrupted", 3)
    assert record.interruptions[-1]["Cause"] == "device-fault" and len(record.faults) == 1
    resumed = run_measurement(MeasurementSpec(protocol, faulty, url, "synthetic"))
    assert (resumed.status, resumed.captures_run) == ("complete", 5)
    assert run_measurement(MeasurementSpec(protocol, clean, "sim://", "synthetic")).missing == ()
    assert (faulty / "manifest.tsv").read_bytes() == (clean / "manifest.tsv").read_bytes()
    for path in sorted((clean / "captures").iterdir()):
        assert (faulty / "captures" / path.name).read_bytes() == path.read_bytes(), path.name
    assert MeasurementRecord.read(faulty / "measurement.json").resumes[0]["AtCapture"] == 3


def test_ctrl_c_pauses_safely_and_a_torn_tail_is_cut(tmp_path):
    protocol = small_protocol(tmp_path, settle=0.0, hold=0.01)
    out = tmp_path / "meas"
    asked = []

    def prompt(message: str) -> None:
        asked.append(message)
        if len(asked) == 4:  # the experimenter presses Ctrl-C at the 4th prompt
            raise KeyboardInterrupt

    run = run_measurement(MeasurementSpec(protocol, out, "sim://", "prompt"), prompt=prompt)
    assert run.status == "interrupted" and run.captures_completed == 2  # block, 2 captures
    assert asked[0].startswith("block pixel-only: remove the skeleton")
    assert "shape-0001 on the display" in asked[2]
    record = MeasurementRecord.read(out / "measurement.json")
    assert record.interruptions[-1]["Cause"] == "signal" and record.clock == "real"
    with open(out / "manifest.tsv", "ab") as handle:  # a kill in the middle of an append
        handle.write(b"2\tshape-0002\tsha")
    resumed = []
    run = run_measurement(MeasurementSpec(protocol, out, "sim://", "prompt"),
                          prompt=resumed.append)
    assert run.status == "complete" and run.captures_completed == 8
    assert resumed[0].startswith("resuming at shape-0002 in block pixel-only: remove the")
    assert len(read_manifest(out / "manifest.tsv", 7)) == 8
    assert list((out / "sourcedata").glob("beh-torn-*.bin"))  # the cut bytes kept


def test_a_resume_must_match_what_began_it(tmp_path):
    protocol = small_protocol(tmp_path)
    out = tmp_path / "meas"
    with pytest.raises(DeviceError):
        run_measurement(MeasurementSpec(protocol, out, "sim://?disconnect_at=6", "timed"),
                        prompt=print)
    other = small_protocol(tmp_path, seed=30)
    other.rename(protocol)
    with pytest.raises(SessionError, match=r"cannot resume: the protocol differs"):
        run_measurement(MeasurementSpec(protocol, out, "sim://", "timed"), prompt=print)
    small_protocol(tmp_path)  # the original back
    with pytest.raises(SessionError, match=r"began with --capture timed"):
        run_measurement(MeasurementSpec(protocol, out, "sim://", "synthetic"))
    store = SessionStore(MeasurementPaths(out))
    store.acquire()
    try:
        with pytest.raises(SessionError, match="in use by another crs-study quality measure"):
            run_measurement(MeasurementSpec(protocol, out, "sim://", "timed"), prompt=print)
    finally:
        store.release()
    record = json.loads((out / "measurement.json").read_text())
    record["status"] = "paused"
    (out / "measurement.json").write_text(json.dumps(record))
    with pytest.raises(MeasurementError, match=r"status: expected one of"):
        run_measurement(MeasurementSpec(protocol, out, "sim://", "timed"), prompt=print)


@pytest.mark.parametrize(("url", "capture", "clock", "message"), [
    ("serial:///dev/null", "synthetic", "auto", "the stand-in reads the simulated device"),
    ("sim://", "photo", "auto", "expected prompt, timed or synthetic"),
    ("sim://", "timed?x=1", "auto", "only synthetic takes options"),
    ("sim://", "prompt", "virtual", "--clock virtual needs the simulated device"),
    ("sim://", "synthetic?noise=1", "auto", "unknown option 'noise'"),
    ("sim://", "synthetic?servo=Z:9:0.5", "auto", "'Z:9' is no pixel channel"),
    ("sim://?bogus=1", "synthetic", "auto", "unknown option 'bogus'"),
])
def test_bad_requests_are_refused_in_one_line(tmp_path, url, capture, clock, message):
    protocol = small_protocol(tmp_path)
    with pytest.raises((MeasurementError, SessionError, DeviceError), match=message):
        run_measurement(MeasurementSpec(protocol, tmp_path / "m", url, capture, clock),
                        prompt=print)
