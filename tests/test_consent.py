"""Consent records, the gate, withdrawal."""

from __future__ import annotations

import fcntl
import json
import os
import stat
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study import consent
from crs_study.cli import main
from crs_study.dataset import DATASET_LOCK
from crs_study.errors import ConsentError, CrsStudyWarning
from crs_study.paths import shipped_file

FORM = shipped_file("consent/consent_form.md")


def write_form(path: Path, version: str = "2.0", body: str = "- [ ] I agree.\n") -> Path:
    path.write_text(f"# Consent form\n\nVersion: {version}\n\n{body}", encoding="utf-8")
    return path


# --- forms ----------------------------------------------------------------------------------

def test_shipped_form_and_sheet_carry_version_1_0():
    form = consent.read_form(FORM)
    assert form.version == "1.0"
    assert len(form.sha256) == 64
    sheet = shipped_file("consent/information_sheet.md").read_text(encoding="utf-8")
    assert "Version: 1.0" in sheet


@pytest.mark.parametrize("text, match", [
    pytest.param("Version: 1\n- [ ] yes\n", "Title", id="no-title"),
    pytest.param("# Form\n- [ ] yes\n", "exactly one 'Version", id="no-version"),
    pytest.param("# Form\nVersion: 1\nVersion: 2\n- [ ] yes\n", "found 2", id="two-versions"),
    pytest.param("# Form\nVersion: 1\nI agree.\n", "consent statements", id="no-statements"),
    # an empty version line must not borrow the next line's first word ('-')
    pytest.param("# Form\nVersion:\n\n- [ ] yes\n", "gives no version", id="empty-version"),
])
def test_malformed_form_refused(tmp_path, text, match):
    path = tmp_path / "form.md"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConsentError, match=match):
        consent.read_form(path)


def test_missing_and_binary_form_refused(tmp_path):
    with pytest.raises(ConsentError, match="no such consent form"):
        consent.read_form(tmp_path / "absent.md")
    binary = tmp_path / "form.md"
    binary.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ConsentError, match="cannot read"):
        consent.read_form(binary)


# --- records --------------------------------------------------------------------------------

def test_record_stores_who_when_which_form(tmp_path):
    register = consent.Register(tmp_path / "reg")
    record = register.record(consent.read_form(FORM), "ab", "p01", name="Ada Lovelace")
    assert record.participant == "p01"
    assert record.form_version == "1.0"
    assert record.experimenter == "AB"
    assert record.form_sha256 == consent.read_form(FORM).sha256
    assert record.time.endswith("+00:00")
    # owner-only permissions on the register directory and its file
    assert stat.S_IMODE(os.stat(tmp_path / "reg").st_mode) == 0o700
    assert stat.S_IMODE(os.stat(register.path).st_mode) == 0o600
    assert consent.Register(tmp_path / "reg").records()["p01"].name == "Ada Lovelace"


def test_generated_labels_are_bids_valid_and_unique(tmp_path):
    register = consent.Register(tmp_path)
    labels = {register.record(consent.read_form(FORM), "AB").participant for _ in range(50)}
    assert len(labels) == 50
    assert all(consent.check_label(label) == label for label in labels)


@settings(max_examples=200, deadline=None)
@given(st.text(min_size=0, max_size=12))
def test_label_check_accepts_exactly_alphanumeric(label):
    valid = label.isascii() and label.isalnum()
    if valid:
        assert consent.check_label(label) == label
    else:
        with pytest.raises(ConsentError, match="letters and digits"):
            consent.check_label(label)


@pytest.mark.parametrize("label", ["ab1\n", "\nab1", "ab 1", "sub-1", "a_b", "../x", "é1", ""])
def test_label_check_refuses_near_misses(label):
    """A trailing newline slipped through a '$'-anchored pattern; it is not BIDS-valid."""
    with pytest.raises(ConsentError, match="letters and digits"):
        consent.check_label(label)


def test_register_inside_a_dataset_is_refused(tmp_path):
    dataset = tmp_path / "ds"
    (dataset / "code").mkdir(parents=True)
    (dataset / "dataset_description.json").write_text("{}")
    for place in (dataset / "register", dataset / "code" / "reg", dataset):
        with pytest.raises(ConsentError, match="inside the dataset"):
            consent.Register(place).record(consent.read_form(FORM), "AB", "p1", name="Ada")
        with pytest.raises(ConsentError, match="inside the dataset"):
            consent.Register(place).records()
    assert not any("Ada" in p.read_text() for p in dataset.rglob("*") if p.is_file())


