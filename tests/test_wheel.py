"""The package as a user installs it: a wheel in a fresh venv runs the main job from any folder.

The wheel is built offline from a copy of the source (pip wheel without build isolation: the
test venv's setuptools, no index), installed without dependencies into a fresh venv that
reaches the test venv's site-packages for numpy, pandas and the rest (a .pth file; the
editable install's finder there is not activated, so the source tree is out of sight), then
run from an empty folder. Before the defaults shipped as package data this failed with
``protocols/digit_identification.toml: no such file``.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # about 20 s, most of it the demo itself; kept in the default run


def _run(command: list[str], cwd: Path, timeout: float = 240,
         home: Path | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "MPLBACKEND", "PYTHONSTARTUP")}
    if home is not None:
        env["HOME"] = str(home)
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, check=False)
    assert done.returncode == 0, f"{command} exited {done.returncode}:\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with the wheel of this source tree installed; its ``bin`` folder.

    Built once per run: the suite's worker processes share the base of their temporary
    folders, and the first to take the lock there builds while the others wait, then use
    its venv (read-only: each test runs in a folder of its own)."""
    run = tmp_path_factory.getbasetemp()      # a worker's: popen-gwN in the run's folder
    run = run.parent if "PYTEST_XDIST_WORKER" in os.environ else run
    shared = run / "wheel-venv"
    with open(run / "wheel-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)          # released when the file is closed
        if not (shared / "built").exists():
            shutil.rmtree(shared, ignore_errors=True)    # a build that failed part-way
            shared.mkdir()
            _build(shared)
            (shared / "built").touch()
    return shared / "venv" / "bin"


def _build(base: Path) -> None:
    """The wheel of a copy of this source tree, installed in a fresh venv in ``base``."""
    source = base / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    shutil.copytree(REPO / "crs_study", source / "crs_study",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
          "--no-index", "-q", "-w", str(base / "dist"), str(source)], base)
    (wheel,) = (base / "dist").glob("crs_study-*.whl")
    venv = base / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], base)
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
          "--no-index", "-q", str(wheel)], base)
    site = _run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                base).stdout.strip()
    dependencies = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    Path(site, "test-venv-dependencies.pth").write_text("\n".join(sorted(dependencies)) + "\n")
    with zipfile.ZipFile(wheel) as archive:
        shipped = {n for n in archive.namelist() if n.startswith("crs_study/data/")}
    for folder in ("protocols", "analysis", "consent"):
        for path in (REPO / "crs_study" / "data" / folder).iterdir():
            assert f"crs_study/data/{folder}/{path.name}" in shipped


def test_crs_study_demo_from_an_empty_folder(installed, tmp_path):
    """The README's first command as a user meets it, in a fresh folder."""
    home = tmp_path / "home"
    home.mkdir()
    (tmp_path / "here").mkdir()
    done = _run([str(installed / "crs-study"), "demo"], tmp_path / "here", home=home)
    lines = done.stdout.splitlines()
    assert lines[0].startswith("demo: 20 simulated participants, 2400 trials, dataset in "
                               f"{home / 'crs-study-demo'}/demo-")
    assert not any((tmp_path / "here").iterdir())   # nothing in the current folder
    report = next(line for line in lines if line.startswith("report: "))
    assert Path(report.removeprefix("report: ")).is_file()
    assert any(line.startswith("chart (accuracy): ") for line in lines)


def test_the_library_from_an_empty_folder(installed, tmp_path):
    code = (
        "import crs_study, crs_study.paths as paths\n"
        "from crs_study.protocol import load_protocol\n"
        "from crs_study.session import dry_run\n"
        "from crs_study.dataset.session_metadata import SessionMetadata\n"
        "print(crs_study.__file__)\n"
        "print(crs_study.__version__)\n"
        "print(load_protocol(paths.resolve_protocol('pilot')).study_id)\n"
        "(result,) = dry_run('pilot', 1, 'ds', responder='random')\n"
        "meta = SessionMetadata.read(result.sidecar)\n"
        "print(meta.status, meta.trials_completed)\n"
    )
    lines = _run([str(installed / "python"), "-c", code], tmp_path).stdout.splitlines()
    assert Path(lines[0]).is_relative_to(installed.parent)  # the wheel, not the source tree
    assert lines[1] == tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert lines[2:] == ["digitid-pilot", "complete 26"]


def test_the_python_api_from_an_empty_folder(installed, tmp_path):
    """A notebook's session with the wheel alone (a shipped protocol by
    name, changed in Python, rehearsed and analysed without writing)."""
    code = (
        "import dataclasses, crs_study\n"
        "protocol = crs_study.load_protocol('pilot')\n"
        "shorter = dataclasses.replace(protocol, design=dataclasses.replace(\n"
        "    protocol.design, practice_trials=1))\n"
        "result = crs_study.dry_run(shorter, participants=2, out='ds')\n"
        "print(len(result), result.trials, result.finished)\n"
        "table = crs_study.analyze('ds', write=False).accuracy.to_frame()\n"
        "print(list(table['condition']), int(table['n_trials'].sum()))\n"
        "print(crs_study.dry_run('pilot', participants=2, out='ds2').trials)\n"
    )
    lines = _run([str(installed / "python"), "-c", code], tmp_path).stdout.splitlines()
    assert lines == ["2 44 True", "['pixel-only', 'crs'] 40", "52"]
    assert not (tmp_path / "ds" / "derivatives").exists()


def test_init_copies_the_shipped_files_to_edit(installed, tmp_path):
    _run([str(installed / "crs-study"), "init", "study"], tmp_path)
    assert (tmp_path / "study" / "consent" / "consent_form.md").read_bytes() == \
        (REPO / "consent" / "consent_form.md").read_bytes()
    done = _run([str(installed / "crs-study"), "validate", "study/protocols/pilot.toml"],
                tmp_path)
    # the copy finds the plan its protocol names, itself copied (the pilot's own, descriptive)
    copied = tomllib.loads((tmp_path / "study" / "protocols" / "pilot.toml").read_text())
    plan = copied["study"]["analysis_plan"]
    assert plan == "analysis/pilot.toml"
    assert f"analysis plan {plan}: found" in done.stdout
    assert (tmp_path / "study" / plan).read_bytes() == \
        (REPO / "crs_study" / "data" / plan).read_bytes()
