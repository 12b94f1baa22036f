"""The dataset's paths (crs_study.dataset.bids): names built and parsed, sessions found, and
the writer putting every file where the module says.

Names follow the BIDS specification, "Common principles: file name structure" (entities
``key-label`` joined by ``_``, then the suffix and extension; alphanumeric labels).
"""

from __future__ import annotations

import shutil
import string
from pathlib import Path

import pytest
from _session_helpers import record_consent
from hypothesis import given
from hypothesis import strategies as st

from crs_study.dataset import bids
from crs_study.dataset.bids import BidsName, SessionPaths
from crs_study.errors import DatasetError


@pytest.fixture(autouse=True)
def _consented():
    """p01: people's labels, gated by consent on every device, sim:// too."""
    record_consent("p01")


FIXTURE = Path(__file__).parent / "fixtures" / "sessions_4c71d44" / "dataset"
_label = st.text(string.ascii_letters + string.digits, min_size=1, max_size=10)


def test_session_paths_are_the_layout_the_dataset_has_always_had(tmp_path):
    paths = SessionPaths(tmp_path, "p7k2m9q", 2)
    beh = tmp_path / "sub-p7k2m9q" / "ses-2" / "beh"
    assert paths.tsv == beh / "sub-p7k2m9q_ses-2_task-digitid_beh.tsv"
    assert paths.sidecar == beh / "sub-p7k2m9q_ses-2_task-digitid_beh.json"
    assert paths.lock == tmp_path / "sub-p7k2m9q" / "ses-2" / ".sub-p7k2m9q_ses-2.lock"
    source = tmp_path / "sourcedata" / "sub-p7k2m9q" / "ses-2"
    assert paths.frame_log == source / "sub-p7k2m9q_ses-2_task-digitid_frames.tsv.gz"
    assert paths.torn_backup("beh", "20261124T000000Z") == \
        source / "sub-p7k2m9q_ses-2_task-digitid_beh-torn-20261124T000000Z.bin"
    assert bids.derivatives_dir(tmp_path) == tmp_path / "derivatives" / "crs-study"
    assert bids.task_sidecar_name() == "task-digitid_beh.json"


def test_a_session_less_participant_has_no_ses_entity(tmp_path):
    paths = SessionPaths(tmp_path, "a1", None)
    assert paths.tsv == tmp_path / "sub-a1" / "beh" / "sub-a1_task-digitid_beh.tsv"
    assert paths.frame_log == tmp_path / "sourcedata" / "sub-a1" / \
        "sub-a1_task-digitid_frames.tsv.gz"
    assert paths.lock == tmp_path / "sub-a1" / ".sub-a1.lock"


@pytest.mark.parametrize("participant, session", [("p-1", 1), ("", 1), ("p1", "1_2"),
                                                  ("p1", "")])
def test_labels_that_are_not_bids_are_refused(tmp_path, participant, session):
    with pytest.raises(DatasetError, match=r"label .* is not valid: BIDS labels are letters "
                                           r"and digits only"):
        SessionPaths(tmp_path, participant, session)


@given(participant=_label, session=st.none() | st.integers(1, 10**4) | _label, task=_label,
       suffix=_label, extension=st.sampled_from([".tsv", ".json", ".tsv.gz", ".bin"]))
def test_names_parse_back_to_their_entities(participant, session, task, suffix, extension):
    entities = (("sub", participant),) + ((("ses", str(session)),) if session is not None
                                           else ()) + (("task", task),)
    name = "_".join(f"{k}-{v}" for k, v in entities) + f"_{suffix}{extension}"
    parsed = BidsName.parse(name)
    assert parsed == BidsName(entities, suffix, extension)
    assert parsed.name == name
    assert (parsed.participant, parsed.task) == (participant, task)
    assert parsed.session == (None if session is None else str(session))


@pytest.mark.parametrize("name", [
    "participants.tsv", "task-digitid_beh.json", "sub-a1", "sub-a1_beh", "sub-a_1_beh.tsv",
    "sub-a1_ses-1_ses-2_task-x_beh.tsv", "sub-a1_task-x_beh.", "sub-a1_task-x_beh.tsv ",
    "xsub-a1_task-x_beh.tsv", "sub-a1_task-x-y_beh.tsv",
])
def test_other_names_do_not_parse(name):
    assert BidsName.parse(name) is None


@given(participant=_label, session=st.none() | st.integers(1, 10**4) | _label)
def test_a_trial_file_path_gives_back_its_session(participant, session):
    root = Path("/data/study")
    paths = SessionPaths(root, participant, session)
    assert SessionPaths.from_beh_file(paths.tsv) == paths
    assert paths.session == (int(session) if str(session).isdigit()
                             and str(int(session)) == str(session) and int(session) >= 1
                             else session)


def test_a_moved_or_misnamed_trial_file_is_one_line(tmp_path):
    moved = tmp_path / "sub-b2" / "ses-1" / "beh" / "sub-a1_ses-1_task-digitid_beh.tsv"
    with pytest.raises(DatasetError, match=r"the file name says sub-a1 ses-1 but it is stored "
                                           r"in .*sub-b2/ses-1/beh; expected .*sub-a1/ses-1/beh"):
        SessionPaths.from_beh_file(moved)
    with pytest.raises(DatasetError, match="not a session's trial file"):
        SessionPaths.from_beh_file(tmp_path / "sub-a1" / "beh" / "sub-a1_task-digitid_events.tsv")
    with pytest.raises(DatasetError, match="expected the file inside a dataset's"):
        SessionPaths.from_beh_file(Path("sub-a1_ses-1_task-digitid_beh.tsv"))


