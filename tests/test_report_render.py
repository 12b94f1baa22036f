"""The charts and the HTML report as a reader sees them: one colour per condition in the
plan's order across every chart, whole error-bar caps, level axes with units, degenerate
psychometric fits flagged, legends clear of the chance line; the HTML report rendered by a
real browser (headless Chromium): Markdown marks rendered, the headline first and set
apart, no table wider than the page, only the methods used cited.

The data: three simulated participants of a short QUEST+ protocol (fixed-level charts, the
psychometric functions, the adaptive tracks and thresholds all from one dry-run), analysed
with the chi-square LR (the bootstrap is not what is shown here).
"""

from __future__ import annotations

import dataclasses
import html
import json
import re
import shutil
import subprocess

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from _session_helpers import adaptive_protocol  # noqa: E402
from analysis_fixtures import dataset, write_plan  # noqa: E402

import crs_study  # noqa: E402
from crs_study.analysis import analyze, load_dataset  # noqa: E402
from crs_study.analysis.charts import COLOURS, PERCENT_LIMITS, plot_psychometric  # noqa: E402
from crs_study.analysis.psychometric import analyse_psychometric  # noqa: E402
from crs_study.analysis.report_text import split_table  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def adaptive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("render")
    protocol = adaptive_protocol(folder, trials=10, levels=5, digits=(1, 4, 7), practice=0)
    crs_study.dry_run(protocol, participants=3, out=folder / "ds")
    data = load_dataset(folder / "ds")
    plan = data.plan
    plan = dataclasses.replace(
        plan, primary=dataclasses.replace(plan.primary, p_value="chi2"),
        report=dataclasses.replace(plan.report, format="html"),
        confusion=dataclasses.replace(plan.confusion, bootstrap=50),
        psychometric=dataclasses.replace(plan.psychometric, bootstrap=20))
    return analyze(data, plan, folder / "out")


def _colours(ax) -> dict[str, str]:
    """Condition -> colour, from the legend's entries (labels starting with a condition)."""
    out = {}
    legend = ax.get_legend()
    for handle, text in zip(legend.legend_handles, legend.get_texts(), strict=True):
        label = text.get_text().split(":")[0].split(" (")[0]
        if label in ("pixel-only", "crs"):
            out[label] = matplotlib.colors.to_hex(handle.get_color())
    return out


def test_one_colour_per_condition_in_the_plans_order_in_every_chart(adaptive):
    """The plan lists pixel-only first: it is the first colour everywhere (the tracks and
    thresholds charts took the alphabetical order and swapped them)."""
    expected = {"pixel-only": COLOURS[0], "crs": COLOURS[1]}
    assert adaptive.colours == expected
    assert set(adaptive.plots()) == {"accuracy", "speed_accuracy", "caf", "psychometric",
                                     "tracks", "thresholds"}
    for name in adaptive.plots():
        ax = adaptive.plot(name)
        if name == "accuracy":   # the condition's square marker at its x position
            got = {ax.get_xticklabels()[int(round(line.get_xdata()[0]))].get_text():
                   matplotlib.colors.to_hex(line.get_color()) for line in ax.lines
                   if line.get_marker() == "s"}
        else:
            got = _colours(ax)
        assert got == expected, name


def test_the_accuracy_bar_caps_are_drawn_whole(adaptive):
    ax = adaptive.plot("accuracy")
    caps = [y for line in ax.lines if line.get_marker() == "_" for y in line.get_ydata()]
    assert caps and max(caps) <= 100 < ax.get_ylim()[1] == PERCENT_LIMITS[1]
    assert min(caps) >= 0 > ax.get_ylim()[0]


def test_level_axes_name_the_level_and_its_units_and_label_the_top(adaptive):
    tracks = adaptive.plot("tracks")
    assert tracks.get_ylabel() == "digit height (pixel pitches)"
    assert adaptive.plot("thresholds").get_xlabel() == "digit height (pixel pitches)"
    assert adaptive.plot("psychometric").get_xlabel() == "digit height (pixel pitches)"
    top = float(adaptive.thresholds.tracks["level"].max())
    ticks = [float(t) for t in tracks.get_yticks()]
    labels = [t.get_text() for t in tracks.get_yticklabels()]
    assert max(ticks) >= 0.95 * top and all(labels)


def _steep_trials(lapse: bool) -> pd.DataFrame:
    """Accuracy jumps from chance to its top between two adjacent levels (slope not
    identified); with ``lapse`` the top is 70 %, more errors than lapse_max allows."""
    rows = []
    top = 0.7 if lapse else 1.0
    for level, accuracy in ((0.4, 0.1), (0.6, 0.1), (0.8, top), (1.0, top), (1.2, top)):
        n = 40
        rows += [{"participant_id": "p1", "condition": "crs", "digit": 1, "response": 1,
                  "correct": float(k < round(accuracy * n)), "digit_height": level}
                 for k in range(n)]
    return pd.DataFrame(rows)


def _gradual_trials() -> pd.DataFrame:
    rng = np.random.default_rng(3)
    rows = []
    for level in (0.4, 0.6, 0.8, 1.0, 1.2):
        p = 0.1 + 0.88 / (1 + np.exp(-6 * (level - 0.8)))
        rows += [{"participant_id": "p1", "condition": "crs", "digit": 1, "response": 1,
                  "correct": float(rng.random() < p), "digit_height": level}
                 for _ in range(200)]
    return pd.DataFrame(rows)


