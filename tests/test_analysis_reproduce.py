"""``analyze --check``: a reanalysis against an earlier results.json (crs_study.analysis.
reproduce). A reviewer's question is whether the published numbers come back; the comparison
must say yes when only where, when and with which version differ, and name every value that
moved otherwise."""

from __future__ import annotations

import copy
import json
import shutil

import pytest
from _cli import crs_study
from _session_helpers import tiny_protocol
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.analysis import analyze
from crs_study.analysis.reproduce import compare_results
from crs_study.errors import AnalysisError


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    """A dry-run of three simulated participants, analysed once (results.json written)."""
    folder = tmp_path_factory.mktemp("reproduce")
    done = crs_study("dry-run", tiny_protocol(folder), "--participants", 3, "--out",
                     folder / "ds", "--responder", "random")
    assert done.returncode == 0, done.stderr
    analyze(folder / "ds")  # results.json written, as the command writes it
    return folder / "ds"


def test_the_same_data_give_the_same_numbers_even_moved_elsewhere(analysed, tmp_path):
    moved = tmp_path / "elsewhere" / analysed.name
    shutil.copytree(analysed, moved)
    earlier = analysed / "derivatives/crs-study/results.json"
    done = crs_study("analyze", moved, "--check", earlier)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("the same numbers: ") and "both times" in done.stdout
    # --check writes nothing: the moved copy's own results are the copied ones, untouched
    assert (moved / "derivatives/crs-study/results.json").read_bytes() == earlier.read_bytes()


@pytest.mark.slow
def test_a_changed_number_is_named_with_both_values(analysed, tmp_path):
    results = json.loads((analysed / "derivatives/crs-study/results.json").read_text())
    comparison = results["comparisons"][0]
    comparison["p_value"] = comparison["p_value"] * 1.01 + 1e-9
    results["software"]["version"] = "0.0.1"
    earlier = tmp_path / "results.json"
    earlier.write_text(json.dumps(results))
    done = crs_study("analyze", analysed, "--check", earlier)
    assert done.returncode == 1, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("the numbers differ in 1 of ")
    assert "crs-study 0.0.1 then" in lines[0]
    assert lines[1].startswith("  comparisons[0].p_value: ")
    verdict = json.loads(crs_study("analyze", analysed, "--check", earlier, "--json").stdout)
    assert not verdict["same"] and verdict["differences"][0]["where"] == "comparisons[0].p_value"


@pytest.mark.parametrize("argv, message", [
    (["--check", "/nonexistent/results.json"], "cannot read the earlier results"),
    (["--check", "{dataset}/dataset_description.json"], "not a results.json"),
    (["--check", "{dataset}/derivatives/crs-study/results.json", "--check-rtol", "1.5"],
     "tolerance"),
    (["--check", "{dataset}/derivatives/crs-study/results.json", "--out", "x"],
     "--check writes nothing"),
])
def test_bad_checks_are_one_line(analysed, argv, message, capsys):
    from crs_study.cli import main

    assert main(["analyze", str(analysed), *(a.format(dataset=analysed) for a in argv)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err


def test_from_python_an_analysis_compares_with_a_path_or_a_dict(analysed):
    analysis = analyze(analysed, write=False)
    earlier = analysed / "derivatives/crs-study/results.json"
    assert analysis.compare(earlier).same
    content = json.loads(earlier.read_text())
    content["n_trials_total"] += 1
    verdict = analysis.compare(content)
    assert [d.where for d in verdict.differences] == ["n_trials_total"]


# --- the comparison itself ------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.text(max_size=5)
    | st.floats(-1e6, 1e6, allow_nan=False),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner,
                                                                   max_size=4),
    max_leaves=20)
results_like = st.dictionaries(st.text(min_size=1, max_size=6), json_values, max_size=6)


@settings(max_examples=200, deadline=None)
@given(results=results_like)
def test_a_result_is_the_same_as_itself_and_provenance_never_counts(results):
    again = copy.deepcopy(results)
    again["generated_at"] = "2030-01-01T00:00:00+00:00"
    again["software"] = {"name": "crs-study", "version": "9.9"}
    again["charts"] = ["figures/other.png"]
    verdict = compare_results(results, again)
    assert verdict.same and verdict.largest_relative == 0.0


@settings(max_examples=200, deadline=None)
@given(value=st.floats(-1e6, 1e6, allow_nan=False).filter(lambda v: abs(v) > 1e-3),
       factor=st.floats(1e-9, 1e-3))
def test_a_number_differs_exactly_when_it_moves_beyond_the_tolerance(value, factor):
    earlier = {"primary": {"estimate": value}, "headline": "x"}
    moved = {"primary": {"estimate": value * (1 + factor)}, "headline": "x"}
    verdict = compare_results(earlier, moved, rtol=1e-6)
    relative = abs(value * factor) / max(abs(value), abs(value * (1 + factor)))
    assert verdict.same == (relative <= 1e-6)
    if not verdict.same:
        assert [d.where for d in verdict.differences] == ["primary.estimate"]


def test_missing_keys_items_types_and_dataset_paths():
    earlier = {"a": [1, 2, 3], "b": {"c": 1}, "d": True, "e": 1,
               "datasets": [{"path": "/lab/old/ds", "name": "n"}],
               "warnings": ["/lab/old/ds/sub-01: no trial file"]}
    now = {"a": [1, 2], "b": {"c": 1, "x": 0}, "d": 1, "e": 1.0,
           "datasets": [{"path": "/home/reviewer/ds", "name": "n"}],
           "warnings": ["/home/reviewer/ds/sub-01: no trial file"]}
    earlier["seed"], now["seed"] = 10690251453282634688, 10690251453282634689
    verdict = compare_results(earlier, now)
    assert [d.where for d in verdict.differences] == ["a[2]", "b.x", "d", "seed"]
    assert "a[2]: 3 then, null now" in verdict.describe()
    with pytest.raises(AnalysisError, match="tolerance"):
        compare_results(earlier, now, rtol=float("nan"))
