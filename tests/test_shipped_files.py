"""Shipped defaults (crs_study.paths): the package's copies equal the repository's, names and
paths resolve as documented, and ``crs-study init`` copies them to edit."""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import pytest

from crs_study import paths
from crs_study.cli import main
from crs_study.errors import ConfigError, ConsentError, ProtocolError

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("folder", sorted(paths.SHIPPED_FOLDERS))
def test_the_shipped_copies_equal_the_repository_files(folder):
    """One file, two places: a change to one that is not made to the other fails here."""
    if not (REPO / folder).is_dir():
        pytest.skip("not a checkout of the repository")
    ours, shipped = REPO / folder, paths.data_dir() / folder
    names = sorted(p.name for p in ours.iterdir() if p.is_file())
    assert names == sorted(p.name for p in shipped.iterdir() if p.is_file()), \
        f"{folder}/ and {shipped} hold different files: copy the new one over"
    for name in names:
        assert filecmp.cmp(ours / name, shipped / name, shallow=False), \
            (f"{folder}/{name} differs from the shipped copy: make the same change to both "
             f"(cp {folder}/{name} crs_study/data/{folder}/{name}, or the other way)")


def test_the_wheel_ships_every_file_of_the_data_folders():
    """pyproject's package-data patterns cover every file the folders hold."""
    import tomllib

    patterns = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"]["crs_study"]
    root = paths.data_dir().parent
    for folder in paths.SHIPPED_FOLDERS:
        for path in (paths.data_dir() / folder).iterdir():
            relative = path.relative_to(root)
            assert any(relative.match(p) for p in patterns), f"{relative} would not ship"


def test_names_and_paths():
    assert sorted(paths.shipped_protocols()) == ["digit_identification", "digit_size_adaptive",
                                                 "digit_size_psychometric",
                                                 "letter_identification", "pilot"]
    assert paths.resolve_protocol("pilot") == paths.data_dir() / "protocols" / "pilot.toml"
    assert paths.resolve_protocol(Path("pilot")).name == "pilot.toml"
    assert paths.resolve_protocol("mine/study.toml") == Path("mine/study.toml")  # as given
    assert paths.resolve_consent_form("consent_form").name == "consent_form.md"
    assert paths.DEFAULT_PROTOCOL in paths.shipped_protocols()
    for text in ("pilot", "digit_identification", "a-b_c", "x1"):
        assert paths.is_name(text)
    for text in ("pilot.toml", "./pilot", "protocols/pilot", "-x", "", "/abs"):
        assert not paths.is_name(text)


