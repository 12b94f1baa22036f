"""Charts: pure functions of result objects, ``plot_x(result, ax=None) -> Axes``.

No pyplot state: without ``ax`` a new figure is made (reach it as ``ax.figure``), so charts
render the same under any backend and in threads, and a script drawing many holds none of
them; that figure and its Axes display as a picture in a notebook with no magic
(:mod:`crs_study._figure`).

Every chart colours a condition alike: :func:`condition_colours` gives each condition its
colour from its place in the plan's order (``colours``; by default the result's own order),
so that ``crs`` is the same colour in the accuracy, tracks and thresholds charts of one
report. Percent axes run a little past 0 and 100 so that an interval's cap at either end is
drawn whole, and a level axis names the level's units (:data:`LEVEL_UNITS`).
"""

from __future__ import annotations

import textwrap
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.ticker import FixedLocator, FormatStrFormatter, NullLocator

from crs_study._figure import new_axes
from crs_study.analysis.accuracy import PARTICIPANT_LEVEL, AccuracyResult, headline_accuracy
from crs_study.analysis.confusion import ConfusionResult
from crs_study.analysis.psychometric import PsychometricResult
from crs_study.analysis.speed_accuracy import SpeedAccuracyResult
from crs_study.analysis.thresholds import ThresholdResult
from crs_study.dataset.schema import LEVEL_COLUMNS

#: Paul Tol's "bright" qualitative scheme (colour-blind safe), one colour per condition.
COLOURS = ("#4477aa", "#ee6677", "#228833", "#ccbb44", "#66ccee", "#aa3377")
#: Units of the level columns as an axis writes them (the dataset's units: pitch, mm/s).
LEVEL_UNITS = {"pitch": "pixel pitches"}
#: Percent axes: a margin past 0 and 100 % so that a cap at either end is not cut.
PERCENT_LIMITS = (-4.0, 104.0)


def condition_colours(conditions: Iterable[str]) -> dict[str, str]:
    """Each condition's colour by its place in ``conditions`` (the plan's order)."""
    return {c: COLOURS[i % len(COLOURS)] for i, c in enumerate(dict.fromkeys(conditions))}


def level_label(column: str | None) -> str:
    """``digit height (pixel pitches)``, ``stroke speed (mm/s)``: the column and its units."""
    if not column:
        return "level"
    units = LEVEL_COLUMNS.get(column, (None, None))[1]
    name = column.replace("_", " ")
    return f"{name} ({LEVEL_UNITS.get(units, units)})" if units else name


def _colour(colours: Mapping[str, str], condition: str) -> str:
    return colours.get(condition) or COLOURS[len(colours) % len(COLOURS)]


def _axes(ax: Axes | None, size: tuple[float, float] = (5.0, 4.0)) -> Axes:
    return ax if ax is not None else new_axes(size)


def _percent_axis(ax: Axes, label: str = "correct (%)") -> None:
    ax.set_ylim(*PERCENT_LIMITS)
    ax.set_yticks(range(0, 101, 20))
    ax.set_ylabel(label)


def _level_ticks(axis, low: float, high: float, scale: str) -> None:
    """Ticks labelled from ``low`` to ``high`` (on a log scale, six at even ratios, rounded
    to two figures: matplotlib's own leave a range under a decade mostly unlabelled)."""
    if scale != "log" or not (0 < low < high):
        return
    ticks = sorted({float(f"{v:.2g}") for v in np.geomspace(low, high, 6)})
    axis.set_major_locator(FixedLocator(ticks))
    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_locator(NullLocator())


def _legend(ax: Axes, **options) -> None:
    """A legend when something is labelled: matplotlib warns on an empty one (a condition
    with no correct response has no mean to label, say)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**options)


def save(ax: Axes, path: str | Path, dpi: int = 110) -> Path:
    """Write the axes' figure as PNG (metadata without dates, for identical reruns)."""
    path = Path(path)
    ax.figure.savefig(path, dpi=dpi, format="png", metadata={"Software": None})
    return path


