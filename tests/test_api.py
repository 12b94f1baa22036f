"""The Python API: ``crs_study`` re-exports the functions a notebook calls,
each taking objects as well as paths and returning a result object.

Before this, ``dry_run(load_protocol(p), ...)`` raised ``TypeError: expected str, bytes or
os.PathLike object, not Protocol``, and ``import crs_study`` offered nothing but the version.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
from contextlib import redirect_stdout
from dataclasses import replace

import pandas as pd
import pytest
from _session_helpers import record_consent, tiny_protocol

import crs_study
from crs_study.cli import main
from crs_study.dataset import SessionMetadata
from crs_study.errors import SessionError

API = ["load_protocol", "make_plan", "validate", "dry_run", "run_session", "load_dataset",
       "analyze", "power", "Protocol", "TrialPlan", "ProtocolSummary", "DryRunResult",
       "SessionResult", "StudyData", "Analysis", "PowerResult", "run_measurement",
       "analyze_measurement", "MeasurementSpec", "MeasurementRun", "MeasuredQuality"]


def _cli(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    with redirect_stdout(out):
        code = main(list(argv))
    return code, out.getvalue()


def test_the_package_exports_exactly_the_api():
    assert sorted(crs_study.__all__) == sorted(["CrsStudyError", "__version__", *API])
    for name in API:
        assert getattr(crs_study, name).__name__ == name
    assert crs_study.dry_run is crs_study.session.dry_run
    assert crs_study.analyze is crs_study.analysis.analyze
    with pytest.raises(AttributeError, match="has no attribute 'dry_runn'"):
        crs_study.dry_runn  # noqa: B018


def test_import_crs_study_loads_no_numerical_library():
    """The API is loaded on first use: the command line's start and ``import crs_study``
    stay quick (``python -X importtime -c "import crs_study"``: about 30 ms)."""
    code = ("import sys, crs_study; print(sorted(m for m in ('numpy', 'pandas', 'scipy', "
            "'matplotlib') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, check=True)
    assert done.stdout.strip() == "[]"


def test_no_api_name_is_also_a_subpackage():
    """Importing a submodule sets the package's attribute of that name to the module: a
    subpackage ``crs_study.power`` once replaced the ``power`` function after any
    ``import crs_study.power...`` (seen as an order-dependent failure of the test above).
    Each API name is checked after every stage of the package has been imported."""
    code = ("import pkgutil, importlib, crs_study\n"
            "for m in pkgutil.walk_packages(crs_study.__path__, 'crs_study.'):\n"
            "    if m.name != 'crs_study.__main__':  # that one runs the command line\n"
            "        importlib.import_module(m.name)\n"
            "print(sorted(n for n in crs_study.API if not callable(getattr(crs_study, n))))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.strip() == "[]"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return crs_study.load_protocol(tiny_protocol(tmp_path_factory.mktemp("protocol")))


def test_dry_run_of_a_protocol_changed_in_python(tiny, tmp_path):
    twice = replace(tiny, design=replace(tiny.design, repetitions=2))
    result = crs_study.dry_run(twice, participants=2, out=tmp_path / "ds", responder="random")
    assert isinstance(result, crs_study.DryRunResult) and result.finished
    (first, second) = result                               # a sequence of SessionResult
    assert first.trials_completed == len(crs_study.make_plan(twice, "sim01", 1, 0)) == \
        2 * 3 * 2 + 2
    stored = SessionMetadata.read(first.sidecar)
    settled = crs_study.load_protocol(twice)
    assert stored.protocol_text == settled.text and stored.protocol_sha256 == settled.sha256
    assert "repetitions = 2" in stored.protocol_text and stored.protocol_sha256 != tiny.sha256
    again = crs_study.dry_run(twice, participants=2, out=tmp_path / "ds", responder="random")
    assert [r.status for r in again] == ["already-complete"] * 2
    with pytest.raises(SessionError, match="cannot resume: the protocol file differs"):
        crs_study.dry_run(tiny, participants=2, out=tmp_path / "ds", responder="random")


def test_dry_run_result_tables(tiny, tmp_path):
    result = crs_study.dry_run(tiny.path, 2, tmp_path / "ds", responder="random")
    frame = result.to_frame()
    assert list(frame["participant"]) == ["sim01", "sim02"]
    assert list(frame.columns[:5]) == ["status", "participant", "session", "trials_planned",
                                       "trials_completed"]
    assert result.trials == frame["trials_completed"].sum()
    code, out = _cli("dry-run", str(tiny.path), "--participants", "2", "--out",
                     str(tmp_path / "ds"), "--responder", "random", "--json")
    printed = json.loads(out)
    assert code == 0 and printed["trials"] == result.trials
    assert [s["participant"] for s in printed["sessions"]] == ["sim01", "sim02"]
    assert json.loads(result.to_json())["dataset"] == printed["dataset"]


def test_analyze_a_dry_run_from_its_folder(tiny, tmp_path):
    crs_study.dry_run(tiny, 3, tmp_path / "ds", responder="random")
    analysis = crs_study.analyze(tmp_path / "ds", write=False)
    assert isinstance(analysis, crs_study.Analysis) and analysis.files is None
    table = analysis.accuracy.to_frame()
    assert isinstance(table, pd.DataFrame) and set(table["condition"]) == {"pixel-only", "crs"}
    data = crs_study.load_dataset(tmp_path / "ds")
    assert not (data.trials["trial_type"] == "practice").any()
    assert table["n_trials"].sum() == len(data.trials)
    assert not (tmp_path / "ds" / "derivatives").exists()


def test_run_session_from_keyword_arguments(tiny, tmp_path):
    record_consent("p01")  # a person's label is gated on sim:// too
    result = crs_study.run_session(tiny, "p01", tmp_path / "ds", responder="random",
                                   device_url="sim://")
    assert isinstance(result, crs_study.SessionResult) and result.status == "complete"
    assert result.trials_completed == len(crs_study.make_plan(tiny, "p01", 1, 0))
    code, out = _cli("run", str(tiny.path), "--participant", "p01", "--device", "sim://",
                     "--out", str(tmp_path / "ds"), "--responder", "random", "--json")
    assert code == 0 and json.loads(out)["status"] == "already-complete"


def test_make_plan_from_a_name_a_path_or_an_object(tiny):
    plan = crs_study.make_plan("pilot", "p01")
    assert plan == crs_study.make_plan(crs_study.load_protocol("pilot"), "p01", 1, 0)
    assert len(crs_study.make_plan(tiny.path, "p01")) == 2 * 3 + 2
    faster = replace(tiny, design=replace(tiny.design, practice_trials=0))
    assert crs_study.make_plan(faster, "p01").count("practice") == 0


def test_validate_is_what_the_command_prints(tiny):
    summary = crs_study.validate(tiny.path, participant="p7")
    code, out = _cli("validate", str(tiny.path), "--participant", "p7", "--json")
    assert code == 0 and json.loads(out) == summary.to_dict()
    code, listed = _cli("validate", str(tiny.path), "--json", "--list")
    assert len(json.loads(listed)["plan_trials"]) == len(summary.plan)
    frame = summary.to_frame()
    assert list(frame["condition"]) == list(tiny.conditions)
    assert (frame["test_trials"] == 3).all()
    assert frame.loc[0, "frames"] == summary.wire.conditions[0].frames
