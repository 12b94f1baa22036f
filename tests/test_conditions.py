"""Display conditions as objects: what a condition means comes from the registry alone.

The acceptance case registers a third condition in the test only (not shipped): the paper's
"linear connection" display (Zhang et al., "Continuity reinforcement skeleton for pixel-based
haptic display", Nature Communications 2024, Fig. 2d: straight connections between the pixel
tips, as in origami-like displays), which exists only on the simulated device. Registered
before the command line starts, it goes through ``validate``, ``dry-run`` and ``analyze`` as
real ``crs-study`` processes with nothing else changed.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crs_study.errors import RenderError
from crs_study.geometry.layout import load_layout
from crs_study.paths import shipped_file
from crs_study.rendering import CONDITIONS, Condition, Renderer, get_condition
from crs_study.rendering.render import render_pixel_only
from crs_study.stimuli.targets import Bump
from tests._session_helpers import tiny_protocol

THIRD = "linear-connection"

#: A crs-study process with the third condition registered first (the test's registry entry).
LAUNCHER = f"""
import sys
from crs_study.cli import main
from crs_study.rendering import Condition, register_condition
from crs_study.rendering.render import render_pixel_only

register_condition(Condition(
    {THIRD!r}, render_pixel_only, drives_beams=False, display_model="linear", fast_path=True,
    description="straight connections between the pixel tips (simulated device only)"))
