"""Loading datasets: the tidy table's columns and types, integrity checks, exclusions."""

from __future__ import annotations

import hashlib
import shutil

import numpy as np
import pandas as pd
import pytest
from analysis_fixtures import dataset, edit_sidecar, explicit_dataset, session_files
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.analysis.load import load_datasets, with_exclusions
from crs_study.analysis.plan import Exclusions
from crs_study.dataset import SessionMetadata
from crs_study.dataset.schema import TRIAL_COLUMNS
from crs_study.errors import DatasetError


@pytest.fixture
def small(tmp_path):
    return dataset(tmp_path / "ds", n_participants=3, p_timeout=0.1, p_fault=0.05,
                   p_anticipation=0.05)


def test_every_schema_column_is_typed(small):
    data = load_datasets(small)
    trials = data.trials
    assert list(trials.columns[:4]) == ["dataset", "participant", "participant_id", "session"]
    assert set(TRIAL_COLUMNS) <= set(trials.columns)
    assert trials["digit"].dtype == np.int64
    assert str(trials["response"].dtype) == "Int64"
    assert trials["correct"].dtype == float and trials["response_time"].dtype == float
    assert trials["timed_out"].dtype == bool and trials["device_fault"].dtype == bool
    assert set(trials["participant"]) == {"01", "02", "03"} and set(trials["session"]) == {"1"}
    timed_out = trials["timed_out"]
    assert timed_out.any()
    # n/a became missing values, never strings
    assert trials.loc[timed_out, "correct"].isna().all()
    assert trials.loc[timed_out, "response"].isna().all()
    assert trials.loc[timed_out, "response_time"].isna().all()
    assert not data.warnings and len(data.sessions) == 3


def test_exclusions_are_counted_per_reason_and_condition(small):
    rules = Exclusions(anticipation_s=0.15)
    data = with_exclusions(load_datasets(small), rules)
    t = data.trials
    assert t.loc[t["trial_type"] == "practice", "excluded"].all()
    assert (t.loc[t["exclusion"] == "anticipation", "response_time"] < 0.15).all()
    kept = data.analysed
    assert kept["correct"].notna().all() and not kept["device_fault"].any()
    assert (kept["response_time"] >= 0.15).all() and (kept["trial_type"] == "test").all()
    counts = data.exclusion_counts
    assert set(counts) == {"practice", "device_fault", "timeout", "anticipation"}
    assert sum(sum(c.values()) for c in counts.values()) == int(t["excluded"].sum())
    for reason, per_condition in counts.items():
        for condition, n in per_condition.items():
            assert n == ((t["exclusion"] == reason) & (t["condition"] == condition)).sum()


def test_timeouts_can_count_as_errors(small):
    data = with_exclusions(load_datasets(small), Exclusions(timeouts="count_as_error"))
    timed_out = data.analysed["timed_out"]
    assert timed_out.any() and (data.analysed.loc[timed_out, "correct"] == 0).all()
    assert "timeout" not in data.exclusion_counts


def test_slow_responses_are_excluded_when_the_plan_says(small):
    data = with_exclusions(load_datasets(small), Exclusions(max_response_time_s=2.5))
    assert (data.analysed["response_time"] <= 2.5).all()
    assert sum(data.exclusion_counts["slow"].values()) > 0


def test_edited_trials_are_reported_as_tampering(small):
    tsv, _ = session_files(small)[0]
    tsv.write_bytes(tsv.read_bytes().replace(b"\t0\t", b"\t1\t", 1))
    data = load_datasets(small)
    assert any("TAMPERED?" in w and tsv.name in w for w in data.warnings)
    with pytest.raises(DatasetError, match=r"TAMPERED\? sha256 is"):
        load_datasets(small, strict=True)


def test_metadata_mismatch_and_status_are_reported(small):
    (_, first), (_, second), (_, third) = session_files(small)
    edit_sidecar(first, Participant="99")
    edit_sidecar(second, ProtocolSha256="0" * 64)
    edit_sidecar(third, Status="interrupted")
    warnings = load_datasets(small).warnings
    assert any("Participant is '99' but the file name says '01'" in w for w in warnings)
    assert any("ProtocolSha256 does not match" in w for w in warnings)
    assert any("status is 'interrupted'" in w for w in warnings)