def test_a_degenerate_psychometric_fit_is_flagged_on_the_chart():
    lapsing = analyse_psychometric(_steep_trials(lapse=True), ["crs"], 0.1, "digit_height",
                                   lapse_max=0.1, n_bootstrap=0)
    assert any("at its bound 0.1" in f for f in lapsing.fits["crs"].degenerate())
    steep = analyse_psychometric(_steep_trials(lapse=False), ["crs"], 0.1, "digit_height",
                                 lapse_max=0.1, n_bootstrap=0)
    assert any("not identified" in f for f in steep.fits["crs"].degenerate())
    for bad, why in ((lapsing, "lapse rate"), (steep, "not identified")):
        ax = plot_psychometric(bad)
        label = ax.get_legend().get_texts()[0].get_text()
        assert "DEGENERATE FIT" in label and why in " ".join(label.split())
        assert ax.lines[-2].get_linestyle() == "--"          # the fitted curve, dashed
    good = analyse_psychometric(_gradual_trials(), ["crs"], 0.1, "digit_height",
                                lapse_max=0.1, n_bootstrap=0)
    assert good.fits["crs"].degenerate() == ()
    assert "DEGENERATE" not in plot_psychometric(good).get_legend().get_texts()[0].get_text()


@pytest.mark.parametrize("name", ["psychometric", "thresholds"])
def test_the_legend_does_not_hide_the_chance_line(adaptive, name):
    ax = adaptive.plot(name)
    figure = ax.figure
    figure.draw_without_rendering()
    legend = ax.get_legend().get_window_extent()
    chance = next(line for line in ax.lines if line.get_label().startswith("chance"))
    assert not legend.overlaps(chance.get_window_extent())
    assert not legend.overlaps(ax.get_window_extent())


def test_wide_tables_are_split_with_their_key_column():
    table = [[f"c{i}" for i in range(22)], [f"v{i}" for i in range(22)]]
    parts = split_table(table, 8)
    assert [len(p[0]) for p in parts] == [8, 8, 8]            # 21 columns, 7 a part
    assert all(p[0][0] == "c0" and p[1][0] == "v0" for p in parts)
    assert [c for p in parts for c in p[0][1:]] == table[0][1:]


def test_only_the_methods_used_are_cited(adaptive, tmp_path):
    adaptive_text = adaptive.report_path.read_text()
    assert "Watson AB (2017) QUEST+" in adaptive_text and "Levitt H" not in adaptive_text
    assert "Wichmann FA" in adaptive_text
    plan = write_plan(tmp_path / "p.toml", '[plan]\nname = "fixed"\n[primary]\n'
                      'random_effects = ["participant"]\np_value = "chi2"\n'
                      '[confusion]\nbootstrap = 50\n')
    fixed = analyze([dataset(tmp_path / "ds", n_participants=3, repetitions=2)], plan,
                    tmp_path / "out")
    text = fixed.report_path.read_text()
    for absent in ("Watson AB", "Levitt H", "Wichmann FA", "Halekoh U"):
        assert absent not in text
    for present in ("Wilson EB", "Bates D", "Miller GA"):
        assert present in text


_PROBE = """<script>
window.addEventListener('load', () => {
  const root = document.documentElement, body = document.body;
  const images = [...document.images];
  const headline = document.querySelector('.headline');
  const first = document.querySelector('h1').nextElementSibling;
  const out = document.createElement('pre');
  out.id = 'probe';
  out.textContent = JSON.stringify({
    scroll: root.scrollWidth, client: root.clientWidth,
    images: images.length, loaded: images.filter(i => i.naturalWidth > 0).length,
    code: document.querySelectorAll('code').length,
    backticks: (body.innerText.match(/`/g) || []).length,
    headline_first: first === headline,
    headline_weight: getComputedStyle(headline.querySelector('strong')).fontWeight,
    tables: [...document.querySelectorAll('table')].map(t => t.getBoundingClientRect().right),
  });
  body.appendChild(out);
});
</script>"""


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium to render the report")
def test_the_html_report_renders_in_a_browser(adaptive, tmp_path):
    """Chromium lays the page out at 1000 px: nothing wider than the window, every chart
    loaded, no literal Markdown, the headline the first thing under the title, in bold."""
    report = adaptive.report_path
    probe = report.with_name("probe.html")
    probe.write_text(report.read_text().replace("</body>", _PROBE + "</body>"))
    command = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
               "--window-size=1000,1400", "--virtual-time-budget=10000",
               "--allow-file-access-from-files", "--dump-dom", probe.as_uri()]
    done = subprocess.run(command, capture_output=True, text=True, timeout=180, check=False)
    match = re.search(r'<pre id="probe">(.*?)</pre>', done.stdout, re.S)
    assert match, done.stderr[-2000:]
    seen = json.loads(html.unescape(match.group(1)))
    assert seen["scroll"] <= seen["client"], seen
    assert max(seen["tables"]) <= seen["client"], seen
    assert seen["images"] == len(adaptive.charts) and seen["loaded"] == seen["images"], seen
    assert seen["code"] > 0 and seen["backticks"] == 0, seen
    assert seen["headline_first"] and int(seen["headline_weight"]) >= 600, seen
    shot = tmp_path / "report.png"          # a picture of the page, for a person to look at
    subprocess.run([*command[:-2], f"--screenshot={shot}", report.as_uri()],
                   capture_output=True, timeout=180, check=False)
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
