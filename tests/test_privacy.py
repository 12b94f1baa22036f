"""Nothing identifying enters the dataset, and the gate guards real sessions."""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from crs_study import consent
from crs_study.cli import main
from crs_study.paths import shipped_file

PILOT = str(shipped_file("protocols/pilot.toml"))
NAMES = {"p1": "Ada Lovelace", "p2": "Grace Hopper"}


def dataset_text(root: Path):
    for path in root.rglob("*"):
        if path.is_file():
            data = path.read_bytes()
            if path.suffix == ".gz":
                data = gzip.decompress(data)
            yield path, data


@pytest.mark.slow
def test_names_in_the_register_never_reach_the_dataset(tmp_path, capsys):
    """Real sessions (the serial code path against virtual boards, so the gate reads the
    register; on a virtual clock, as names not timing are checked here), then an analysis:
    no part of a name in any file, frame logs decompressed."""
    from tests._session_helpers import tiny_protocol

    register = consent.Register(tmp_path / "register")
    form = consent.read_form(shipped_file("consent/consent_form.md"))
    for label, name in NAMES.items():
        register.record(form, "AB", label, name=name)
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.1)
    script = tmp_path / "answers.txt"
    script.write_text("7\t0.05\n" * 4)
    out = tmp_path / "dataset"
    for label in NAMES:
        code = main(["run", str(protocol), "--participant", label,
                     "--device", "serial://lscsim://A,lscsim://B", "--clock", "virtual",
                     "--responder", f"scripted:{script}", "--out", str(out), "--json",
                     "--consent-register", str(register.directory)])
        assert code == 0, capsys.readouterr().err
    assert main(["analyze", str(out), "--json"]) == 0
    files = list(dataset_text(out))
    assert any(path.name.endswith("_beh.tsv") for path, _ in files)
    assert any(path.name == "results.json" for path, _ in files)
    for path, data in files:
        for name in NAMES.values():
            for part in (name, *name.split()):
                assert part.encode() not in data, f"{part!r} found in {path}"


def test_gate_refuses_a_real_device_without_consent(tmp_path, capsys):
    code = main(["run", PILOT, "--participant", "p9", "--device",
                 "serial:///dev/crs-study-no-such-port", "--out", str(tmp_path / "ds"),
                 "--responder", "random", "--consent-register", str(tmp_path / "reg")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "no consent record for participant 'p9'" in err[0]
    assert not (tmp_path / "ds" / "sub-p9").exists()


def test_gate_admits_a_recorded_participant_then_meets_the_device(tmp_path, capsys):
    register = consent.Register(tmp_path / "reg")
    register.record(consent.read_form(shipped_file("consent/consent_form.md")), "AB", "p9")
    code = main(["run", PILOT, "--participant", "p9", "--device",
                 "serial:///dev/crs-study-no-such-port", "--out", str(tmp_path / "ds"),
                 "--responder", "random", "--consent-register", str(register.directory)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "consent" not in err[0] and "crs-study-no-such-port" in err[0]