def test_correct_is_recomputed_when_it_contradicts_the_response(tmp_path):
    root = explicit_dataset(tmp_path / "ds", {"01": [("crs", 3, 0, 1), ("crs", 4, 0, 0)]})
    tsv, sidecar = session_files(root)[0]
    lines = tsv.read_text().splitlines()
    columns = lines[0].split("\t")
    cells = lines[1].split("\t")
    cells[columns.index("correct")] = "0"      # digit 3 answered 3, yet marked wrong
    lines[1] = "\t".join(cells)
    tsv.write_text("\n".join(lines) + "\n")
    data = load_datasets(root)
    assert any("row 2: correct=0 disagrees with digit=3 response=3" in w for w in data.warnings)
    assert data.trials["correct"].tolist() == [1.0, 0.0]


@pytest.mark.parametrize(("column", "value", "message"), [
    pytest.param("digit", "seven", r"row 2: column 'digit': expected a finite number or 'n/a', "
                 r"got 'seven'", id="text-in-number"),
    pytest.param("repetition", "1.5", r"row 2: column 'repetition': expected a whole number",
                 id="fraction"),
    pytest.param("digit", "n/a", r"row 2: column 'digit' is 'n/a'", id="missing-digit"),
    pytest.param("response_time", "inf", r"row 2: column 'response_time': expected a finite "
                 r"number or 'n/a', got '?inf'?", id="infinite"),
])
def test_malformed_cells_fail_in_one_line(tmp_path, column, value, message):
    root = explicit_dataset(tmp_path / "ds", {"01": [("crs", 3, 0, 1), ("crs", 4, 0, 0)]})
    tsv, _ = session_files(root)[0]
    frame = pd.read_csv(tsv, sep="\t", dtype=str, keep_default_na=False)
    frame.loc[0, column] = value
    frame.to_csv(tsv, sep="\t", index=False)
    with pytest.raises(DatasetError, match=message) as info:
        load_datasets(root)
    assert tsv.name in str(info.value) and "\n" not in str(info.value)


