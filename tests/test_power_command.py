"""``crs-study power`` as a user meets it: one line, two files, a progress bar; bad input is
one line naming the option, with nothing written."""

from __future__ import annotations

import json

import pytest
from _session_helpers import tiny_protocol

from crs_study.analysis.synthetic import SyntheticSpec, write_dataset
from crs_study.cli import main
from crs_study.paths import shipped_file
from crs_study.power_analysis import backends


@pytest.fixture(scope="module")
def protocol(tmp_path_factory):
    """The tiny protocol with the pilot's plan reduced to random intercepts: these tests are
    about the command's output, and the maximal model's fits of two participants' six trials
    (variances the data cannot bound) cost seconds a study."""
    folder = tmp_path_factory.mktemp("protocol")
    path = tiny_protocol(folder, digits=(1, 4, 7))
    plan = shipped_file("analysis/pilot.toml").read_text(encoding="utf-8")
    (folder / "plan.toml").write_text(plan.replace('structure = "maximal"',
                                                   'structure = "intercepts"'))
    path.write_text(path.read_text().replace('analysis_plan = "analysis/pilot.toml"',
                                             'analysis_plan = "plan.toml"'))
    return path


def _args(protocol, out, *extra):
    return ["power", str(protocol), "--draws", "4", "--studies", "20", "--participants",
            "2:4:2", "--jobs", "1", "--out", str(out), *extra]


def test_the_answer_in_one_line_the_json_and_the_chart(protocol, tmp_path, capsys):
    out = tmp_path / "result"
    assert main(_args(protocol, out, "--studies", "120")) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0].startswith(("80 % power at N = ", "80 % power not reached by N = 4"))
    assert "120 studies per point" in lines[0]
    assert lines[1:] == [f"results: {out / 'power.json'}", f"chart:   {out / 'power.png'}"]
    data = json.loads((out / "power.json").read_text())
    assert data["headline"] == lines[0] and data["model"]["source"] == "observer"
    assert [p["participants"] for p in data["points"]] == [2, 4]
    assert (out / "power.png").read_bytes()[:4] == b"\x89PNG"
    progress = [line for line in captured.err.splitlines() if line.startswith("[")]
    assert progress[-1].startswith("[" + "#" * 30 + "] 100 %  120/120 studies")
    assert len(progress) == 5 and "s left" in progress[0]   # a line per task: 4 x 25 and 20
    assert captured.err.startswith("predicting the simulated observer's accuracy of 6 "
                                   "stimuli (4 noise draws each)")


def test_json_on_stdout_and_no_progress(protocol, tmp_path, capsys):
    assert main(_args(protocol, tmp_path / "r", "--json")) == 0
    captured = capsys.readouterr()
    data = json.loads(captured.out)
    assert data["studies_per_point"] == 20 and data["seed"] == 20260116
    assert captured.err == ""


@pytest.mark.parametrize("extra, message", [
    pytest.param(["--participants", "1:4"], "--participants: expected at least 2 "
                 "participants (the participant variance needs two), got 1", id="N-below-2"),
    pytest.param(["--participants", "x:y"], "--participants: expected N, A:B or A:B:STEP "
                 "with whole numbers (e.g. 4:40:4), got 'x:y'", id="non-numeric-range"),
    pytest.param(["--participants", "8:4"], "--participants: expected A:B:STEP with A <= B "
                 "and STEP >= 1, got '8:4'", id="reversed-range"),
    pytest.param(["--repetitions", "0:2"], "--repetitions: expected values of at least 1, "
                 "got 0", id="no-repetitions"),
    pytest.param(["--studies", "many"], "--studies: expected a whole number, got 'many'",
                 id="studies"),
    pytest.param(["--target", "80"], "--target: expected a power between 0 and 1 (e.g. "
                 "0.8), got 80.0", id="target"),
    pytest.param(["--effect-scale", "-1"], "--effect-scale: expected at least 0, got '-1'",
                 id="effect-scale"),
    pytest.param(["--fidelity", "exact"], "--fidelity: expected one of model, full, got "
                 "'exact'", id="fidelity"),
    pytest.param(["--fidelity", "full", "--repetitions", "2"], "--repetitions: --fidelity "
                 "full runs the protocol as written (1 repetitions)", id="full-repetitions"),
    pytest.param(["--scheduler", "nowhere"], "--scheduler: expected a Dask scheduler "
                 "address such as tcp://HOST:8786, got 'nowhere'", id="scheduler"),
    pytest.param(["--pilot", "no-such-dataset"], "--pilot: no-such-dataset is not a "
                 "dataset folder", id="pilot-missing"),
])
def test_bad_input_is_one_line_naming_the_option_and_nothing_is_written(
        protocol, tmp_path, capsys, extra, message):
    out = tmp_path / "never"
    assert main(_args(protocol, out, *extra)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"crs-study power: error: {message}")
    assert not out.exists()