@pytest.mark.parametrize("resolve, text, error, message", [
    (paths.resolve_protocol, "pilto", ProtocolError,
     r"^'pilto' is not a shipped protocol \(shipped: digit_identification, "
     r"digit_size_adaptive, digit_size_psychometric, letter_identification, pilot\); give "
     r"the path of your own file$"),
    (paths.resolve_protocol, "protocols/pilot.toml", ProtocolError,
     r"^protocols/pilot.toml: no such protocol file; crs-study ships one named 'pilot': give "
     r"that name, or copy the shipped files to edit them with crs-study init DIR$"),
    (paths.resolve_consent_form, "form", ConsentError,
     r"^'form' is not a shipped consent form \(shipped: consent_form, information_sheet\)"),
])
def test_unknown_names_are_one_line(tmp_path, monkeypatch, resolve, text, error, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(error, match=message):
        resolve(text)


def test_a_session_records_a_shipped_protocol_without_the_install_location(tmp_path,
                                                                            monkeypatch):
    from crs_study.dataset.session_metadata import SessionMetadata
    from crs_study.session.dry_runs import dry_run

    assert paths.recorded_path("mine/study.toml") == "mine/study.toml"
    monkeypatch.chdir(tmp_path)
    (result,) = dry_run("pilot", 1, "ds", responder="random")
    meta = SessionMetadata.read(result.sidecar)
    assert meta.protocol_path == "crs_study/data/protocols/pilot.toml"
    assert str(paths.data_dir()) not in result.sidecar.read_text()


def test_shipped_file_prefers_the_current_folder_then_the_package(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = paths.data_dir() / "analysis" / "digit_identification.toml"
    assert paths.shipped_file("analysis/digit_identification.toml") == shipped
    (tmp_path / "analysis").mkdir()
    (tmp_path / "analysis" / "digit_identification.toml").write_text("# mine\n")
    assert paths.shipped_file("analysis/digit_identification.toml") == \
        Path("analysis/digit_identification.toml")
    assert paths.shipped_file("pilot") == paths.resolve_protocol("pilot")
    with pytest.raises(ConfigError, match=r"^analysis/nope.toml: no such file \(looked in "):
        paths.shipped_file("analysis/nope.toml")


def test_a_referenced_file_is_found_beside_the_protocol_then_above_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    project = tmp_path / "study"
    protocol = project / "protocols" / "mine.toml"
    shipped = paths.data_dir() / "consent" / "consent_form.md"
    assert paths.find_referenced(protocol, "consent/consent_form.md") == shipped
    above = project / "consent" / "consent_form.md"
    above.parent.mkdir(parents=True)
    above.write_text("# edited\n")
    assert paths.find_referenced(protocol, "consent/consent_form.md") == above
    beside = project / "protocols" / "consent" / "consent_form.md"
    beside.parent.mkdir(parents=True)
    beside.write_text("# beside\n")
    assert paths.find_referenced(protocol, "consent/consent_form.md") == beside


def test_copy_defaults_copies_once_and_never_overwrites(tmp_path):
    target = tmp_path / "study"
    copied = paths.copy_defaults(target)
    assert all(item.written for item in copied) and len(copied) == 15
    for folder in paths.SHIPPED_FOLDERS:
        for source in (paths.data_dir() / folder).iterdir():
            assert (target / folder / source.name).read_bytes() == source.read_bytes()
    assert not any(item.written for item in paths.copy_defaults(target))  # identical: left
    edited = target / "protocols" / "pilot.toml"
    edited.write_text(edited.read_text() + "# my change\n")
    (target / "consent" / "consent_form.md").unlink()
    with pytest.raises(ConfigError, match=r"protocols/pilot.toml: exists and differs from the "
                                          r"shipped copy; nothing was copied"):
        paths.copy_defaults(target)
    assert edited.read_text().endswith("# my change\n")
    assert not (target / "consent" / "consent_form.md").exists()  # nothing written at all
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="exists and is not a directory"):
        paths.copy_defaults(tmp_path / "file")


def test_init_then_use_the_copies_from_another_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["init", "study"]) == 0
    out = capsys.readouterr().out
    assert "copied  study/protocols/pilot.toml" in out
    assert out.splitlines()[-1] == ("init: 15 of 15 files copied into study; edit them, then "
                                    "check one with: crs-study validate "
                                    "study/protocols/pilot.toml")
    assert main(["validate", "study/protocols/pilot.toml", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["protocol"] == "study/protocols/pilot.toml"
    # the copy still has the shipped study id, which seeds every session's trial order
    assert captured.err == ("crs-study validate: warning: study id 'digitid-pilot' is the "
                            "shipped pilot protocol's: give the copy an id of its own ([study] "
                            "id), since the id seeds every session's trial order\n")
    assert main(["init", "study"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("init: 0 of 15 files copied")
    copy = tmp_path / "study" / "protocols" / "pilot.toml"
    copy.write_text(copy.read_text().replace('id = "digitid-pilot"', 'id = "ourlab-pilot"'))
    assert main(["validate", str(copy), "--json"]) == 0
    assert capsys.readouterr().err == ""


def test_commands_take_a_shipped_protocol_by_name_from_any_folder(tmp_path, monkeypatch,
                                                                   capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["validate", "pilot", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["protocol"] == \
        str(paths.data_dir() / "protocols" / "pilot.toml")
    assert main(["dry-run", "pilot", "--participants", "1", "--out", "ds", "--json",
                 "--responder", "random"]) == 0
    assert json.loads(capsys.readouterr().out)["trials"] == 26
    assert main(["run", "pilot", "--participant", "p1", "--device", "sim://", "--out", "ds",
                 "--responder", "random", "--seed-check", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["trials"] == 26
    assert main(["dry-run", "protocols/pilot.toml", "--participants", "1", "--out", "ds"]) == 2
    assert "crs-study ships one named 'pilot'" in capsys.readouterr().err
    register = tmp_path / "register"
    assert main(["consent", "record", "--form", "consent_form", "--experimenter", "AB",
                 "--participant", "p1", "--register", str(register)]) == 0
    assert "participant p1, form version 1.0" in capsys.readouterr().out


@pytest.mark.parametrize("link", ["protocols", "consent/consent_form.md"])
def test_init_refuses_to_write_through_a_symbolic_link(tmp_path, link):
    """A ``protocols`` folder (or a file) that is a link elsewhere: the copy would land there."""
    import subprocess
    import sys

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    target = tmp_path / "study" / link
    target.parent.mkdir(parents=True)
    target.symlink_to(elsewhere if link == "protocols" else elsewhere / "form.md")
    done = subprocess.run([sys.executable, "-m", "crs_study", "init", str(tmp_path / "study")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert f"{target}: is a symbolic link" in done.stderr
    assert list(elsewhere.iterdir()) == []
    assert sorted(p.name for p in (tmp_path / "study").iterdir()) == [link.split("/")[0]]