def plot_accuracy(result: AccuracyResult, ax: Axes | None = None, *,
                  colours: Mapping[str, str] | None = None) -> Axes:
    """Accuracy per condition over per-participant lines joining conditions.

    The marker and its bar are :func:`~crs_study.analysis.accuracy.headline_accuracy`: the
    mean of the participants' accuracies with the t interval across participants (it
    accounts for the differences between participants); the pooled-trial Wilson interval is
    used, and the title says so, only where that has no width (one participant, or every
    participant alike).
    """
    ax = _axes(ax)
    colours = colours or condition_colours(result.conditions)
    conditions = list(result.by_condition["condition"])
    x = {c: i for i, c in enumerate(conditions)}
    wide = result.by_participant.pivot(index="participant_id", columns="condition",
                                       values="accuracy").reindex(columns=conditions)
    for _, row in wide.iterrows():
        ax.plot(range(len(conditions)), 100 * row.to_numpy(float), color="0.6", lw=0.8,
                alpha=0.6, marker="o", ms=3, zorder=1)
    table = headline_accuracy(result)
    for _, row in table.iterrows():
        acc = 100 * row["accuracy"]
        ax.errorbar(x[row["condition"]], acc,
                    yerr=[[acc - 100 * row["ci_low"]], [100 * row["ci_high"] - acc]],
                    fmt="s", color=_colour(colours, row["condition"]), ms=8, capsize=6, lw=2,
                    zorder=3)
        ax.annotate(f"{acc:.1f} %", (x[row["condition"]], acc), xytext=(10, 0),
                    textcoords="offset points", va="center", fontsize=9)
    ax.axhline(100 * result.chance, color="k", ls=":", lw=1)
    ax.text(len(conditions) - 0.5, 100 * result.chance, " chance", va="bottom", ha="right",
            fontsize=8)
    ax.set_xticks(range(len(conditions)), conditions)
    ax.set_xlim(-0.5, len(conditions) - 0.5)
    ax.set_xlabel("display condition")
    _percent_axis(ax)
    level = f"{100 * (1 - result.alpha):.0f} %"
    methods = set(table["method"])
    if methods == {PARTICIPANT_LEVEL}:
        title = (f"Accuracy by condition: mean of {wide.shape[0]} participants, {level} t "
                 "interval\nacross participants (grey: each participant)")
    else:
        title = textwrap.fill(f"Accuracy by condition ({level}: " + "; ".join(sorted(methods))
                              + "); grey: each participant", 70)
    ax.set_title(title, fontsize=8)
    return ax


def plot_confusion(result: ConfusionResult, ax: Axes | None = None) -> Axes:
    """Heatmap of row proportions (symbol shown x symbol reported), counts in the cells."""
    ax = _axes(ax, (4.6, 4.0))
    proportions = result.proportions.to_numpy(float)
    image = ax.imshow(proportions, cmap="Blues", vmin=0, vmax=1)
    labels = [str(v) for v in result.counts.index]
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    counts = result.counts.to_numpy()
    for (i, j), value in np.ndenumerate(counts):
        if value:
            # a count sits in its cell: the layout is the axes', its ticks' and labels'
            # (measuring a hundred counts for it took a third of the chart's time)
            ax.text(j, i, str(value), ha="center", va="center", fontsize=7,
                    color="white" if proportions[i, j] > 0.5 else "black", in_layout=False)
    ax.set_xlabel("response")
    ax.set_ylabel(f"{result.counts.index.name or 'symbol'} shown")
    ci = "" if result.ci95 is None else f" [{result.ci95[0]:.2f}, {result.ci95[1]:.2f}]"
    ax.set_title(f"{result.condition}: {result.bits:.2f} bits{ci} transmitted", fontsize=9)
    ax.figure.colorbar(image, ax=ax, shrink=0.8, label="proportion of row")
    return ax


def plot_speed_accuracy(result: SpeedAccuracyResult, ax: Axes | None = None, *,
                        colours: Mapping[str, str] | None = None) -> Axes:
    """Mean correct RT against accuracy: participants (small) and, per condition, the geometric
    mean RT and pooled accuracy with their intervals (``summarise_efficiency``)."""
    ax = _axes(ax)
    colours = colours or condition_colours(result.conditions)
    for condition in result.conditions:
        colour = _colour(colours, condition)
        cells = result.efficiency.loc[result.efficiency["condition"] == condition]
        ax.scatter(cells["mean_correct_rt"].astype(float), 100 * cells["accuracy"].astype(float),
                   s=14, color=colour, alpha=0.45, lw=0)
        row = result.efficiency_summary.loc[result.efficiency_summary["condition"] == condition]
        if row.empty or row.iloc[0]["mean_correct_rt"] is None \
                or np.isnan(float(row.iloc[0]["mean_correct_rt"])):
            continue
        row = row.iloc[0]
        rt, acc = float(row["mean_correct_rt"]), 100 * float(row["accuracy"])
        ax.errorbar(rt, acc, xerr=[[rt - float(row["mean_correct_rt_ci_low"])],
                                   [float(row["mean_correct_rt_ci_high"]) - rt]],
                    yerr=[[acc - 100 * float(row["accuracy_ci_low"])],
                          [100 * float(row["accuracy_ci_high"]) - acc]],
                    fmt="D", color=colour, ms=8, capsize=4, lw=2, label=condition)
    # the dots are each participant's mean, the diamonds the participants' geometric mean:
    # the axis says both, as the legend does
    ax.set_xlabel(f"{result.rt_column.replace('_', ' ')} of correct trials (s): dots mean, "
                  "diamonds geometric mean", fontsize=8)
    _percent_axis(ax)
    _legend(ax, fontsize=8, title="condition (geometric mean RT, pooled\naccuracy; 95 % CI)",
            title_fontsize=8)
    ax.set_title("Speed against accuracy (dots: participants)", fontsize=9)
    return ax