def test_a_pilot_without_both_conditions_writes_nothing(protocol, tmp_path, capsys):
    pilot = write_dataset(tmp_path / "pilot", SyntheticSpec(
        n_participants=2, repetitions=1, digits=(1, 4, 7), accuracy={"crs": 0.6}))
    out = tmp_path / "never"
    assert main(_args(protocol, out, "--pilot", str(pilot))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--pilot" in err[0] and "['pixel-only']" in err[0]
    assert not out.exists()


def test_an_unreachable_scheduler_writes_nothing(protocol, tmp_path, capsys, monkeypatch):
    import socket


    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    monkeypatch.setattr(backends, "CONNECT_TIMEOUT", 2.0)
    out = tmp_path / "never"
    assert main(_args(protocol, out, "--scheduler", f"tcp://127.0.0.1:{port}")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--scheduler tcp://127.0.0.1:{port}: cannot reach" in err[0]
    assert not out.exists()


# --- outputs that do not mislead: the range follows the effect, nothing is overwritten -----

#: The pilot's plan with random intercepts and the chi-square LR: cheap studies (no
#: bootstrap reference, no slopes), for what these tests show.
CHI2_PLAN = """
[plan]
name = "chi2"
conditions = ["pixel-only", "crs"]
[primary]
random_effects = ["participant"]
structure = "intercepts"
p_value = "chi2"
"""


@pytest.fixture(scope="module")
def chi2_plan(tmp_path_factory):
    path = tmp_path_factory.mktemp("plan") / "chi2.toml"
    path.write_text(CHI2_PLAN)
    return path


def test_the_default_range_is_chosen_from_the_effect_so_the_curve_crosses_the_target(
        protocol, chi2_plan, monkeypatch):
    """No participants given: a coarse search picks the counts from the effect (the fixed
    4:40:4 was flat at 100 % for the shipped protocol: "N = 4 or fewer"); a smaller effect
    moves the range to larger N, and the search's N lies inside the range. (A coarser
    search than the command's, to keep the test short.)"""
    from crs_study.power_analysis import api
    from crs_study.power_analysis.backends import open_backend
    from crs_study.power_analysis.model import model_from_parameters
    from crs_study.power_analysis.protocol_design import design_from_protocol

    monkeypatch.setattr(api, "SEARCH_STUDIES", 20)
    monkeypatch.setattr(api, "SEARCH_MAX", 128)
    design = design_from_protocol(protocol, chi2_plan)
    found = {}
    with open_backend(1) as backend:
        for name, crs in (("large", 0.95), ("small", 0.75)):
            model = model_from_parameters(design, {"pixel-only": 0.5, "crs": crs},
                                          participant_sd=0.3)
            counts, note = api.auto_range(design, model, 1, (1,), 0.8, backend)
            assert "chosen from the effect" in note and counts == tuple(sorted(counts))
            assert len(counts) >= 5
            n = int(note.split("near N = ")[1].split(" ")[0])
            assert counts[0] <= n <= counts[-1] and (counts[0] < n or counts[0] == 2)
            found[name] = n
    assert found["small"] > found["large"]


def test_the_command_uses_the_chosen_range_and_the_chart_states_the_effect(
        protocol, chi2_plan, tmp_path, monkeypatch):
    from crs_study.power_analysis import api

    monkeypatch.setattr(api, "SEARCH_STUDIES", 4)
    monkeypatch.setattr(api, "SEARCH_MAX", 8)
    out = tmp_path / "auto"
    assert main(["power", str(protocol), "--draws", "2", "--studies", "2", "--jobs", "1",
                 "--plan", str(chi2_plan), "--effect-scale", "0.7", "--out", str(out)]) == 0
    data = json.loads((out / "power.json").read_text())
    assert any(n.startswith("participant range") for n in data["notes"])
    assert len(data["points"]) >= 5
    result = api.power(protocol, participants="2", studies=2, draws=2, effect_scale=0.7,
                       plan=chi2_plan)
    title = " ".join(result.plot().get_title().split())
    assert "odds ratio crs / pixel-only" in title and "--effect-scale 0.7" in title
    assert "typical participant: pixel-only" in title
    assert repr(result).startswith("<PowerResult of ") and "\n" not in repr(result)
    assert "--effect-scale 0.7" in result._repr_html_()
    assert result.plot()._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"     # shows in a notebook


def test_a_second_run_does_not_overwrite_the_first(protocol, chi2_plan, tmp_path, capsys,
                                                   monkeypatch):
    monkeypatch.chdir(tmp_path)
    base = ["power", str(protocol), "--draws", "2", "--studies", "2", "--participants",
            "2", "--jobs", "1", "--plan", str(chi2_plan)]
    stem = protocol.stem
    assert main(base) == 0
    first = (tmp_path / f"power_{stem}" / "power.json").read_bytes()
    assert main([*base, "--seed", "7"]) == 0
    out = capsys.readouterr().out
    assert f"results: power_{stem}-2/power.json" in out
    assert (tmp_path / f"power_{stem}" / "power.json").read_bytes() == first
    assert main([*base, "--out", f"power_{stem}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds an earlier run's power.json" in err[0]
    assert (tmp_path / f"power_{stem}" / "power.json").read_bytes() == first
