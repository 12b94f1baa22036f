"""The analysis as a Python API: ``analyze`` returns an ``Analysis`` of
result objects (``to_frame()``, ``to_json()``), writing the report is a flag or a method, and
``results.json`` says what the code named in tests/fixtures/analysis_results/COMMIT wrote for
the same datasets (made by its make_fixture.py): a refactoring must not change it, and a
deliberate change of the analysis regenerates it, its diff reviewed in the commit.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest
from analysis_fixtures import CHI2_PLAN, dataset, explicit_dataset, write_plan
from matplotlib.axes import Axes

from crs_study.analysis import Analysis, StudyData, analyze, load_dataset, load_plan
from crs_study.analysis.charts import save
from crs_study.errors import AnalysisError
from crs_study.paths import shipped_file

FIXTURE = Path(__file__).parent / "fixtures" / "analysis_results"
CASES = {"pilot": shipped_file("analysis/pilot.toml"), "levels": FIXTURE / "levels_plan.toml"}


def _comparable(results: dict) -> dict:
    """results.json without what differs between runs and machines (the time, the absolute
    paths, the version that wrote it), as the fixture stores it."""
    results = json.loads(json.dumps(results))
    results["generated_at"] = None
    results["software"] = None
    for entry in results["datasets"]:
        entry["path"] = None
    results["plan"]["path"] = None
    return results


def _same(got, expected, where="results"):
    """Equal, key for key and in order; floats to 1e-9 relative (a BLAS may sum in another
    order), everything else exactly."""
    if isinstance(expected, dict):
        assert isinstance(got, dict) and list(got) == list(expected), where
        for key in expected:
            _same(got[key], expected[key], f"{where}.{key}")
    elif isinstance(expected, list):
        assert isinstance(got, list) and len(got) == len(expected), where
        for i, (a, b) in enumerate(zip(got, expected, strict=True)):
            _same(a, b, f"{where}[{i}]")
    elif isinstance(expected, float) and isinstance(got, float):
        assert math.isclose(got, expected, rel_tol=1e-9, abs_tol=1e-12), \
            f"{where}: {got!r} != {expected!r}"
    else:
        assert got == expected and type(got) is type(expected), \
            f"{where}: {got!r} != {expected!r}"


@pytest.fixture(scope="module", params=sorted(CASES))
def written(request, tmp_path_factory):
    name = request.param
    out = tmp_path_factory.mktemp(name) / "out"
    # a copy: the analysis records its outputs in the dataset it reads (its outputs registry)
    copy = shutil.copytree(FIXTURE / name, tmp_path_factory.mktemp(name) / name)
    return name, analyze(copy, CASES[name], out)


def test_results_json_is_what_main_wrote(written):
    name, analysis = written
    expected = json.loads((FIXTURE / f"{name}.results.json").read_text())
    saved = json.loads(analysis.results_path.read_text())
    _same(_comparable(saved), _comparable(expected))


def test_to_json_is_the_file_byte_for_byte(written):
    _, analysis = written
    assert analysis.to_json() == analysis.results_path.read_text()
    assert analysis.to_dict() == json.loads(analysis.results_path.read_text())
    assert analysis.files.folder == analysis.results_path.parent
    assert analysis.report_path.exists() and analysis.chart("accuracy").exists()


def test_each_result_object_holds_its_section_of_results_json(written):
    _, analysis = written
    results = analysis.to_dict()
    accuracy = json.loads(analysis.accuracy.to_json())
    assert accuracy["conditions"] == results["conditions"]
    assert accuracy["accuracy_by_participant"] == results["accuracy_by_participant"]
    primary = json.loads(analysis.primary.to_json())
    secondary = json.loads(analysis.secondary.to_json())
    assert primary["comparisons"] + secondary["comparisons"] == results["comparisons"]
    assert {k: primary[k] for k in ("omnibus", "model")} == results["primary"]
    assert secondary["per_digit"] == results["per_digit"]
    assert json.loads(analysis.confusions.to_json()) == results["information_transfer"]
    assert json.loads(analysis.speed_accuracy.to_json()) == results["speed_accuracy"]
    assert json.loads(analysis.psychometric.to_json()) == results["psychometric"]
    assert analysis.headline == results["headline"]
    assert list(analysis.warnings) == results["warnings"]


def test_accuracy_to_frame_is_the_accuracy_table(written):
    _, analysis = written
    table = analysis.accuracy.to_frame()
    assert list(table.columns[:6]) == ["condition", "n_trials", "n_correct", "accuracy",
                                       "ci_low", "ci_high"]
    for _, row in table.iterrows():
        saved = analysis.results["conditions"][row["condition"]]
        assert (row["n_trials"], row["n_correct"]) == (saved["n_trials"], saved["n_correct"])
        assert [row["ci_low"], row["ci_high"]] == pytest.approx(saved["ci95"])
    trials = analysis.data.trials
    assert table["n_trials"].sum() == trials["correct"].notna().sum()


def test_the_tables_of_the_other_results(written):
    _, analysis = written
    comparisons = analysis.to_frame()
    assert list(comparisons["primary"]) == [c["primary"] for c in
                                            analysis.results["comparisons"]]
    assert comparisons.loc[0, "method"].startswith("GLMM")
    transfer = analysis.confusions.to_frame()
    assert list(transfer["condition"]) == list(analysis.results["information_transfer"])
    (condition, result), *_ = analysis.confusions.items()
    assert result.to_frame().to_numpy().sum() == \
        analysis.results["information_transfer"][condition]["n_trials"]
    assert not analysis.speed_accuracy.to_frame().empty
    assert not analysis.primary.to_frame().empty and not analysis.secondary.to_frame().empty


def test_analyse_without_writing_then_write(tmp_path):
    # the chi2 p: a reanalysis with the bootstrap's p is test_analysis_report's and the next
    # test's, so this one checks what writing later adds
    root = dataset(tmp_path / "ds", n_participants=4, repetitions=2)
    plan = write_plan(tmp_path / "plan.toml", CHI2_PLAN)
    quiet = analyze(root, plan, write=False)
    assert isinstance(quiet, Analysis) and quiet.files is None and quiet.report_path is None
    assert not (root / "derivatives").exists() and "charts" not in quiet.to_dict()
    files = quiet.write()                       # the dataset's derivatives/crs-study
    assert files.folder == root / "derivatives" / "crs-study"
    written = json.loads(files.results.read_text())
    assert written.pop("charts") == [p.relative_to(files.folder).as_posix()
                                     for p in files.charts]
    assert written == quiet.to_dict()
    assert files.report.read_text().startswith("# Analysis: test plan")
    loud = analyze(root, plan, tmp_path / "out")
    a, b = loud.to_dict(), json.loads(files.results.read_text())
    a.pop("generated_at"), b.pop("generated_at")
    assert a == b


def test_a_chart_from_the_analysis(tmp_path, written):
    _, analysis = written
    ax = analysis.plot("accuracy")
    assert isinstance(ax, Axes)
    png = save(ax, tmp_path / "accuracy.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(AnalysisError, match="no chart 'pie'; this analysis has accuracy, "):
        analysis.plot("pie")
    with pytest.raises(AnalysisError, match=r"no chart 'tracks' \(not in this analysis: no "
                                            r"session is adaptive\); this analysis has"):
        analysis.plot("tracks")                  # a raw KeyError before


def test_every_result_object_shows_itself_in_a_line_and_a_table(written):
    """A concise repr (the dataclass's was 29,000 characters for an Analysis) and a small
    HTML table for notebooks (IPython's _repr_html_ hook)."""
    _, analysis = written
    objects = [analysis, analysis.data, analysis.accuracy, analysis.primary,
               analysis.secondary, analysis.confusions, *analysis.confusions.values(),
               analysis.speed_accuracy, analysis.psychometric, analysis.thresholds,
               analysis.compare(analysis.to_dict())]
    for result in objects:
        text = repr(result)
        assert text.startswith("<") and "\n" not in text and len(text) < 1200, text
        html = result._repr_html_()
        assert html.startswith("<table>") and html.endswith("</table>")
    assert analysis.headline[:40] in repr(analysis)
    assert f"warnings ({len(analysis.warnings)})" in analysis._repr_html_()


def test_charts_show_in_a_notebook_and_leave_no_figure_behind(written):
    """Drawn without pyplot: a script that draws every chart holds no figure afterwards;
    the Axes and its figure give IPython a PNG (_repr_png_), so no %matplotlib is needed."""
    import matplotlib.pyplot as plt

    _, analysis = written
    before = plt.get_fignums()
    for name in analysis.plots():
        ax = analysis.plot(name)
        assert ax._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
        assert ax.figure._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plt.get_fignums() == before == []


# --- load_dataset: the trials an analysis sees -------------------------------------------------

def _cells():
    """Two participants; per condition digit 0 timed out (None), the rest right or wrong."""
    return {p: [(c, d, 0, None if d == 0 else int(d % 2 == 0)) for c in ("pixel-only", "crs")
                for d in range(10)] for p in ("01", "02")}


def _with_practice(root: Path) -> Path:
    """Mark the second trial of every session (pixel-only, digit 1, answered) a practice
    trial, in the TSV and in the hash its sidecar records."""
    for tsv in root.glob("sub-*/ses-*/beh/*_beh.tsv"):
        table = pd.read_csv(tsv, sep="\t", dtype=str, keep_default_na=False)
        table.loc[1, "trial_type"] = "practice"
        table.to_csv(tsv, sep="\t", index=False)
        sidecar = tsv.with_suffix(".json")
        meta = json.loads(sidecar.read_text())
        meta["TrialsSha256"] = hashlib.sha256(tsv.read_bytes()).hexdigest()
        sidecar.write_text(json.dumps(meta))
    return root


def test_load_dataset_applies_the_plans_exclusions_and_leaves_practice_out(tmp_path):
    root = _with_practice(explicit_dataset(tmp_path / "ds", _cells()))
    data = load_dataset(root, write_plan(tmp_path / "plan.toml"))
    assert isinstance(data, StudyData)
    trials = data.to_frame()
    assert len(data.all_trials) == 40 and len(trials) == 40 - 2 - 4
    assert not (trials["trial_type"] == "practice").any()     # practice out by default
    assert trials["correct"].notna().all()                    # time-outs excluded
    assert data.exclusion_counts["practice"] == {"crs": 0, "pixel-only": 2}
    assert set(data.excluded["exclusion"]) == {"practice", "timeout"}
    assert data.plan.name == "test plan" and data.plan_path == tmp_path / "plan.toml"


def test_load_dataset_keeps_practice_or_everything_when_asked(tmp_path):
    root = _with_practice(explicit_dataset(tmp_path / "ds", _cells()))
    plan = write_plan(tmp_path / "plan.toml")
    with_practice = load_dataset(root, plan, practice=True)
    assert (with_practice.trials["trial_type"] == "practice").sum() == 2
    assert any("practice trials kept, unlike the analysis plan" in w
               for w in with_practice.warnings)
    everything = load_dataset(root, plan, exclude=False, practice=True)
    assert len(everything.trials) == 40
    assert everything.trials["correct"].isna().sum() == 4     # time-outs kept, not recoded
    assert any("exclusions were not applied" in w for w in everything.warnings)
    no_rules = load_dataset(root, plan, exclude=False)
    assert len(no_rules.trials) == 38                         # practice still out
    assert len(with_practice.trials) == 36


def test_analyze_takes_loaded_data_and_another_plan(tmp_path):
    root = dataset(tmp_path / "ds", n_participants=4, repetitions=2)
    plan = write_plan(tmp_path / "plan.toml")
    data = load_dataset(root, plan)
    a = analyze(data, write=False).to_dict()
    b = analyze(root, plan, write=False).to_dict()
    a.pop("generated_at"), b.pop("generated_at")
    assert a == b
    # the other plan takes the chi2 p: the bootstrap's p is not what it is read for
    base = load_plan(plan)
    strict = replace(base, alpha=0.01, exclusions=replace(base.exclusions,
                                                          max_response_time_s=2.0),
                     primary=replace(base.primary, p_value="chi2"))
    other = analyze(data, strict, write=False)
    assert other.results["alpha"] == 0.01 and "slow" in other.results["exclusions"]
    assert other.results["plan"] == {"name": "test plan", "path": None, "sha256": None,
                                     "lock": {"status": "not locked", "locked_at": None,
                                              "sha256": None, "deviations": []}}
    assert len(other.data.trials) < len(data.trials)
    files = other.write(tmp_path / "out")
    assert "Plan `test plan` (given in Python, not read from a file)" in \
        files.report.read_text()