def test_find_sessions_in_a_dataset_written_by_the_previous_code():
    found = bids.find_sessions(FIXTURE)
    assert [(s.participant, s.session) for s in found] == \
        [("p01", 1), ("p02", 1), ("p03", 1), ("p04", 1)]
    assert all(s.root == FIXTURE and s.tsv.is_file() and s.sidecar.is_file()
               and s.frame_log.is_file() for s in found)


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    return path


def test_beh_files_sessions_first_then_session_less_participants_each_sorted(tmp_path):
    # The order the analysis has always read sessions in (analysis/load.py's globs).
    files = [_touch(SessionPaths(tmp_path, p, s).tsv)
             for p, s in (("b", 1), ("a", 2), ("a", 10), ("c", None), ("a0", None))]
    _touch(tmp_path / "sub-a" / "ses-1" / "beh" / "sub-a_ses-1_task-other_beh.tsv")
    _touch(tmp_path / "sub-a" / "ses-1" / "beh" / "sub-a_ses-1_task-digitid_beh.json")
    _touch(tmp_path / "sourcedata" / "sub-a" / "ses-1" / "sub-a_ses-1_task-digitid_beh.tsv")
    _touch(tmp_path / "derivatives" / "x" / "sub-a_task-digitid_beh.tsv")
    # sorted as paths are: ses-10 before ses-2
    assert bids.beh_files(tmp_path) == [files[2], files[1], files[0], files[4], files[3]]
    assert [(s.participant, s.session) for s in bids.find_sessions(tmp_path)] == \
        [("a", 10), ("a", 2), ("b", 1), ("a0", None), ("c", None)]
    assert [s.participant for s in bids.find_sessions(tmp_path, task="other")] == ["a"]
    assert bids.beh_files(tmp_path / "nowhere") == []


def test_session_numbers(tmp_path):
    for name in ("ses-2", "ses-10", "ses-x", "ses-1"):
        (tmp_path / "sub-a" / name).mkdir(parents=True)
    assert bids.session_numbers(tmp_path, "a") == [1, 2, 10]
    assert bids.session_numbers(tmp_path, "b") == []


def test_the_writer_puts_every_file_where_the_module_says(tmp_path):
    """A session with a torn row cut on resume: each file written is one the module names."""
    from _session_helpers import tiny_protocol

    from crs_study.dataset import ARRIVALS_FILE
    from crs_study.session.runner import run_session
    from crs_study.session.spec import SessionSpec

    protocol = tiny_protocol(tmp_path)
    spec = SessionSpec(protocol, "p01", tmp_path / "ds", "sim://", 1, "random", "virtual")
    result = run_session(spec)
    paths = SessionPaths(tmp_path / "ds", "p01", 1)
    assert (result.tsv, result.sidecar) == (paths.tsv, paths.sidecar)
    with paths.tsv.open("a") as handle:  # a torn row, as after a kill mid-append
        handle.write("8\ttest")
    paths.sidecar.write_text(paths.sidecar.read_text().replace('"complete"', '"interrupted"'))
    assert run_session(spec).trials_run == 0  # the torn tail is cut and kept under sourcedata
    written = {p for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    (backup,) = paths.source_dir.glob("*-torn-*.bin")
    assert backup.name.startswith(f"{paths.stem}_beh-torn-")
    expected = {paths.tsv, paths.sidecar, paths.lock, paths.frame_log, backup}
    root = tmp_path / "ds"
    expected |= {root / name for name in (bids.DATASET_DESCRIPTION, bids.PARTICIPANTS_TSV,
                                          bids.PARTICIPANTS_JSON, bids.DATASET_README,
                                          bids.task_sidecar_name(), ".crs-study.lock",
                                          ARRIVALS_FILE)}  # the count that counterbalances
    assert written == expected
    assert bids.find_sessions(root) == [paths]


def test_find_sessions_agrees_with_what_the_analysis_loads(tmp_path):
    """The reader can switch to this module: the same sessions, in the same order, as
    crs_study.analysis.load finds today (fixture sessions and a session-less participant)."""
    from crs_study.analysis.load import load_datasets

    root = Path(shutil.copytree(FIXTURE, tmp_path / "ds"))
    extra = SessionPaths(root, "p00", None)
    extra.beh_dir.mkdir(parents=True)
    extra.tsv.write_bytes(SessionPaths(root, "p02", 1).tsv.read_bytes())
    loaded = load_datasets(root)
    assert any("p00" in w and "metadata missing" in w for w in loaded.warnings)
    sessions = loaded.sessions[["participant", "session", "file"]].to_records(index=False)
    assert [(p, s, Path(f)) for p, s, f in sessions] == \
        [(s.participant, "" if s.session is None else str(s.session), s.tsv)
         for s in bids.find_sessions(root)]