sys.exit(main(sys.argv[1:]))
"""


def test_shipped_conditions_say_what_they_mean():
    pixels, crs = get_condition("pixel-only"), get_condition("crs")
    assert (pixels.drives_beams, pixels.display_model, pixels.benefit_side) == \
        (False, "linear", -1.0)
    assert (crs.drives_beams, crs.display_model, crs.benefit_side) == (True, "beam", 1.0)
    assert "mount the skeleton" in crs.setup_prompt
    assert "remove the skeleton" in pixels.setup_prompt


@pytest.mark.parametrize("changes, message", [
    pytest.param({"name": "two words"}, r"without whitespace, got 'two words'", id="name"),
    pytest.param({"name": ""}, r"non-empty string", id="empty"),
    pytest.param({"render": 3}, r"render must be callable, got 3", id="render"),
    pytest.param({"display_model": "lnear"}, r"unknown display model 'lnear'; known: .*linear",
                 id="model"),
])
def test_a_malformed_condition_is_a_one_line_error(changes, message):
    with pytest.raises(RenderError, match=message):
        replace(get_condition("pixel-only"), **changes)


def test_unknown_condition_names_the_known_ones():
    with pytest.raises(RenderError, match=r"unknown condition 'crss'; known: crs, pixel-only"):
        get_condition("crss")


def test_the_fast_path_follows_the_condition(layout2d, monkeypatch):
    """A registered condition on the pixels alone with a fast path renders a bump as the
    general path does (pixels sampled, every boundary servo at 0)."""
    monkeypatch.setitem(CONDITIONS, THIRD, Condition(THIRD, render_pixel_only, False, "linear",
                                                     fast_path=True))
    bump = Bump((3.0, -2.0), 90.0, 5.0)
    fast = Renderer(layout2d, THIRD).render(bump).setpoints
    general = Renderer(layout2d, THIRD).limit(render_pixel_only(layout2d, bump)).setpoints
    np.testing.assert_allclose(fast, general, atol=1e-10)
    assert not fast[layout2d.n_pixels:].any()


def _protocol(tmp_path: Path) -> Path:
    """The tiny pilot with three conditions in a Latin square, its plan beside it."""
    path = tiny_protocol(tmp_path, digits=(1, 4, 7), practice=0)
    text = path.read_text(encoding="utf-8")
    text = re.sub(r'(?m)^names = .*', f'names = ["pixel-only", "crs", "{THIRD}"]', text)
    text = re.sub(r'(?m)^counterbalancing = .*', 'counterbalancing = "latin"', text)
    text = text.replace('analysis_plan = "analysis/pilot.toml"', 'analysis_plan = "three.toml"')
    text = re.sub(r'(?m)^crs = "CRS block.*$', r'\g<0>\n' + f'{THIRD} = "Linear-connection '
                  'block: the simulated device shows straight connections"', text)
    path.write_text(text, encoding="utf-8")
    plan = shipped_file("analysis/pilot.toml").read_text(encoding="utf-8")
    plan, n = re.subn(r'(?m)^conditions = .*$',
                      f'conditions = ["pixel-only", "crs", "{THIRD}"]', plan)
    assert n == 1 and 'p_value = "chi2"' in plan and 'reference = "pixel-only"' in plan
    # kept fast: random intercepts, a short confusion bootstrap (seconds, not a minute)
    plan = re.sub(r'(?m)^structure = .*$', 'structure = "intercepts"', plan)
    plan = re.sub(r'(?m)^bootstrap = \d+', 'bootstrap = 100', plan)
    (tmp_path / "three.toml").write_text(plan, encoding="utf-8")
    return path


def _crs_study(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    launcher = tmp_path / "with_third_condition.py"
    launcher.write_text(LAUNCHER, encoding="utf-8")
    return subprocess.run([sys.executable, str(launcher), *args], cwd=tmp_path,
                          capture_output=True, text=True, timeout=900)


def test_a_third_condition_runs_through_validate_dry_run_and_analyze(tmp_path):
    protocol = _protocol(tmp_path)
    checked = _crs_study(tmp_path, "validate", str(protocol), "--json")
    assert checked.returncode == 0, checked.stderr
    summary = json.loads(checked.stdout)
    assert summary["trials"]["per_condition"][THIRD] == {"practice": 0, "test": 3}
    # on the pixels alone: no boundary feed to report (the CRS line reports one)
    assert f"{THIRD}: every frame within travel" in summary["checks"]
    assert any(c.startswith("crs: every frame within travel (largest boundary feed")
               for c in summary["checks"])

    out = tmp_path / "ds"
    ran = _crs_study(tmp_path, "dry-run", str(protocol), "--participants", "3", "--out",
                     str(out), "--json")
    assert ran.returncode == 0, ran.stderr
    # the linear connection's frames leave every boundary servo at 0 (its renderer's meaning)
    layout = load_layout("crs2d")
    boundary = [f"a{j:02d}" for j in range(layout.n_pixels, layout.n_actuators)]
    third_frames = 0
    for beh in sorted(out.glob("sub-*/ses-1/beh/*_beh.tsv")):
        trials = pd.read_csv(beh, sep="\t")
        frames = pd.read_csv(out / "sourcedata" / beh.parent.parent.relative_to(out)
                             / beh.name.replace("_beh.tsv", "_frames.tsv.gz"), sep="\t")
        third = trials.loc[trials["condition"] == THIRD, "trial_index"]
        shown = frames[frames["trial"].isin(third) & (frames["kind"] == "stimulus")]
        third_frames += len(shown)
        assert not shown[boundary].to_numpy().any()
        crs = trials.loc[trials["condition"] == "crs", "trial_index"]
        assert frames.loc[frames["trial"].isin(crs), boundary].to_numpy().any()
    assert third_frames > 0

    analysed = _crs_study(tmp_path, "analyze", str(out), "--out", str(tmp_path / "res"),
                          "--include-simulated", "--jobs", "1")
    assert analysed.returncode == 0, analysed.stderr
    results = json.loads((tmp_path / "res" / "results.json").read_text(encoding="utf-8"))
    omnibus = results["primary"]["omnibus"]
    assert omnibus is not None and omnibus["df"] == 2
    compared = {c["condition"]: c for c in results["comparisons"] if c["primary"]}
    assert set(compared) == {"crs", THIRD}
    assert all(c["reference"] == "pixel-only" for c in compared.values())


def test_the_simulated_participant_feels_the_conditions_display_model(monkeypatch):
    from crs_study.protocol import load_protocol
    from crs_study.session.responders.observer import PerceptualObserver, benefit_side

    monkeypatch.setitem(CONDITIONS, THIRD, Condition(THIRD, render_pixel_only, False,
                                                     "nearest"))
    protocol = load_protocol("pilot")
    observer = PerceptualObserver(protocol.layout(), protocol, 1)
    assert [observer.model_name(c) for c in ("pixel-only", "crs", THIRD)] == \
        ["linear", "beam", "nearest"]
    assert benefit_side(THIRD) == -1.0
    # the options replace the model of every condition on the same side
    replaced = PerceptualObserver(protocol.layout(), protocol, 1, pixel_model="spline")
    assert [replaced.model_name(c) for c in ("pixel-only", "crs", THIRD)] == \
        ["spline", "beam", "spline"]
