"""No traceback anywhere: hostile values in every kind of input file, and in the command line's
numeric options, end in exit 0 (a value that happens to be valid) or exit 2 with exactly one
line on stderr naming the file, key or option; never a traceback, never a hang (each case
runs under a time bound).

The kinds: a protocol and its ``[adaptive]`` tables, a device file, a strokes file, a
stimulus-set file, an analysis plan, a dataset's trial TSV and JSON sidecar (and a dataset
that is a symbolic link loop), the consent register, a live recording replayed by
``live-send``, the numeric options of every command (power and live included) and Dask
``--scheduler`` addresses. The values are the ones that broke a first day: subnormal and huge
floats (1e-310, 1e-320, 1e308), integers beyond int64, 256-character and longer strings,
nesting deeper than Python's recursion limit, and their neighbours (NaN, infinities, empty
strings, NUL). Hypothesis draws which key gets which value; a key's value is replaced on its
line, in its table, so the rest of the file stays valid.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
import signal
import tomllib
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.cli import main
from crs_study.errors import CrsStudyError
from crs_study.paths import shipped_file

#: The longest a single case may take (a hang is a failure, not a stuck suite).
CASE_LIMIT_S = 30
#: An --out that cannot be made (a folder in /proc): power refuses it before any work.
UNWRITABLE = "/proc/crs-fuzz/out"
SETTINGS = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])


def deep(opening: str, closing: str, depth: int) -> str:
    return opening * depth + closing * depth


#: Hostile TOML values (as TOML text).
TOML_VALUES = st.one_of(
    st.sampled_from(["1e-310", "1e-300", "1e-320", "5e-324", "1e308", "-1e308", "nan", "inf",
                     "-inf", "-0.0", "0", "-1", "99999999999999999999", "9223372036854775807",
                     "-9223372036854775808", "true", '""', '"\\u0000"', '"a\\nb"', "[]",
                     "{}", '"/"', '"."', '"' + "x" * 256 + '"', '"' + "y/" * 3000 + '"',
                     "[1, 2]", '["a"]', "{a = 1}"]),
    st.integers(50, 5000).map(lambda d: deep("[", "]", d)),
    st.integers(50, 3000).map(lambda d: "{a=" * d + "1" + "}" * d),
)


def timed(call):
    """Run ``call`` under :data:`CASE_LIMIT_S` (SIGALRM: the test's own thread)."""
    def expired(signum, frame):
        raise TimeoutError(f"a case took more than {CASE_LIMIT_S} s")
    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(CASE_LIMIT_S)
    try:
        return call()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def cli(argv: list[str]) -> tuple[int, str]:
    """``crs-study ARGV`` in this process: (exit code, stderr); stdout is dropped."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), \
            warnings.catch_warnings():
        warnings.simplefilter("default")  # shown as the command shows them, not raised
        try:
            code = timed(lambda: main(argv))
        except SystemExit as exit_:  # argparse's refusal of an option
            code = exit_.code
    return code, err.getvalue()


def assert_clean(code: int, err: str, case: object) -> None:
    assert "Traceback" not in err, (case, err)
    assert code in (0, 2), (case, code, err)
    if code == 2:
        lines = err.strip().splitlines()
        errors = [line for line in lines if ": error: " in line]
        if len(errors) > 1:  # validate lists every error it finds, then counts them
            assert re.fullmatch(rf"crs-study validate: {len(errors)} errors in .*", lines[-1]) \
                and lines[-len(errors) - 1:-1] == errors, (case, err)
        else:
            assert len(errors) == 1 and lines[-1] == errors[0], (case, err)
        assert all(len(e) < 2000 for e in errors), (case, errors[0][:300])


def value_lines(text: str) -> list[tuple[int, str, str]]:
    """(line index, table, key) of every ``key = value`` line whose value stands alone."""
    found, table = [], ""
    for i, line in enumerate(text.splitlines()):
        header = re.match(r"^\s*\[+([^\]]+)\]+", line)
        if header:
            table = header.group(1).strip()
            continue
        match = re.match(r"^\s*([A-Za-z0-9_\-]+)\s*=\s*(.*)$", line)
        if not match:
            continue
        try:
            tomllib.loads(f"x = {match.group(2)}")
        except tomllib.TOMLDecodeError:
            continue
        found.append((i, table, match.group(1)))
    return found


def replaced(text: str, index: int, value: str) -> str:
    lines = text.splitlines()
    key = lines[index].split("=", 1)[0]
    lines[index] = f"{key}= {value}"
    return "\n".join(lines) + "\n"


PROTOCOL = shipped_file("protocols/pilot.toml").read_text(encoding="utf-8")
DEVICE = shipped_file("devices/crs2d.toml").read_text(encoding="utf-8")
STROKES = shipped_file("digits.toml").read_text(encoding="utf-8")
PLAN = shipped_file("analysis/digit_identification.toml").read_text(encoding="utf-8")
PROTOCOL_WITH_STROKES = PROTOCOL.replace("[stimulus]\n", '[stimulus]\nstrokes_file = '
                                         '"digits.toml"\n', 1)


def fresh(tmp_path: Path, name: str) -> Path:
    folder = tmp_path / name
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    return folder


@SETTINGS
@given(line=st.sampled_from(value_lines(PROTOCOL)), value=TOML_VALUES)
def test_protocol_values(tmp_path, line, value):
    folder = fresh(tmp_path, "p")
    (folder / "p.toml").write_text(replaced(PROTOCOL, line[0], value), encoding="utf-8")
    assert_clean(*cli(["validate", str(folder / "p.toml")]), (line, value))


@SETTINGS
@given(line=st.sampled_from(value_lines(DEVICE)), value=TOML_VALUES)
def test_device_file_values(tmp_path, line, value):
    folder = fresh(tmp_path, "d")
    (folder / "d.toml").write_text(replaced(DEVICE, line[0], value), encoding="utf-8")
    assert_clean(*cli(["device", "check", "--device", "sim://", "--layout",
                       str(folder / "d.toml")]), (line, value))


@SETTINGS
@given(line=st.sampled_from(value_lines(STROKES)), value=TOML_VALUES)
def test_strokes_file_values(tmp_path, line, value):
    folder = fresh(tmp_path, "s")
    (folder / "digits.toml").write_text(replaced(STROKES, line[0], value), encoding="utf-8")
    (folder / "p.toml").write_text(PROTOCOL_WITH_STROKES, encoding="utf-8")
    assert_clean(*cli(["validate", str(folder / "p.toml")]), (line, value))


@SETTINGS
@given(line=st.sampled_from(value_lines(PLAN)), value=TOML_VALUES)
def test_analysis_plan_values(tmp_path, line, value):
    from crs_study.analysis.plan import load_plan

    folder = fresh(tmp_path, "a")
    (folder / "plan.toml").write_text(replaced(PLAN, line[0], value), encoding="utf-8")
    try:
        timed(lambda: load_plan(folder / "plan.toml"))
    except CrsStudyError as error:
        assert "\n" not in str(error) and "plan.toml" in str(error), (line, value, error)


@pytest.mark.parametrize("kind", ["protocol", "device", "strokes", "plan"])
def test_nesting_deeper_than_the_recursion_limit_is_one_line(dataset, tmp_path, kind):
    nested = "x = " + deep("[", "]", 100_000) + "\n"
    if kind == "plan":
        (tmp_path / "plan.toml").write_text(nested)
        code, err = cli(["analyze", str(dataset), "--plan", str(tmp_path / "plan.toml"),
                         "--out", str(tmp_path / "out")])
    elif kind == "strokes":
        (tmp_path / "digits.toml").write_text(nested)
        (tmp_path / "p.toml").write_text(PROTOCOL_WITH_STROKES)
        code, err = cli(["validate", str(tmp_path / "p.toml")])
    elif kind == "device":
        (tmp_path / "d.toml").write_text(nested)
        code, err = cli(["device", "check", "--device", "sim://", "--layout",
                         str(tmp_path / "d.toml")])
    else:
        (tmp_path / "p.toml").write_text(nested)
        code, err = cli(["validate", str(tmp_path / "p.toml")])
    assert code == 2 and "nested too deeply" in err, err
    assert_clean(code, err, kind)


# --- the dataset: trial TSV cells and sidecar values ---------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "base"
    code, err = cli(["dry-run", "pilot", "--participants", "2", "--out", str(out)])
    assert code == 0, err
    return out


def session_files(root: Path) -> tuple[Path, Path]:
    beh = root / "sub-sim01" / "ses-1" / "beh"
    stem = "sub-sim01_ses-1_task-digitid_beh"
    return beh / f"{stem}.tsv", beh / f"{stem}.json"


CELLS = st.sampled_from(["1e308", "99999999999999999999", "-1", "1e-320", "nan", "inf", "",
                         "n/a", "x" * 300, "0x10", "1_000", "-0", "\x00", "3.5"])
JSON_VALUES = st.one_of(
    st.sampled_from([5, -1, 1e308, 10**30, None, True, "", "x" * 5000, [], {}, [1, "a"],
                     {"a": {"b": 1}}]),
    st.integers(50, 3000).map(lambda d: json.loads(deep("[", "]", d))),
)


def load_clean(root: Path, case: object) -> None:
    import crs_study

    try:
        timed(lambda: crs_study.load_dataset(root))
    except CrsStudyError as error:
        assert "\n" not in str(error), (case, error)


@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(row=st.integers(0, 5), column=st.integers(0, 18), value=CELLS)
def test_trial_tsv_cells(dataset, tmp_path, row, column, value):
    root = fresh(tmp_path, "t") / "ds"
    shutil.copytree(dataset, root)
    tsv, _ = session_files(root)
    lines = tsv.read_text(encoding="utf-8").split("\n")
    cells = lines[row + 1].split("\t")
    cells[column % len(cells)] = value
    lines[row + 1] = "\t".join(cells)
    tsv.write_text("\n".join(lines), encoding="utf-8")
    load_clean(root, (row, column, value))


@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(key=st.sampled_from(["Protocol", "ProtocolSha256", "Seed", "Participant", "Session",
                            "Status", "TrialsCompleted", "TrialsPlanned", "Faults", "Resumes",
                            "TaskName", "Responder", "DeviceFile", "StartTime"]),
       value=JSON_VALUES)
def test_sidecar_values(dataset, tmp_path, key, value):
    root = fresh(tmp_path, "j") / "ds"
    shutil.copytree(dataset, root)
    _, sidecar = session_files(root)
    data = json.loads(sidecar.read_text(encoding="utf-8"))
    data[key] = value
    sidecar.write_text(json.dumps(data), encoding="utf-8")
    load_clean(root, (key, value))


@pytest.mark.parametrize("case", ["cell 1e308", "cell big int", "Protocol a number",
                                  "deep sidecar", "symlink loop", "dataset a symlink loop"])
def test_the_issues_dataset_cases_from_the_command_line(dataset, tmp_path, case):
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    tsv, sidecar = session_files(root)
    if case.startswith("cell"):
        lines = tsv.read_text().split("\n")
        cells = lines[1].split("\t")
        cells[2] = "1e308" if case == "cell 1e308" else "99999999999999999999"  # block
        lines[1] = "\t".join(cells)
        tsv.write_text("\n".join(lines))
    elif case == "Protocol a number":
        data = json.loads(sidecar.read_text())
        data["Protocol"] = 5
        sidecar.write_text(json.dumps(data))
    elif case == "deep sidecar":
        sidecar.write_text(deep("[", "]", 100_000))
    elif case == "symlink loop":
        tsv.unlink()
        tsv.symlink_to(tsv.name)  # a link to itself
    else:
        root = tmp_path / "loop"
        root.symlink_to(root.name)  # the dataset given is a link to itself
    code, err = cli(["analyze", str(root), "--out", str(tmp_path / "out")])
    assert_clean(code, err, case)
    if case.startswith("cell"):
        assert code == 2 and "column 'block'" in err and tsv.name in err


# --- the consent register ------------------------------------------------------------------

REGISTER_LINES = st.one_of(
    st.sampled_from(["{}", "[]", "5", "null", '"x"', "{", "not json", "\x00",
                     deep("[", "]", 100_000)]),
    st.fixed_dictionaries({"event": st.sampled_from(["consent", "withdrawal", "other", 5])},
                          optional={k: st.one_of(st.text(max_size=5), st.integers(), st.none())
                                    for k in ("participant", "time", "form_path",
                                              "form_version", "form_sha256",
                                              "experimenter")}).map(json.dumps),
)


@SETTINGS
@given(line=REGISTER_LINES)
def test_consent_register_lines(tmp_path, monkeypatch, line):
    folder = fresh(tmp_path, "r")
    folder.chmod(0o700)
    (folder / "register.jsonl").write_text(line + "\n", encoding="utf-8")
    (folder / "register.jsonl").chmod(0o600)
    assert_clean(*cli(["consent", "list", "--consent-register", str(folder)]), line[:80])


# --- the command line's numeric options ----------------------------------------------------

# a valid value runs the command in full: "0_1" (an underscore Python's int and float accept)
# and "0.25" (a fraction) are valid for a duration or a count yet short as one, where 1_000
# or 2.5 would keep a live session or a sweep running for minutes or seconds
NUMBERS = st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e308", "99999999999999999999",
                           "1e-320", "-0", "", "0x10", "0_1", "1e400", "0.25"])
OPTIONS = [
    (["dry-run", "pilot", "--out", "{tmp}/o"], "--participants"),
    (["dry-run", "pilot", "--out", "{tmp}/o", "--participants", "1"], "--session"),
    (["dry-run", "pilot", "--out", "{tmp}/o", "--participants", "1"], "--counterbalance"),
    (["run", "pilot", "--participant", "sim1", "--device", "sim://", "--out", "{tmp}/o",
      "--responder", "random"], "--session"),
    (["run", "pilot", "--participant", "sim1", "--device", "sim://", "--out", "{tmp}/o",
      "--responder", "random"], "--counterbalance"),
    (["device", "sweep", "--device", "sim://", "--layout", "crs1d", "--channel", "A:1"],
     "--seconds"),
    (["device", "sweep", "--device", "sim://", "--layout", "crs1d", "--channel", "A:1",
      "--seconds", "0.2"], "--frame-rate"),
    (["device", "check", "--device", "sim://", "--layout", "crs1d"], "--deadband-us"),
    (["device", "check", "--device", "sim://", "--layout", "crs1d"], "--refresh-s"),
    (["device", "monitor", "--port", "loop://", "--max-frames", "1"], "--seconds"),
    (["device", "monitor", "--port", "loop://", "--seconds", "0.1"], "--max-frames"),
    (["device", "monitor", "--port", "loop://", "--seconds", "0.1"], "--baud"),
    (["device", "boards", "--layout", "crs1d", "--quiet", "--seconds", "0.1"], "--baud"),
    (["device", "boards", "--layout", "crs1d", "--quiet"], "--seconds"),
    # power: a valid value ends at --out, which cannot be made (tried before any work)
    *[(["power", "pilot", "--studies", "2", "--participants", "2", "--out", UNWRITABLE], name)
      for name in ("--participants", "--repetitions", "--studies", "--jobs", "--draws",
                   "--target", "--seed", "--effect-scale", "--participant-sd",
                   "--participant-slope-sd")],
    # live: a session of 0.3 s on the simulated device when the value is valid
    *[(["live", "--device", "sim://", "--listen", "127.0.0.1:0", "--no-view", "--seconds",
        "0.3"], name)
      for name in ("--diameter-mm", "--max-height-mm", "--area-margin-mm", "--silence-s",
                   "--move-ms", "--max-packets", "--seconds")],
    # live-send: a short hold to a port nobody listens on when the value is valid
    *[(["live-send", "--hold", "--seconds", "0.2", "--to", "127.0.0.1:9"], name)
      for name in ("--rate", "--seconds", "--jitter-mm", "--repeat", "--press-mm", "--seed")],
]


@pytest.mark.slow
@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(option=st.sampled_from(OPTIONS), value=NUMBERS)
def test_numeric_options(tmp_path, monkeypatch, option, value):
    folder = fresh(tmp_path, "n")
    monkeypatch.chdir(folder)
    argv, name = option
    argv = [a.replace("{tmp}", str(folder)) for a in argv] + [f"{name}={value}"]
    assert_clean(*cli(argv), argv)


# --- [adaptive] tables, stimulus-set files ---------------------------------------------------

ADAPTIVE = shipped_file("protocols/digit_size_adaptive.toml").read_text(encoding="utf-8")
LETTERS = shipped_file("letters.toml").read_text(encoding="utf-8")
LETTER_PROTOCOL = shipped_file("protocols/letter_identification.toml").read_text(
    encoding="utf-8").replace('set = "letters"', 'set = "set.toml"', 1)


def load_clean_protocol(path: Path, case: object) -> None:
    """The protocol loads, or its error is one line naming the file (the loader that
    validate and dry-run run first, without the device checks of every level)."""
    from crs_study.protocol import load_protocol

    try:
        timed(lambda: load_protocol(path, check_device=False))
    except CrsStudyError as error:
        assert "\n" not in str(error) and path.name in str(error), (case, error)


@SETTINGS
@given(line=st.sampled_from([v for v in value_lines(ADAPTIVE) if v[1].startswith("adaptive")]),
       value=TOML_VALUES)
def test_adaptive_table_values(tmp_path, line, value):
    folder = fresh(tmp_path, "ad")
    (folder / "p.toml").write_text(replaced(ADAPTIVE, line[0], value), encoding="utf-8")
    load_clean_protocol(folder / "p.toml", (line, value))


@pytest.mark.parametrize("value", ['"0.6"', "[0.6]", "{a = 0.6}", "true"])
def test_width_to_height_of_a_wrong_type_is_one_line_from_validate(tmp_path, value):
    text = re.sub(r"(?m)^width_to_height = .*$", f"width_to_height = {value}", ADAPTIVE)
    (tmp_path / "p.toml").write_text(text, encoding="utf-8")
    code, err = cli(["validate", str(tmp_path / "p.toml")])
    assert_clean(code, err, value)
    assert code == 2 and "adaptive.width_to_height: expected a number" in err, err


@SETTINGS
@given(line=st.sampled_from(value_lines(LETTERS)), value=TOML_VALUES)
def test_stimulus_set_file_values(tmp_path, line, value):
    folder = fresh(tmp_path, "set")
    (folder / "set.toml").write_text(replaced(LETTERS, line[0], value), encoding="utf-8")
    (folder / "p.toml").write_text(LETTER_PROTOCOL, encoding="utf-8")
    load_clean_protocol(folder / "p.toml", (line, value))


# --- a live recording replayed by live-send ---------------------------------------------------

HEADER = {"format": "crs-study live recording", "version": 1, "layout": "crs2d",
          "condition": "crs", "device": "sim://", "listen": "127.0.0.1:5005",
          "started": "2026-01-01T00:00:00+00:00", "config": {}}
PACKET_VALUES = st.one_of(
    st.sampled_from([1e308, -1e308, 1e-320, 10**30, -1, 0, 1e9, "x", None, True, [], {},
                     "nan", 5.0]),
    st.integers(50, 900).map(lambda d: json.loads(deep("[", "]", d))),
)


def packet(at: float, **values) -> str:
    fields = {"t": at, "read": at, "from": "127.0.0.1:1", "status": "accepted", "stream": 1,
              "seq": int(at * 100), "sender_time": at, "x": 0.0, "y": 0.0, "z": 1.0, **values}
    return json.dumps({"packet": fields})


@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(key=st.sampled_from(["t", "x", "y", "z"]), value=PACKET_VALUES,
       row=st.integers(0, 2))
def test_live_recording_values(tmp_path, key, value, row):
    folder = fresh(tmp_path, "rec")
    lines = [json.dumps(HEADER)] + [packet(0.01 * k, **({key: value} if k == row else {}))
                                    for k in range(3)]
    (folder / "r.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert_clean(*cli(["live-send", "--replay", str(folder / "r.jsonl"), "--to",
                       "127.0.0.1:9"]), (key, value, row))


@pytest.mark.parametrize("line", ["not json", deep("[", "]", 100_000), "5", "{}",
                                  '{"packet": 5}', "\x00"])
def test_live_recording_lines(tmp_path, line):
    lines = [json.dumps(HEADER), packet(0.0), line, packet(0.01)]
    (tmp_path / "r.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert_clean(*cli(["live-send", "--replay", str(tmp_path / "r.jsonl"), "--to",
                       "127.0.0.1:9"]), line[:40])


# --- Dask scheduler addresses -----------------------------------------------------------------

ADDRESSES = st.one_of(
    st.sampled_from(["", "tcp://", "tcp://:1", "tcp://h:0", "tcp://h:-1", "tcp://h:99999",
                     "tcp://[::1", "tcp://a:b", "tls://127.0.0.1:1", "ucx://127.0.0.1:1",
                     "inproc://x", "http://127.0.0.1:1", "/tmp/scheduler", "\x00",
                     "tcp://" + "a" * 300 + ":1", "tcp://127.0.0.1:1" + "0" * 300,
                     "tcp://h:1e308", "tcp://h:99999999999999999999"]),
    st.text(max_size=40).map(lambda text: "tcp://" + text),
)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(address=ADDRESSES)
def test_scheduler_addresses(tmp_path, monkeypatch, address):
    from crs_study.power_analysis import backends

    monkeypatch.setattr(backends, "CONNECT_TIMEOUT", 1.0)  # an address that parses: 1 s
    folder = fresh(tmp_path, "s")
    code, err = cli(["power", "pilot", "--studies", "2", "--participants", "2",
                     "--scheduler", address, "--out", str(folder / "never")])
    assert_clean(code, err, address)
    assert code == 2 and not (folder / "never").exists(), (address, err)
