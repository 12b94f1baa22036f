"""The report of a measurement: the chart in the style of the paper's Fig. 2d, the residual
map, and the text. Charts are pure functions of a :class:`~crs_study.quality.
measured_result.MeasuredQuality` (given axes, or new ones made without pyplot).

The chart follows Fig. 2d of Wang, Meng & Chen, "Continuity reinforcement skeleton for
pixel-based haptic display" (and Fig. 4f-g in 2D): D_S (left) and D_P (right) against d/l,
the paper's theory lines for pixel displays (solid) and the linear connection (dashed), the
measured points with their bootstrap intervals (CRS: blue crosses; pixel-only: red circles),
and beside each the model's prediction for the same targets (open squares).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from crs_study._figure import new_axes, new_axes_grid
from crs_study._files import make_dirs, write_atomically
from crs_study.quality.criteria import THEORY, theory

if TYPE_CHECKING:  # the result's plot methods call these charts: no import at run time
    from crs_study.quality.measured_result import MeasuredQuality

_STYLE = {"crs": ("tab:blue", "x"), "pixel-only": ("tab:red", "o")}
_EQUATIONS = {"1d": {"D_P": "Eq. 1", "D_S": "Eq. 2"},
              "hex": {"D_P": "Eq. 5", "D_S": "Eq. 6"}, "square": {"D_P": "Eq. 5",
                                                                 "D_S": "Eq. 6"}}
_PAPER_LABEL = {"nearest": "paper: pixel display", "linear": "paper: linear connection"}


def plot_measured(result: MeasuredQuality, axes=None):
    """D_S (left) and D_P (right) against d/l (module docstring); returns the two axes."""
    if axes is None:
        axes = new_axes_grid(1, 2, (10, 4.2))
    axes = np.asanyarray(axes).ravel()     # a ChartGrid stays one (it displays)
    top = max(r.d_over_l for r in result.rows) * 1.25 if result.rows else 0.5
    grid = np.linspace(0.0, top, 60)
    width = 0.012 * top
    for ax, quantity in zip(axes, ("D_S", "D_P"), strict=True):
        for (lattice, model), lines in THEORY.items():
            if lattice != result.lattice:
                continue
            coefficient, power = lines[quantity]
            if model == "linear" and quantity == "D_P":
                continue  # the same line as the pixel display's
            ax.plot(grid, theory(lattice, model, quantity, grid),
                    "-" if model == "nearest" else "--", lw=1.2,
                    color="0.2" if model == "nearest" else "tab:orange",
                    label=f"{_PAPER_LABEL[model]}: {coefficient:g} (d/l)"
                          + ("" if power == 1 else f"^{power}"))
        for condition in dict.fromkeys(r.condition for r in result.rows):
            colour, marker = _STYLE.get(condition, ("tab:green", "d"))
            rows = [r for r in result.rows if r.condition == condition]
            x = np.array([r.d_over_l for r in rows])
            for name, shift, style in ((quantity, -width, marker),
                                       (f"model_{quantity}", width, "s")):
                intervals = [getattr(r, name) for r in rows]
                y = np.array([i.estimate for i in intervals])
                low = np.array([i.low for i in intervals])
                high = np.array([i.high for i in intervals])
                err = np.vstack([np.nan_to_num(y - low), np.nan_to_num(high - y)])
                measured = name == quantity
                ax.errorbar(x + shift, y, yerr=err, fmt=style, ms=7 if measured else 6,
                            mew=2 if measured else 1.2, capsize=3, color=colour,
                            mfc=colour if measured and marker != "x" else "none",
                            ls="none", alpha=1.0 if measured else 0.75,
                            label=(f"{condition}: measured" if measured else
                                   f"{condition}: model ({rows[0].model}), as sampled"))
        ax.set_xlim(0.0, top)
        ax.set_ylim(bottom=0.0)
        ax.set_xlabel("d/l")
        ax.set_ylabel(quantity)
        ax.set_title(f"{quantity} ({_EQUATIONS[result.lattice][quantity]}), "
                     f"{result.device}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    verdicts = "; ".join(f"{v.condition}: {v.verdict}" for v in result.verdicts)
    axes[0].figure.suptitle(f"Measured against the model ({result.confidence:.0%} bootstrap "
                            f"intervals over shapes): {verdicts}", fontsize=9)
    return axes


def plot_residual_map(result: MeasuredQuality, ax=None):
    """Each pixel's offset at neutral and its stroke's error at the protocol's bump height,
    (gain - 1) z_f (mm), against the limits; a named servo marked. 2D: each pixel at its
    place, coloured by the sum; 1D: bars along the line. Returns the axes."""
    pixels = result.residual_map.pixels
    height = result.height_mm
    offset = np.array([p.offset_mm if math.isfinite(p.offset_mm) else 0.0 for p in pixels])
    stroke = np.array([(p.gain - 1.0) * height if math.isfinite(p.gain) else 0.0
                       for p in pixels])
    flagged = [p for p in pixels if p.flagged]
    title = "Residual map: " + ("; ".join(f"{p.channel} (pixel {p.pixel}): {p.why}"
                                          for p in flagged) if flagged else
                                "every servo within its limits")
    if result.lattice == "1d":
        if ax is None:
            ax = new_axes((7.5, 4.0))
        _residual_bars(ax, pixels, offset, stroke, result)
    else:
        if ax is None:
            ax = new_axes((6.4, 5.6))
        _residual_hexagons(ax, pixels, offset + stroke, height, result)
    ax.set_title(title, fontsize=8, wrap=True)
    return ax


def _residual_bars(ax, pixels, offset, stroke, result: MeasuredQuality) -> None:
    x = np.arange(len(pixels))
    limit = result.residual_map.offset_limit_mm
    ax.bar(x - 0.2, offset, 0.4, color="tab:purple", label="offset at neutral (mm)")
    ax.bar(x + 0.2, stroke, 0.4, color="tab:olive",
           label=f"(gain - 1) z_f, z_f = {result.height_mm:g} mm (mm)")
    ax.axhspan(-limit, limit, color="0.85", zorder=0,
               label=f"offset limit +-{limit:g} mm")
    gain_limit = result.residual_map.gain_limit * result.height_mm
    for sign in (-1, 1):
        label = f"gain limit 1 +- {result.residual_map.gain_limit:g}" if sign > 0 else None
        ax.axhline(sign * gain_limit, ls="--", lw=1, color="tab:olive", label=label)
    ax.axhline(0.0, color="0.3", lw=0.8)
    ax.set_xticks(x, [f"pixel {p.pixel}\n{p.channel}" + ("\nNAMED" if p.flagged else "")
                      for p in pixels], fontsize=8)
    for tick, p in zip(ax.get_xticklabels(), pixels, strict=True):
        if p.flagged:
            tick.set_color("tab:red")
            tick.set_fontweight("bold")
    ax.set_ylabel("mm")
    ax.legend(fontsize=7)
    ax.grid(axis="y", alpha=0.3)


def _residual_hexagons(ax, pixels, error, height: float, result: MeasuredQuality) -> None:
    from matplotlib.colors import TwoSlopeNorm

    x = np.array([p.x_mm for p in pixels])
    y = np.array([p.y_mm for p in pixels])
    limit = max(float(np.max(np.abs(error))), result.residual_map.offset_limit_mm)
    size = 1500
    shown = ax.scatter(x, y, c=error, s=size, marker="h", cmap="coolwarm",
                       norm=TwoSlopeNorm(0.0, -limit, limit), edgecolors="0.4",
                       linewidths=0.8)
    for p, e in zip(pixels, error, strict=True):
        ax.annotate(f"{p.channel}\n{e:+.2f}", (p.x_mm, p.y_mm), ha="center", va="center",
                    fontsize=7, fontweight="bold" if p.flagged else "normal")
    flagged = [p for p in pixels if p.flagged]
    if flagged:
        ax.scatter([p.x_mm for p in flagged], [p.y_mm for p in flagged], s=size * 1.2,
                   marker="h", facecolors="none", edgecolors="black", linewidths=2.5)
    ax.figure.colorbar(shown, ax=ax, shrink=0.8,
                       label=f"offset + (gain - 1) z_f at z_f = {height:g} mm (mm)")
    ax.set_aspect("equal")
    ax.margins(0.15)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")


def _fmt(value: float | None, digits: int = 4) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _interval(interval) -> str:
    return (f"{_fmt(interval.estimate)} [{_fmt(interval.low)}, {_fmt(interval.high)}]")


def report_markdown(result: MeasuredQuality, figures: dict[str, str]) -> str:
    """The report: verdicts, the table, the registration, the residual map, the figures."""
    lines = [f"# Measured display quality: {result.protocol} on {result.device}", "",
             f"Measurement: `{result.measurement}`. D_P and D_S as Wang, Meng & Chen define "
             f"them (\"Continuity reinforcement skeleton for pixel-based haptic display\", "
             f"{_EQUATIONS[result.lattice]['D_P']} and {_EQUATIONS[result.lattice]['D_S']}), "
             f"means over shapes with {result.confidence:.0%} percentile bootstrap intervals; "
             f"the model's prediction is its surface for the same setpoints, sampled at the "
             f"measured points and read by the same fit (its exact value beside). Verdict: "
             f"measured - model within +-{result.tolerance_D_P:g} (D_P) and "
             f"+-{result.tolerance_D_S:g} (D_S).", "", "## Verdicts", ""]
    for verdict in result.verdicts:
        lines.append(f"- **{verdict.condition}: {verdict.verdict}**. Farthest from the model: "
                     f"{verdict.detail}.")
    lines += ["", "## D_P and D_S", "",
              "| condition | model | d/l | shapes | D_P measured | D_P model | D_P exact | "
              "D_P paper | D_S measured | D_S model | D_S exact | D_S paper | verdict |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result.rows:
        lines.append(
            f"| {r.condition} | {r.model} | {r.d_over_l:.4f} | {r.shapes} | {_interval(r.D_P)} "
            f"| {_interval(r.model_D_P)} | {_fmt(r.exact_D_P)} | {_fmt(r.paper_D_P)} | "
            f"{_interval(r.D_S)} | {_interval(r.model_D_S)} | {_fmt(r.exact_D_S)} | "
            f"{_fmt(r.paper_D_S)} | D_P {r.verdict_D_P}, D_S {r.verdict_D_S} |")
    reg = result.registration
    lines += ["", "## Registration", "",
              f"{reg.mode} fit of {len(reg.pixels)} pixel fiducials ({reg.source}): rotation "
              f"{reg.rotation_deg:.3f} deg, scale {reg.scale:.5f}, translation "
              f"({reg.translation[0]:.3f}, {reg.translation[1]:.3f}) mm; residual "
              f"{reg.rms_mm:.3f} mm RMS, at most {reg.max_mm:.3f} mm (pixel "
              f"{reg.worst_pixel}).", "", "## Residual map", "",
              "| pixel | channel | offset at neutral (mm) | gain | +- | shapes | RMS (mm) | "
              "named |", "|---|---|---|---|---|---|---|---|"]
    for p in sorted(result.residual_map.pixels, key=lambda p: (not p.flagged, p.pixel)):
        lines.append(f"| {p.pixel} | {p.channel} | {_fmt(p.offset_mm, 3)} | {_fmt(p.gain, 3)} "
                     f"| {_fmt(p.gain_se, 3)} | {p.shapes} | {_fmt(p.rms_mm, 3)} | "
                     f"{p.why or ''} |")
    if result.notes:
        lines += ["", "## Notes", ""] + [f"- {note}" for note in result.notes]
    lines += ["", "## Figures", ""] + [f"![{name}]({path})" for name, path in figures.items()]
    return "\n".join(lines) + "\n"


def write_report(result: MeasuredQuality, out: str | Path) -> dict[str, Path]:
    """``report.md``, ``results.json``, ``shapes.csv`` and ``figures/*.png`` in ``out``."""
    out = Path(out)
    make_dirs(out / "figures")
    files = {}
    axes = plot_measured(result)
    files["chart"] = out / "figures" / "measured_quality.png"
    axes[0].figure.savefig(files["chart"], dpi=120)
    ax = plot_residual_map(result)
    files["residual_map"] = out / "figures" / "residual_map.png"
    ax.figure.savefig(files["residual_map"], dpi=120)
    files["results"] = out / "results.json"
    write_atomically(files["results"], result.to_json())
    files["shapes"] = out / "shapes.csv"
    write_atomically(files["shapes"], result.shapes_frame().to_csv(index=False))
    files["report"] = out / "report.md"
    write_atomically(files["report"], report_markdown(
        result, {"D_P and D_S": "figures/measured_quality.png",
                 "residual map": "figures/residual_map.png"}))
    return files