@pytest.mark.parametrize("initials", ["", "A1", "ABCDE", "A B"])
def test_bad_experimenter_initials_refused(tmp_path, initials):
    with pytest.raises(ConsentError, match="initials"):
        consent.Register(tmp_path).record(consent.read_form(FORM), initials, "p1")


def test_corrupt_register_line_is_a_one_line_error(tmp_path):
    (tmp_path / consent.REGISTER_FILE).write_text('{"event": "consent"\n', encoding="utf-8")
    os.chmod(tmp_path / consent.REGISTER_FILE, 0o600)
    with pytest.raises(ConsentError, match=r"register.jsonl:1: not a consent register line"):
        consent.Register(tmp_path).records()


def test_cli_record_and_list_hide_names(tmp_path, capsys):
    reg = str(tmp_path / "reg")
    assert main(["consent", "record", "--register", reg, "--participant", "p7",
                 "--form", str(FORM), "--experimenter", "CD", "--name", "Grace Hopper"]) == 0
    assert main(["consent", "list", "--register", reg, "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line[:1] == "{"]
    assert rows == [{**rows[0], "participant": "p7", "status": "consented"}]
    assert "name" not in rows[0]
    assert main(["consent", "list", "--register", reg, "--show-names"]) == 0
    assert "Grace Hopper" in capsys.readouterr().out


def test_cli_malformed_form_is_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.md"
    bad.write_text("# Form\nno version\n- [ ] ok\n", encoding="utf-8")
    code = main(["consent", "record", "--register", str(tmp_path), "--participant", "p1",
                 "--form", str(bad), "--experimenter", "AB"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "Version" in err[0]


# --- the gate -------------------------------------------------------------------------------

def test_gate_refuses_without_record(tmp_path):
    with pytest.raises(ConsentError, match="no consent record for participant 'p1'.*"
                                           "crs-study consent record"):
        consent.require_consent(tmp_path, "p1", "1.0")


def test_gate_refuses_mismatched_version_and_admits_match(tmp_path):
    register = consent.Register(tmp_path)
    register.record(consent.read_form(FORM), "AB", "p1")
    with pytest.raises(ConsentError, match="form version '1.0', the protocol needs version '2.0'"):
        consent.require_consent(tmp_path, "p1", "2.0")
    assert consent.require_consent(tmp_path, "p1", "1.0").participant == "p1"
    # consent on the new form (a renewal, said so) admits the new version
    register.record(consent.read_form(write_form(tmp_path / "v2.md", "2.0")), "AB", "p1",
                    renew=True)
    assert consent.require_consent(tmp_path, "p1", "2.0").form_version == "2.0"


def test_gate_refuses_a_form_changed_without_a_new_version(tmp_path):
    register = consent.Register(tmp_path / "reg")
    register.record(consent.read_form(write_form(tmp_path / "old.md", "2.0")), "AB", "p1")
    changed = consent.read_form(write_form(tmp_path / "new.md", "2.0", "- [ ] I agree to more.\n"))
    with pytest.raises(ConsentError, match="text differs.*new version"):
        consent.require_consent(register.directory, "p1", "2.0", changed)
    same_text = consent.read_form(write_form(tmp_path / "copy.md", "2.0"))
    assert consent.require_consent(register.directory, "p1", "2.0", same_text).participant == "p1"


def test_gate_refuses_withdrawn_participant(tmp_path):
    register = consent.Register(tmp_path / "reg")
    register.record(consent.read_form(FORM), "AB", "p1")
    dataset = tmp_path / "ds"
    dataset.mkdir()
    (dataset / "dataset_description.json").write_text("{}")
    consent.withdraw("p1", [dataset], tmp_path / "reg")
    with pytest.raises(ConsentError, match="withdrew consent"):
        consent.require_consent(tmp_path / "reg", "p1", "1.0")
    with pytest.raises(ConsentError, match="new label"):
        register.record(consent.read_form(FORM), "AB", "p1")


# --- withdrawal -----------------------------------------------------------------------------

PARTICIPANTS = ("a1", "a10", "b2")


def make_dataset(root: Path) -> Path:
    """A dataset in the stored layout (docs/architecture.md) with three participants (labels a1
    and a10 share a prefix on purpose)."""
    root.mkdir(parents=True)
    (root / "dataset_description.json").write_text('{"Name": "t"}\n')
    (root / DATASET_LOCK).touch()  # as in every dataset a runner made
    rows = "".join(f"sub-{p}\t{i}\n" for i, p in enumerate(PARTICIPANTS))
    (root / "participants.tsv").write_text("participant_id\tcounterbalance\n" + rows)
    for p in PARTICIPANTS:
        for ses in (1, 2):
            beh = root / f"sub-{p}" / f"ses-{ses}" / "beh"
            beh.mkdir(parents=True)
            stem = f"sub-{p}_ses-{ses}_task-digitid_beh"
            (beh / f"{stem}.tsv").write_text(f"trial_index\tdigit\n0\t{ses}\n")
            (beh / f"{stem}.json").write_text(json.dumps({"Participant": p}))
        src = root / "sourcedata" / f"sub-{p}" / "ses-1"
        src.mkdir(parents=True)
        (src / f"sub-{p}_ses-1_frames.tsv.gz").write_bytes(bytes(range(64)) + p.encode())
        deriv = root / "derivatives" / "crs-study" / f"sub-{p}"
        deriv.mkdir(parents=True)
        (deriv / f"sub-{p}_accuracy.tsv").write_text("acc\n0.5\n")
    return root


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_withdrawal_removes_one_participant_and_leaves_others_byte_identical(tmp_path):
    dataset = make_dataset(tmp_path / "ds")
    register = consent.Register(tmp_path / "reg")
    for p in PARTICIPANTS:
        register.record(consent.read_form(FORM), "AB", p, name=f"Name {p}")
    before = snapshot(dataset)

    entries = consent.withdraw("a1", [dataset], register.directory)

    after = snapshot(dataset)
    gone = {k for k in before if "sub-a1/" in k or "/sub-a1_" in k or k.startswith("sub-a1/")}
    assert gone and not any(k in after for k in gone)
    assert set(after) == set(before) - gone  # nothing added (no journal, no staging, no tmp)
    for key, data in before.items():
        if key not in gone and key != "participants.tsv":
            assert after[key] == data, key
    assert after["participants.tsv"] == before["participants.tsv"].replace(b"sub-a1\t0\n", b"")
    assert register.records()["a1"].status == "withdrawn"
    assert register.records()["a10"].status == "consented"
    # the audit line: label, date and what was removed, nothing of the data or the name
    audit = [json.loads(line) for line in register.audit_path.read_text().splitlines()]
    assert len(audit) == 1 and audit[0]["participant"] == "a1"
    assert sorted(audit[0]["removed"]) == sorted(entries[0]["removed"])
    assert "Name a1" not in register.audit_path.read_text()
    assert not (dataset / consent.JOURNAL_FILE).exists()
    assert not (dataset / consent.STAGING_DIR).exists()


def test_withdrawal_removes_group_derivatives_that_hold_the_participant(tmp_path):
    """Which participants a group output holds is what the analysis recorded when it wrote
    it (crs_study.dataset.outputs), never a search of the files' text (a label such as a1 is
    part of a10, and a search finds both)."""
    from crs_study.dataset import OutputsRecord

    dataset = make_dataset(tmp_path / "ds")
    group = dataset / "derivatives" / "crs-study" / "report"
    group.mkdir()
    record = OutputsRecord({dataset: ["b2", "a10"]}, group)
    record.begin()
    (group / "results.json").write_text('{"participants": ["b2", "a10"]}')
    (group / "accuracy.png").write_bytes(b"png")
    record.done([group / "results.json", group / "accuracy.png"])
    assert "derivatives/crs-study/report" in consent.participant_paths(dataset, "b2")
    assert "derivatives/crs-study/report" not in consent.participant_paths(dataset, "a1")


def test_withdrawal_removes_a_pipelines_group_outputs_but_not_other_participants(tmp_path):
    """crs-study analyze writes results.json, report.md and figures/ at the pipeline's top;
    they are computed from every participant, so they go; the pipeline's description and the
    other participants' own derivatives stay byte-identical."""
    dataset = make_dataset(tmp_path / "ds")
    pipeline = dataset / "derivatives" / "crs-study"
    (pipeline / "dataset_description.json").write_text('{"DatasetType": "derivative"}')
    (pipeline / "results.json").write_text('{"participants": ["a1", "a10", "b2"]}')
    (pipeline / "report.md").write_text("12 participants")
    (pipeline / "figures").mkdir()
    (pipeline / "figures" / "accuracy.png").write_bytes(b"png")
    paths = consent.participant_paths(dataset, "b2")
    for group in ("results.json", "report.md", "figures"):
        assert f"derivatives/crs-study/{group}" in paths
    assert "derivatives/crs-study/sub-b2" in paths
    assert not any(p.endswith(("dataset_description.json", "sub-a1", "sub-a10")) for p in paths)
    before = snapshot(dataset)
    consent.withdraw("b2", [dataset], tmp_path / "reg")
    after = snapshot(dataset)
    for key in ("derivatives/crs-study/dataset_description.json",
                "derivatives/crs-study/sub-a1/sub-a1_accuracy.tsv"):
        assert after[key] == before[key]


def test_withdrawal_needs_a_dataset_and_skips_nested_ones(tmp_path):
    folder = tmp_path / "folder"
    make_dataset(folder / "copy")
    with pytest.raises(ConsentError, match="not a dataset"):
        consent.withdraw("a1", [folder], tmp_path / "reg")
    assert (folder / "copy" / "sub-a1").exists()
    outer = make_dataset(tmp_path / "outer")
    nested = make_dataset(outer / "sourcedata" / "old")  # another dataset kept inside
    consent.withdraw("a1", [outer], tmp_path / "reg")
    assert not (outer / "sub-a1").exists() and (nested / "sub-a1").exists()
    audit = json.loads(consent.Register(tmp_path / "reg").audit_path.read_text())
    assert audit["participants_tsv_row_removed"] is True


def test_withdrawal_of_an_unknown_label_is_refused(tmp_path):
    """A mistyped label must not 'succeed': no consent record and no data is an error."""
    dataset = make_dataset(tmp_path / "ds")
    before = snapshot(dataset)
    with pytest.raises(ConsentError, match="'zz9' has no consent record.*nothing to withdraw"):
        consent.withdraw("zz9", [dataset], tmp_path / "reg")
    assert snapshot(dataset) == before
    assert not (tmp_path / "reg" / consent.REGISTER_FILE).exists()


def test_withdrawal_marks_the_register_once(tmp_path):
    """A simulated participant has data but no consent record: one withdrawal event."""
    dataset = make_dataset(tmp_path / "ds")
    register = consent.Register(tmp_path / "reg")
    consent.withdraw("a1", [dataset], register.directory)
    consent.withdraw("a1", [dataset], register.directory)  # again: nothing left, still fine
    events = register.events()
    assert [e["event"] for e in events] == ["withdrawal"]


def test_withdraw_cli_needs_a_dataset_or_register_only(tmp_path, capsys):
    reg = str(tmp_path / "reg")
    consent.Register(reg).record(consent.read_form(FORM), "AB", "p1")
    assert main(["consent", "withdraw", "--register", reg, "--participant", "p1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dataset DIR" in err[0] and "--register-only" in err[0]
    assert consent.Register(reg).records()["p1"].status == "consented"
    assert main(["consent", "withdraw", "--register", reg, "--participant", "p1",
                 "--register-only"]) == 0
    assert consent.Register(reg).records()["p1"].status == "withdrawn"


def test_withdraw_cli_names_each_participant_it_finishes(tmp_path, capsys):
    dataset = make_dataset(tmp_path / "ds")
    assert _withdraw_in_subprocess(dataset, tmp_path / "reg", crash_at=2) == -9
    assert main(["consent", "withdraw", "--register", str(tmp_path / "reg"),
                 "--participant", "b2", "--dataset", str(dataset)]) == 0
    out = [line for line in capsys.readouterr().out.splitlines()  # after the lists
           if line.startswith("withdrawn ")]
    assert out[0].startswith("withdrawn a1 from") and out[1].startswith("withdrawn b2 from")


def test_no_session_starts_while_a_withdrawal_is_unfinished(tmp_path, capsys):
    """Killed right after its journal: the participant's data must not come back through a
    session started (or resumed) before the withdrawal is finished."""
    from crs_study.dataset import Dataset, SessionPaths, SessionStore
    from crs_study.errors import SessionError

    dataset = make_dataset(tmp_path / "ds")
    assert _withdraw_in_subprocess(dataset, tmp_path / "reg", crash_at=1) == -9
    before = snapshot(dataset)
    with pytest.raises(SessionError, match="withdrawal was interrupted.*consent recover"):
        SessionStore(SessionPaths(dataset, "a1", 3)).acquire()
    with pytest.raises(SessionError, match="withdrawal was interrupted"):
        Dataset(dataset).register_participant("c3")
    code = main(["run", str(shipped_file("protocols/pilot.toml")), "--participant", "a1",
                 "--session", "3", "--device", "sim://", "--responder", "random",
                 "--out", str(dataset)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "consent recover" in err[0]
    assert snapshot(dataset) == before
    assert main(["consent", "recover", "--dataset", str(dataset)]) == 0
    assert not (dataset / "sub-a1").exists()


def test_the_register_is_marked_before_any_file_moves(tmp_path):
    """Killed after the first file moved: the gate already refuses real sessions."""
    dataset = make_dataset(tmp_path / "ds")
    consent.Register(tmp_path / "reg").record(consent.read_form(FORM), "AB", "a1")
    assert _withdraw_in_subprocess(dataset, tmp_path / "reg", crash_at=2) == -9
    assert consent.pending_withdrawal(dataset) is not None
    with pytest.raises(ConsentError, match="withdrew consent"):
        consent.require_consent(tmp_path / "reg", "a1", "1.0")


def test_withdrawal_refused_while_a_session_runs(tmp_path):
    dataset = make_dataset(tmp_path / "ds")
    lock = dataset / "sub-b2" / "ses-1" / "session.lock"
    with open(lock, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        with pytest.raises(ConsentError, match="is running"):
            consent.withdraw("b2", [dataset], tmp_path / "reg")
    assert (dataset / "sub-b2").exists()


def _withdraw_in_subprocess(dataset: Path, register: Path, crash_at: int | None) -> int:
    env = {**os.environ}
    if crash_at is not None:
        env[consent.CRASH_ENV] = str(crash_at)
    code = (f"from crs_study import consent; "
            f"consent.withdraw('a1', [{str(dataset)!r}], {str(register)!r})")
    return subprocess.run([sys.executable, "-c", code], env=env).returncode


def test_interrupted_withdrawal_recovers_to_a_whole_state(tmp_path):
    """Kill the withdrawal at every checkpoint (SIGKILL, as a power cut); the dataset is then
    either untouched or, after recovery, equal to an uninterrupted withdrawal."""
    reference = make_dataset(tmp_path / "reference")
    consent.withdraw("a1", [reference], tmp_path / "reg-ref")
    whole = snapshot(reference)

    crash_at = 1
    while True:
        dataset = make_dataset(tmp_path / f"ds{crash_at}")
        before = snapshot(dataset)
        code = _withdraw_in_subprocess(dataset, tmp_path / f"reg{crash_at}", crash_at)
        if code == 0:
            break  # no checkpoint left to crash at
        assert code == -9
        journal = consent.pending_withdrawal(dataset)
        if journal is None:
            assert snapshot(dataset) == before or snapshot(dataset) == whole
        if crash_at % 2:
            consent.recover_withdrawal(dataset)
        else:  # the command a lab would type, or the same withdrawal again
            args = (["consent", "recover", "--dataset", str(dataset)] if crash_at % 4 else
                    ["consent", "withdraw", "--participant", "a1", "--dataset", str(dataset),
                     "--register", str(tmp_path / f"reg{crash_at}")])
            assert main(args) == 0
        assert snapshot(dataset) == whole, f"crash at checkpoint {crash_at}"
        audit = consent.Register(tmp_path / f"reg{crash_at}").audit_path.read_text()
        assert len(audit.splitlines()) == 1  # one audit line, however often it was resumed
        crash_at += 1
    assert crash_at > 5  # the loop really crossed the moves and phases


def test_withdraw_cli_one_line_for_missing_dataset(tmp_path, capsys):
    code = main(["consent", "withdraw", "--register", str(tmp_path), "--participant", "p1",
                 "--dataset", str(tmp_path / "nope")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no such dataset" in err[0]


def test_analysis_refuses_a_dataset_with_an_unfinished_withdrawal(tmp_path):
    from crs_study.analysis.load import load_datasets
    from crs_study.errors import DatasetError

    dataset = make_dataset(tmp_path / "ds")
    code = _withdraw_in_subprocess(dataset, tmp_path / "reg", crash_at=2)
    assert code == -9 and consent.pending_withdrawal(dataset) is not None
    with pytest.raises(DatasetError, match="withdrawal was interrupted.*consent recover"):
        load_datasets([dataset])


def test_cli_unwritable_register_is_one_line(tmp_path, capsys):
    """A register path that is a file: one line, exit 2, no traceback."""
    from crs_study.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("")
    form = tmp_path / "form.md"
    form.write_text("# Consent\n\nVersion: 1.0\n\n- [ ] I agree\n")
    assert main(["consent", "record", "--participant", "p01", "--form", str(form),
                 "--experimenter", "AB", "--register", str(blocker / "reg")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "cannot create the consent register" in err


def test_withdrawal_waits_for_the_dataset_lock(tmp_path):
    """participants.tsv is rewritten under the dataset lock a runner takes to add a
    participant; without it the two read-modify-writes could lose a row or bring one back."""
    import threading

    from crs_study.dataset import Dataset

    dataset = make_dataset(tmp_path / "ds")
    done = threading.Event()
    with Dataset(dataset).locked():
        worker = threading.Thread(
            target=lambda: (consent.withdraw("a1", [dataset], tmp_path / "reg"), done.set()))
        worker.start()
        assert not done.wait(0.3)  # blocked on the lock, participants.tsv untouched
        assert "sub-a1\t0\n" in (dataset / "participants.tsv").read_text()
    worker.join(10)
    assert done.is_set() and "sub-a1\t" not in (dataset / "participants.tsv").read_text()


def test_a_register_opened_up_by_hand_is_made_owner_only_again_with_a_warning(tmp_path,
                                                                               capsys):
    register = consent.Register(tmp_path / "reg")
    register.record(consent.read_form(FORM), "AB", "a1", name="Ada Lovelace")
    os.chmod(register.directory, 0o755)
    os.chmod(register.path, 0o644)
    with pytest.warns(CrsStudyWarning, match="readable by others"):
        assert "a1" in register.records()
    assert stat.S_IMODE(os.stat(register.directory).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(register.path).st_mode) == 0o600
    os.chmod(register.path, 0o640)  # the command line says so in one line per file
    with warnings.catch_warnings():
        warnings.simplefilter("always", CrsStudyWarning)  # as outside pytest's "error"
        assert main(["consent", "list", "--register", str(register.directory)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("crs-study consent: warning: ")
    assert stat.S_IMODE(os.stat(register.path).st_mode) == 0o600


def test_temporaries_left_by_a_kill_inside_an_atomic_write_are_removed(tmp_path):
    # A SIGKILL between write_atomically's temporary file and its rename leaves
    # '.<name>.tmp' beside the file; the journal's copy names the participant.
    reference = make_dataset(tmp_path / "reference")
    consent.withdraw("a1", [reference], tmp_path / "reg-ref")
    whole = snapshot(reference)

    dataset = make_dataset(tmp_path / "ds")
    stale = [dataset / f".{consent.JOURNAL_FILE}.tmp", dataset / ".participants.tsv.tmp"]
    for path in stale:
        path.write_text('{"participant": "a1"}')
    assert consent.recover_withdrawal(dataset) is None  # nothing pending: only the debris goes
    assert not any(path.exists() for path in stale)
    for path in stale:
        path.write_text('{"participant": "a1"}')
    consent.withdraw("a1", [dataset], tmp_path / "reg")
    assert snapshot(dataset) == whole


def test_recover_on_a_mistyped_dataset_path_creates_nothing(tmp_path, capsys):
    missing = tmp_path / "typo" / "study"
    assert main(["consent", "recover", "--dataset", str(missing)]) == 2
    assert "no such dataset" in capsys.readouterr().err and not (tmp_path / "typo").exists()
