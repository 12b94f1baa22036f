"""Chart and tables of a quality sweep: D_P and D_S against d/l with the paper's lines.

Pure functions of the sweep's points (:class:`~crs_study.quality.sweep.Point`): the chart is
drawn on given or new axes (Agg-safe), tables are strings.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence

import numpy as np

from crs_study._figure import new_axes_grid
from crs_study.quality.criteria import THEORY, theory
from crs_study.quality.sweep import Point

QUANTITIES = ("D_P", "D_S")
_LATTICE_TITLES = {"1d": "1D line", "square": "square lattice", "hex": "hexagonal lattice"}
_COLUMNS = ("layout", "model", "d_over_l", "D_P", "D_S", "D_P_paper", "D_S_paper",
            "positions", "note")


def _paper(point: Point, quantity: str) -> float | None:
    value = theory(point.layout, point.model, quantity, point.d_over_l)
    return None if value is None else float(value)


def table_rows(points: Sequence[Point]) -> list[dict]:
    """One dict per point with the paper's value beside ours where the paper gives one."""
    return [{"layout": p.layout, "model": p.model, "d_over_l": p.d_over_l, "D_P": p.D_P,
             "D_S": p.D_S, "D_P_paper": _paper(p, "D_P"), "D_S_paper": _paper(p, "D_S"),
             "positions": p.positions, "note": p.note} for p in points]


def to_csv(points: Sequence[Point]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in table_rows(points):
        writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
    return out.getvalue()


def _fmt(value: float | None, digits: int = 4) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def to_markdown(points: Sequence[Point]) -> str:
    """A Markdown table; 'ours/paper' is our value over the paper's line at the same d/l."""
    lines = ["| layout | model | d/l | D_P | D_P paper | D_S | D_S paper | D_S ours/paper | note |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in table_rows(points):
        ratio = (row["D_S"] / row["D_S_paper"]
                 if row["D_S"] is not None and row["D_S_paper"] else None)
        lines.append(
            f"| {row['layout']} | {row['model']} | {row['d_over_l']:.4f} | {_fmt(row['D_P'])} | "
            f"{_fmt(row['D_P_paper'])} | {_fmt(row['D_S'])} | {_fmt(row['D_S_paper'])} | "
            f"{_fmt(ratio, 3)} | {row['note']} |"
        )
    return "\n".join(lines) + "\n"


def plot_quality(points: Sequence[Point], axes: np.ndarray | None = None) -> np.ndarray:
    """D_P (top row) and D_S (bottom row) against d/l, one column per lattice; returns axes.

    Each model is a solid line with markers; the paper's lines (pixel-only for every lattice,
    the linear connection in 1D) are dashed in the colour of their model; every panel has its
    legend. A d/l where a model failed (the beam collapsing under the paper's uncapped feed)
    is an x on the axis; models with no rule for a lattice are named in the panel's corner.
    """
    lattices = [lat for lat in ("1d", "square", "hex") if any(p.layout == lat for p in points)]
    models = list(dict.fromkeys(p.model for p in points))
    if axes is None:
        axes = new_axes_grid(2, max(1, len(lattices)), (4.2 * max(1, len(lattices)), 7))
    colours = {m: f"C{i}" for i, m in enumerate(models)}
    for col, lattice in enumerate(lattices):
        for row, quantity in enumerate(QUANTITIES):
            ax = axes[row, col]
            for model in models:
                mine = sorted((p for p in points if p.layout == lattice and p.model == model
                               and getattr(p, quantity) is not None), key=lambda p: p.d_over_l)
                if mine:
                    ax.plot([p.d_over_l for p in mine], [getattr(p, quantity) for p in mine],
                            "o-", ms=3, color=colours[model], label=model)
                if (lattice, model) in THEORY:
                    xs = [p.d_over_l for p in points if p.layout == lattice]
                    grid = np.linspace(0.0, max(xs), 50)
                    coefficient, power = THEORY[(lattice, model)][quantity]
                    ax.plot(grid, theory(lattice, model, quantity, grid), "--", lw=1,
                            color=colours[model],
                            label=f"paper {model}: {coefficient:g} (d/l)"
                                  + ("" if power == 1 else f"^{power}"))
            ax.set_title(f"{quantity}, {_LATTICE_TITLES[lattice]}")
            ax.set_xlabel("d/l")
            ax.set_ylabel(quantity)
            ax.set_xlim(left=0)
            ax.set_ylim(bottom=0)
            for model in models:  # where the model gave no value, say why on the chart
                failed = [p for p in points if p.layout == lattice and p.model == model
                          and p.note]
                if failed and len(failed) == sum(p.layout == lattice and p.model == model
                                                 for p in points):
                    continue  # the model has no rule for this lattice: nothing to mark
                if failed:
                    why = "collapses" if any("collapse" in p.note for p in failed) else "n/a"
                    ax.plot([p.d_over_l for p in failed], [0.0] * len(failed), "x", ms=7,
                            mew=2, color=colours[model], clip_on=False,
                            label=f"{model}: {why} (uncapped feed)"
                            if why == "collapses" else f"{model}: n/a")
            absent = [m for m in models if not any(p.layout == lattice and p.model == m
                                                   and not p.note for p in points)]
            if absent:
                ax.text(0.98, 0.02, f"no {' or '.join(absent)} model on this lattice",
                        transform=ax.transAxes, ha="right", va="bottom", fontsize=7,
                        color="0.4")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    return axes


def summary_lines(points: Sequence[Point]) -> list[str]:
    """Human-readable lines: the values at d/l = 1/3, then each distinct failure once."""
    out = [f"{p.layout:6s} {p.model:9s} d/l=1/3  D_P={p.D_P:.4f}  D_S={p.D_S:.4f}"
           for p in points if not p.note and math.isclose(p.d_over_l, 1 / 3)]
    return out + failure_lines(points)


def failure_lines(points: Sequence[Point]) -> list[str]:
    """Each distinct failure once, with the d/l values it hit."""
    out = []
    failures: dict[tuple[str, str, str], list[float]] = {}
    for p in points:
        if p.note:
            failures.setdefault((p.layout, p.model, p.note), []).append(p.d_over_l)
    for (layout, model, note), xs in failures.items():
        out.append(f"{layout:6s} {model:9s} n/a at d/l = {', '.join(f'{x:.3g}' for x in xs)}: "
                   f"{note}")
    return out
