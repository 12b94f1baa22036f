"""Charts are pure functions of results: they draw on the axes given, or on a new figure."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from crs_study.analysis import charts  # noqa: E402
from crs_study.analysis.accuracy import analyse_accuracy  # noqa: E402
from crs_study.analysis.confusion import analyse_confusions  # noqa: E402
from crs_study.analysis.psychometric import analyse_psychometric  # noqa: E402
from crs_study.analysis.speed_accuracy import analyse_speed_accuracy  # noqa: E402

CONDITIONS = ["pixel-only", "crs"]


@pytest.fixture(scope="module")
def trials():
    rng = np.random.default_rng(8)
    rows = []
    for p in range(5):
        for c, acc in (("pixel-only", 0.5), ("crs", 0.7)):
            for d in range(10):
                for level in (0.5, 1.0, 1.5):
                    right = rng.random() < acc * (0.6 + 0.4 * (level > 0.7))
                    rows.append({"participant_id": f"p{p}", "condition": c, "digit": d,
                                 "response": d if right else (d + 1) % 10,
                                 "correct": float(right), "digit_height": level,
                                 "response_time": rng.lognormal(0.8, 0.2)})
    frame = pd.DataFrame(rows)
    frame["response"] = frame["response"].astype("Int64")
    return frame


def test_accuracy_chart_has_a_line_per_participant_and_a_point_per_condition(trials):
    result = analyse_accuracy(trials, tuple(CONDITIONS), 0.1)
    ax = charts.plot_accuracy(result)
    assert isinstance(ax.figure, Figure)
    assert len(ax.lines) >= 5                                 # one paired line a participant
    assert [t.get_text() for t in ax.get_xticklabels()] == CONDITIONS
    assert len(ax.containers) == 2                            # error bars per condition


def test_charts_draw_on_the_axes_given(trials):
    figure = Figure()
    axes = figure.subplots(2, 3).ravel()
    confusions, _ = analyse_confusions(trials, CONDITIONS, n_bootstrap=20)
    speed = analyse_speed_accuracy(trials, CONDITIONS)
    psychometric = analyse_psychometric(trials, CONDITIONS, 0.1, n_bootstrap=0)
    drawn = [charts.plot_accuracy(analyse_accuracy(trials, tuple(CONDITIONS), 0.1), axes[0]),
             charts.plot_confusion(confusions["crs"], axes[1]),
             charts.plot_speed_accuracy(speed, axes[2]), charts.plot_caf(speed, axes[3]),
             charts.plot_psychometric(psychometric, axes[4])]
    assert drawn == list(axes[:5])
    assert "bits" in axes[1].get_title() and len(axes[1].images) == 1
    assert [t.get_text() for t in axes[2].get_legend().get_texts()] == CONDITIONS
    assert len(axes[4].lines) >= 2                             # a fitted curve per condition


def test_save_writes_a_png(tmp_path, trials):
    speed = analyse_speed_accuracy(trials, CONDITIONS)
    path = charts.save(charts.plot_caf(speed), tmp_path / "caf.png")
    assert path.read_bytes()[:4] == b"\x89PNG"


def test_accuracy_chart_bars_are_the_participant_level_intervals(trials):
    # the chart's bars account for participants (the headline's interval), and the
    # title says which interval it shows
    from crs_study.analysis.accuracy import headline_accuracy

    result = analyse_accuracy(trials, tuple(CONDITIONS), 0.1)
    ax = charts.plot_accuracy(result)
    shown = headline_accuracy(result)
    for container, (_, row) in zip(ax.containers, shown.iterrows(), strict=True):
        (segments,) = container.lines[2]
        _, (low, high) = np.asarray(segments.get_segments()[0]).T
        assert (low, high) == pytest.approx((100 * row["ci_low"], 100 * row["ci_high"]))
    assert "t interval" in ax.get_title() and "across participants" in ax.get_title()