def plot_caf(result: SpeedAccuracyResult, ax: Axes | None = None, *,
             colours: Mapping[str, str] | None = None) -> Axes:
    """Conditional accuracy functions: accuracy by response-time quantile bin, per condition."""
    ax = _axes(ax)
    colours = colours or condition_colours(result.conditions)
    for condition in result.conditions:
        rows = result.caf.loc[result.caf["condition"] == condition]
        if rows.empty:
            continue
        acc = 100 * rows["accuracy"].to_numpy(float)
        ax.errorbar(rows["mean_rt"].to_numpy(float), acc,
                    yerr=[acc - 100 * rows["ci_low"].to_numpy(float),
                          100 * rows["ci_high"].to_numpy(float) - acc],
                    marker="o", capsize=3, color=_colour(colours, condition), label=condition)
    ax.set_xlabel(f"mean {result.rt_column.replace('_', ' ')} in bin (s)")
    _percent_axis(ax)
    _legend(ax, fontsize=8)
    ax.set_title("Conditional accuracy functions (RT quantile bins)", fontsize=9)
    return ax


def plot_psychometric(result: PsychometricResult, ax: Axes | None = None, *,
                      colours: Mapping[str, str] | None = None) -> Axes:
    """Accuracy against level per condition with the fitted functions and thresholds.

    A degenerate fit (:meth:`~crs_study.analysis.psychometric.PsychometricFit.degenerate`:
    the lapse rate at its bound, or a slope the levels tested cannot pin down) is drawn
    dashed, and its legend entry says why. The legend sits outside the axes, where it hides
    neither the data nor the chance line.
    """
    ax = _axes(ax, (7.0, 4.0))
    colours = colours or condition_colours(result.fits)
    for condition, fit in result.fits.items():
        colour = _colour(colours, condition)
        data = fit.data
        acc = 100 * data["accuracy"].to_numpy(float)
        ax.errorbar(data["level"], acc, yerr=[acc - 100 * data["ci_low"].to_numpy(float),
                                              100 * data["ci_high"].to_numpy(float) - acc],
                    fmt="o", color=colour, capsize=3)
        grid = np.linspace(data["level"].min(), data["level"].max(), 200)
        label = (f"{condition}: threshold {fit.threshold:.3g}" if np.isfinite(fit.threshold)
                 else f"{condition}: no threshold (flat)")
        flags = fit.degenerate()
        if flags:
            label += "\n" + textwrap.fill("DEGENERATE FIT (dashed): " + "; ".join(flags), 40,
                                          subsequent_indent="  ")
        ax.plot(grid, 100 * fit.predict(grid), color=colour, ls="--" if flags else "-",
                label=label)
        if fit.threshold_ci95 is not None:
            ax.axvspan(*fit.threshold_ci95, color=colour, alpha=0.12, lw=0)
    if result.fits:
        guess = next(iter(result.fits.values())).guess
        ax.axhline(100 * guess, color="k", ls=":", lw=1, label=f"chance ({100 * guess:.3g} %)")
    ax.set_xlabel(level_label(result.level_column))
    _percent_axis(ax)
    _legend(ax, fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    ax.set_title("Psychometric functions (shaded: threshold 95 % CI)", fontsize=9)
    return ax


def _threshold_colours(result: ThresholdResult,
                       colours: Mapping[str, str] | None) -> dict[str, str]:
    """The conditions of the thresholds, each with its colour (the plan's order when given;
    else the reference first, as the comparisons name it)."""
    names = list(dict.fromkeys(result.thresholds["condition"])) if len(result.thresholds) \
        else []
    if colours is None:
        order = [c.reference for c in result.comparisons[:1]] + names
        colours = condition_colours(order)
    ordered = [c for c in colours if c in names] + [c for c in names if c not in colours]
    return {c: _colour(colours, c) for c in ordered}


def plot_tracks(result: ThresholdResult, ax: Axes | None = None, *,
                colours: Mapping[str, str] | None = None) -> Axes:
    """Each adaptive track: level against trial, reversals marked, per condition's colour;
    the procedure's final thresholds as ticks at the right."""
    ax = _axes(ax, (6.0, 4.0))
    colours = _threshold_colours(result, colours)
    tracks = result.tracks
    for (_, condition), track in tracks.groupby(["participant_id", "condition"]):
        colour = colours.get(condition, "k")
        ax.plot(track["trial"], track["level"], color=colour, alpha=0.3, lw=0.8)
        reversals = track[track["reversal"]]
        ax.plot(reversals["trial"], reversals["level"], "o", mfc="none", color=colour, ms=3,
                alpha=0.6, mew=0.8)
    for condition, colour in colours.items():  # the median track of each condition
        median = tracks[tracks["condition"] == condition].groupby("trial")["level"].median()
        ax.plot(median.index, median.to_numpy(), color=colour, lw=2.2)
    end = tracks["trial"].max() + 1 if len(tracks) else 1
    for condition, colour in colours.items():
        final = result.thresholds.loc[result.thresholds["condition"] == condition,
                                      "procedure_threshold"]
        ax.plot([end] * len(final), final, "_", color=colour, ms=12, mew=2,
                label=f"{condition} ({len(final)} tracks)")
    design = result.design
    if design is not None and design.scale == "log":
        ax.set_yscale("log")
    if len(tracks):
        _level_ticks(ax.yaxis, float(tracks["level"].min()), float(tracks["level"].max()),
                     design.scale if design else "linear")
    ax.set_xlabel("test trial of the track (thick: median of the tracks)")
    ax.set_ylabel(level_label(design.level_column if design else None))
    ax.set_title("Adaptive tracks (circles: reversals; ticks: final estimates)", fontsize=9)
    _legend(ax, fontsize=8)
    return ax


def plot_thresholds(result: ThresholdResult, ax: Axes | None = None, *,
                    colours: Mapping[str, str] | None = None) -> Axes:
    """Each participant's fitted psychometric function per condition, with the procedure's
    threshold and 95 % interval at the target rate."""
    ax = _axes(ax, (6.0, 4.0))
    design = result.design
    colours = _threshold_colours(result, colours)
    levels = result.tracks["level"] if len(result.tracks) else np.array([1.0])
    grid_u = np.linspace(*design.to_axis(np.array([levels.min(), levels.max()])), 200)
    offsets = {c: 3.0 * (i - (len(colours) - 1) / 2) for i, c in enumerate(colours)}
    for _, row in result.thresholds.iterrows():
        colour = colours[row["condition"]]
        if np.isfinite(row["fit_alpha"]):
            f = 1.0 / (1.0 + np.exp(-row["fit_beta"] * (grid_u - row["fit_alpha"])))
            p = result.guess + (1 - result.guess - row["fit_lapse"]) * f
            ax.plot(design.from_axis(grid_u), 100 * p, color=colour, alpha=0.35, lw=1)
        ax.errorbar(row["procedure_threshold"],
                    100 * design.target_rate + offsets[row["condition"]],
                    xerr=[[row["procedure_threshold"] - row["procedure_ci_low"]],
                          [row["procedure_ci_high"] - row["procedure_threshold"]]],
                    fmt="x", color=colour, alpha=0.7, capsize=2, lw=0.8)
    for condition, colour in colours.items():
        ax.plot([], [], color=colour, label=condition)
    ax.axhline(100 * design.target_rate, color="k", ls="--", lw=0.8,
               label=f"target ({100 * design.target_rate:.3g} %)")
    ax.axhline(100 * result.guess, color="k", ls=":", lw=0.8,
               label=f"chance ({100 * result.guess:.3g} %)")
    if design.scale == "log":
        ax.set_xscale("log")
    _level_ticks(ax.xaxis, float(np.min(levels)), float(np.max(levels)), design.scale)
    ax.set_xlabel(level_label(design.level_column))
    _percent_axis(ax)
    ax.set_title(f"Fitted functions; x: {design.procedure} thresholds at "
                 f"{100 * design.target_rate:.0f} % (95 % CI)", fontsize=9)
    _legend(ax, fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    return ax