def test_missing_column_and_missing_dataset(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: no such dataset directory"):
        load_datasets(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty: no sessions found"):
        load_datasets(tmp_path / "empty")
    root = explicit_dataset(tmp_path / "ds", {"01": [("crs", 3, 0, 1)]})
    tsv, _ = session_files(root)[0]
    frame = pd.read_csv(tsv, sep="\t", dtype=str).drop(columns="condition")
    frame.to_csv(tsv, sep="\t", index=False)
    with pytest.raises(DatasetError, match=r"missing column 'condition'"):
        load_datasets(root)


def test_missing_sidecar_is_a_warning(small):
    session_files(small)[0][1].unlink()
    assert any("session metadata missing" in w for w in load_datasets(small).warnings)


def test_synthetic_sidecars_are_the_runners_format(small):
    """synthetic wrote a reduced sidecar (19 keys, "Session": "1") that the strict reader of
    the runner's format refused; it writes a real SessionMetadata now."""
    for tsv, sidecar in session_files(small):
        meta = SessionMetadata.read(sidecar)
        assert meta.to_json() == sidecar.read_text()
        assert (meta.session, meta.status, meta.trials_completed) == (
            1, "complete", len(tsv.read_text().splitlines()) - 1)
    assert not [w for w in load_datasets(small).warnings if "session metadata" in w]


@pytest.mark.parametrize(("change", "reason"), [
    pytest.param({"Experimenter": "AB"}, "unknown key Experimenter", id="unknown-key"),
    pytest.param({"Seed": "seven"}, "Seed", id="mistyped"),
    pytest.param({"Clock": "sundial"}, "Clock", id="bad-choice"),
])
def test_an_invalid_sidecar_is_read_strictly_a_warning_or_with_strict_an_error(small, change,
                                                                              reason):
    """The sidecar is read as the runner's format (SessionMetadata): a key it does not know, or
    a value of the wrong type, leaves the session's trials unchecked (it was ignored)."""
    tsv, sidecar = session_files(small)[1]
    edit_sidecar(sidecar, **change)
    warnings = [w for w in load_datasets(small).warnings if sidecar.name in w]
    assert len(warnings) == 1 and "session metadata unreadable (" in warnings[0]
    assert reason in warnings[0] and warnings[0].endswith("its trials are unchecked")
    with pytest.raises(DatasetError, match="session metadata unreadable") as info:
        load_datasets(small, strict=True)
    assert "\n" not in str(info.value)


def test_a_trial_file_stored_where_its_name_does_not_say_is_one_line(small):
    """Sessions are found by the dataset's own paths module (crs_study.dataset.bids): a file
    moved by hand under another participant's folder was loaded under its name's label."""
    tsv, sidecar = session_files(small)[0]
    other = tsv.parents[2].with_name("sub-99") / "ses-1" / "beh"
    other.mkdir(parents=True)
    shutil.move(tsv, other / tsv.name)
    with pytest.raises(DatasetError, match=r"the file name says sub-01 ses-1 but it is stored "
                       r"in .*sub-99/ses-1/beh"):
        load_datasets(small)


def test_several_datasets_keep_participants_apart(tmp_path):
    a = dataset(tmp_path / "a", n_participants=2)
    b = dataset(tmp_path / "b", n_participants=2, seed=5)
    trials = load_datasets([a, b]).trials
    assert trials["participant_id"].nunique() == 4       # both have sub-01 and sub-02
    assert trials["dataset"].nunique() == 2


def test_a_dataset_named_twice_is_refused_in_one_line(tmp_path, monkeypatch):
    root = dataset(tmp_path / "ds", n_participants=2, repetitions=1)
    (tmp_path / "link").symlink_to(root, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    for second in (root, tmp_path / "ds" / ".", "ds", tmp_path / "link"):
        with pytest.raises(DatasetError, match=r"the same dataset as .*ds \(given twice\)"
                           ) as info:
            load_datasets([root, second])
        assert "\n" not in str(info.value)


def test_a_copy_of_a_dataset_is_refused_not_counted_twice(tmp_path):
    root = dataset(tmp_path / "ds", n_participants=2, repetitions=1)
    shutil.copytree(root, tmp_path / "backup")
    with pytest.raises(DatasetError, match=r"the same session \(sub-01 ses-1, identical trial "
                       r"file\) is also in .*ds: the datasets are copies") as info:
        load_datasets([root, tmp_path / "backup"])
    assert "\n" not in str(info.value)
    # one participant's session copied into another dataset is caught as well
    other = dataset(tmp_path / "other", n_participants=2, repetitions=1, seed=9)
    shutil.rmtree(other / "sub-02")
    shutil.copytree(root / "sub-02", other / "sub-02")
    with pytest.raises(DatasetError, match=r"sub-02 ses-1"):
        load_datasets([root, other])


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(column=st.sampled_from(sorted(TRIAL_COLUMNS)), row=st.integers(0, 3),
       value=st.one_of(st.text(alphabet=st.characters(blacklist_characters="\t\n\r"),
                               max_size=6), st.sampled_from(["n/a", "1e400", "-0", "2.5"])))
def test_any_edited_cell_loads_with_a_warning_or_fails_in_one_line(tmp_path, column, row, value):
    root = tmp_path / f"h{abs(hash((column, row, value)))}"
    explicit_dataset(root, {"01": [("crs", 3, 0, 1), ("crs", 4, 0, 0), ("pixel-only", 3, 0, 1),
                                   ("pixel-only", 4, 0, None)]})
    tsv, _ = session_files(root)[0]
    lines = tsv.read_text().splitlines()
    names = lines[0].split("\t")
    cells = lines[row + 1].split("\t")
    cells[names.index(column)] = value
    lines[row + 1] = "\t".join(cells)
    tsv.write_text("\n".join(lines) + "\n")
    try:
        data = load_datasets(root)
    except DatasetError as error:
        assert "\n" not in str(error) and tsv.name in str(error)
    else:
        edited = data.sessions["TrialsSha256"].iloc[0] != hashlib.sha256(
            tsv.read_bytes()).hexdigest()
        assert any("TAMPERED?" in w for w in data.warnings) == edited
        assert len(data.trials) == 4
