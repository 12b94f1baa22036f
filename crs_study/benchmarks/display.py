"""Bench area ``display``: speed against accuracy of the display models.

For a set of 1D (crs1d) and 2D (crs2d) scenes, each a bump of Eq. 7 (l = 90 mm, z_f = 4 mm)
rendered in the CRS condition, every model's surface is timed (median per surface; 1D on 721
points along the line, 2D on a 41 x 41 grid over the display) and compared with the
``reference`` model (Hermite FE energy minimisation with the exact arc-length constraint),
max and RMS error in mm. Times are also given as ratios to the ``nearest`` model's time per
surface measured in the same run (the baseline). ``speed_accuracy_rows(quick)`` returns the
rows (reused by a ``quality`` option), ``format_table(rows)`` prints them and
``plot_speed_accuracy(rows)`` draws the chart.

The chart and a Markdown table of these rows: ``crs-study quality --speed-accuracy --out DIR``
(speed_accuracy.png, speed_accuracy.md). The session figures time ``beam_profiles`` of the
2D and 1D devices per frame (32 CRS bumps at random centres, every frame a new scene: memo
off), alone and with the surface on the observer's 19 x 19 grid, against the ``nearest``
surface on that grid, the targets (2D <= 0.4 ms; 1D informative: about 0.13 ms, where ~100
small numpy calls a frame are the floor without compiled code) and the budget of a session
simulated 100x faster than real time at 15 frames/s (1/1500 s a frame), and state the
simulated seconds per wall second.

Which model to use (measured with ``crs-study bench display`` on a busy 2-CPU machine; bump
z_f = 4 mm, l = 90 mm; time per surface, RMS / max error against ``reference``)

    ========= ================================ ================================
    model     1D (721 points)                  2D (41 x 41 points)
    ========= ================================ ================================
    nearest   0.008 ms, 0.60 / 1.9 mm          0.24 ms, 0.32 / 1.9 mm
    linear    0.010 ms, 0.34 / 1.1 mm          0.067 ms, 0.16 / 1.4 mm
    spline    0.11 ms, 0.15 / 0.49 mm          0.24 ms, 0.068 / 0.49 mm
    beam      0.25 ms, 0.0008 / 0.0028 mm      0.50 ms, 0.0017 / 0.018 mm
    reference 54 ms (the yardstick)            246 ms
    ========= ================================ ================================

Per use, the cheapest model accurate enough:

    ================================== ============ =========================================
    use                                model        why
    ================================== ============ =========================================
    observer, CRS condition            ``beam``     the only model of the compressed skeleton
                                                    (others miss by 12-48 % of the height)
    observer, pixel-only condition     ``linear``   the fabric sewn to the pixel tips drapes
                                                    between them (a tent); ``nearest`` is the
                                                    paper's theory, a staircase no skin shows
    the paper's pixel-only theory      ``nearest``  D_P = 0.25, 0.383, 0.351 d/l exactly
    quality criteria of the CRS        ``beam``     the default sweep in ~12 s cold
    validating any model               ``reference`` independent FE minimisation, 100-500x
                                                    the cost of ``beam``
    peak or contact along a beam only  ``BeamModel.beam_profiles`` (skips the fabric)
    ================================== ============ =========================================

``beam`` is within 0.07 % (1D) and 0.45 % (2D, the fabric meshed 4x coarser than the
reference's) of the 4 mm bump height of the reference. A repeated frame is a memo hit
(microseconds).
"""

from __future__ import annotations

import math

import numpy as np

from crs_study._figure import new_axes
from crs_study.benchmarks import Figure, median_seconds
from crs_study.display import get_model
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import load_layout
from crs_study.rendering.render import Renderer
from crs_study.stimuli.targets import Bump

AREA = "display"
DESCRIPTION = "display models: median time per surface vs error against the FE reference"

MODELS = ("nearest", "linear", "spline", "beam", "reference")
SCENES_1D = ((35.0, 0.0), (45.0, 0.0), (52.0, 0.0), (80.0, 0.0))
SCENES_2D = ((15.0, 8.0), (0.0, 0.0), (-10.0, 20.0), (22.0, -13.0))
HEIGHT_MM = 4.0
#: a simulated session at 15 frames/s must run >= 100x real time: <= 1/1500 s a frame
SESSION_FPS, SESSION_SPEEDUP = 15.0, 100.0
#: options that switch a model's frame memo off, so every timed frame is solved
UNCACHED = {"beam": {"memo_frames": 0}}
#: the observer's sensing grid: 19 x 19 points 3 mm apart around a centre (a few hundred)
OBSERVER_GRID = 19


def _points(dim: str):
    if dim == "1d":
        x = np.linspace(-30.0, 150.0, 721)
        return np.column_stack([x, np.zeros_like(x)])
    g = np.linspace(-90.0, 90.0, 41)
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel()])


def _time_per_surface(model, setpoint_list, xy, repeat: int) -> float:
    """Median time of one surface, cycling through the scenes (no frame is solved twice in a
    row, so per-frame caches do not flatter the figure)."""
    count = len(setpoint_list)
    state = {"i": 0}

    def once():
        model.surface(setpoint_list[state["i"] % count], xy)
        state["i"] += 1

    once()
    return median_seconds(once, repeat=repeat, number=count)


def speed_accuracy_rows(quick: bool = True) -> list[dict]:
    """One row per (device, model): time per surface (median, s), ratio to ``nearest``, and
    the max and RMS error (mm) against ``reference`` over the scenes."""
    repeat = 3 if quick else 9
    rows = []
    for dim, device, scenes in (("1d", "crs1d", SCENES_1D), ("2d", "crs2d", SCENES_2D)):
        layout = load_layout(device)
        renderer = Renderer(layout, "crs")
        setpoints = [renderer.render(Bump(c, 90.0, HEIGHT_MM)).setpoints for c in scenes]
        xy = _points(dim)
        reference = get_model("reference", layout)
        truth = [reference.surface(s, xy) for s in setpoints]
        base = None
        for name in MODELS:
            model = get_model(name, layout, **UNCACHED.get(name, {}))
            try:
                errors = np.concatenate([model.surface(s, xy) - t
                                         for s, t in zip(setpoints, truth, strict=True)])
                reps = 1 if name == "reference" else repeat
                seconds = _time_per_surface(model, setpoints, xy, reps)
            except DisplayModelError as exc:  # pragma: no cover - reported, not hidden
                rows.append({"layout": dim, "model": name, "error": str(exc)})
                continue
            base = seconds if name == "nearest" else base
            rows.append({
                "layout": dim, "model": name, "points": len(xy),
                "seconds_per_surface": seconds,
                "ratio_to_nearest": seconds / base if base else math.nan,
                "max_error_mm": float(np.abs(errors).max()),
                "rms_error_mm": float(np.sqrt(np.mean(errors**2))),
                "height_mm": HEIGHT_MM,
            })
    return rows


def format_table(rows: list[dict], markdown: bool = False) -> str:
    """The speed-accuracy rows as aligned text, or as a Markdown table."""
    head = ["layout", "model", "ms/surface", "x nearest", "max err mm", "rms err mm"]
    body = []
    for r in rows:
        if "error" in r:
            body.append([r["layout"], r["model"], "failed: " + r["error"], "", "", ""])
            continue
        body.append([r["layout"], r["model"], f"{1e3 * r['seconds_per_surface']:.3f}",
                     f"{r['ratio_to_nearest']:.1f}", f"{r['max_error_mm']:.4f}",
                     f"{r['rms_error_mm']:.4f}"])
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in body])
    widths = [6, 10, 11, 10, 11, 11]

    def line(row: list[str]) -> str:
        return " ".join(f"{c:{w}s}" if i < 2 else f"{c:>{w}s}"
                        for i, (c, w) in enumerate(zip(row, widths, strict=True)))

    return "\n".join([line(head)] + [line(row) for row in body])


def plot_speed_accuracy(rows: list[dict], ax=None):
    """Time per surface (x, log) against RMS error vs the reference (y, log), per model."""
    if ax is None:
        ax = new_axes((6, 4))
    markers = {"1d": "o", "2d": "s"}
    for r in rows:
        if "error" in r:
            continue
        err = max(r["rms_error_mm"], 1e-7)  # the reference against itself: plotted at the floor
        ax.scatter(1e3 * r["seconds_per_surface"], err, marker=markers[r["layout"]])
        ax.annotate(f"{r['model']} {r['layout']}", (1e3 * r["seconds_per_surface"], err),
                    textcoords="offset points", xytext=(4, 2), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median time per surface (ms)")
    ax.set_ylabel(f"RMS error vs reference (mm), bump {HEIGHT_MM:g} mm")
    ax.set_title("Display models: speed against accuracy")
    return ax


def _frames(device: str, count: int = 32):
    """Setpoints of ``count`` CRS frames (bumps at random centres) the beams can show."""
    layout = load_layout(device)
    renderer = Renderer(layout, "crs")
    rng = np.random.default_rng(0)
    if device == "crs1d":
        centres = np.column_stack([rng.uniform(20.0, 100.0, count), np.zeros(count)])
    else:
        centres = rng.uniform(-30.0, 30.0, size=(count, 2))
    model = get_model("beam", layout, memo_frames=0)
    usable = []
    for x, y in centres:
        setpoints = renderer.render(Bump((float(x), float(y)), 90.0, HEIGHT_MM)).setpoints
        try:  # a scene the beams cannot show (collapse) is not a frame
            model.beam_profiles(setpoints)
        except DisplayModelError:
            continue
        usable.append(setpoints)
    return layout, usable


def _cycle(func, frames):
    state = {"i": 0}

    def once():
        func(frames[state["i"] % len(frames)])
        state["i"] += 1

    return once


def session_frame_seconds(quick: bool) -> dict[str, float]:
    """Median seconds a frame, every frame a new scene (memo off), for the session figures.

    ``{dim}_profiles``: ``beam_profiles`` alone; ``2d_observer``: profiles plus the surface
    on the observer's 19 x 19 grid; ``2d_surface_64``: profiles plus a 64 x 64 surface;
    ``{dim}_nearest``: the ``nearest`` surface on the same 19 x 19 grid (the baseline).
    """
    repeat = 3 if quick else 9
    out = {}
    for dim, device in (("1d", "crs1d"), ("2d", "crs2d")):
        layout, frames = _frames(device)
        beam = get_model("beam", layout, memo_frames=0)
        nearest = get_model("nearest", layout)
        centre = layout.pixel_xy.mean(axis=0)
        axis = 3.0 * (np.arange(OBSERVER_GRID) - OBSERVER_GRID // 2)
        gx, gy = np.meshgrid(centre[0] + axis, centre[1] + axis)
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        if dim == "1d":
            grid = np.column_stack([np.linspace(-30.0, 150.0, OBSERVER_GRID**2),
                                    np.zeros(OBSERVER_GRID**2)])
        number = len(frames)
        out[f"{dim}_profiles"] = median_seconds(_cycle(beam.beam_profiles, frames), repeat,
                                                number)
        out[f"{dim}_observer"] = median_seconds(
            _cycle(lambda s, m=beam, g=grid: m.surface(s, g), frames), repeat, number)
        out[f"{dim}_nearest"] = median_seconds(
            _cycle(lambda s, m=nearest, g=grid: m.surface(s, g), frames), repeat, number)
        if dim == "2d":
            g = np.linspace(-90.0, 90.0, 64)
            xx, yy = np.meshgrid(g, g)
            big = np.column_stack([xx.ravel(), yy.ravel()])
            out["2d_surface_64"] = median_seconds(
                _cycle(lambda s, m=beam, g=big: m.surface(s, g), frames), repeat, number)
    return out


def run(quick: bool) -> list[Figure]:
    rows = speed_accuracy_rows(quick)
    figures = []
    for r in rows:
        if "error" in r:
            continue
        base = next(x for x in rows if x["layout"] == r["layout"] and x["model"] == "nearest")
        figures.append(Figure(
            AREA, f"{r['layout']} {r['model']} s/surface (rms {r['rms_error_mm']:.2g}, max "
                  f"{r['max_error_mm']:.2g} mm)",
            r["seconds_per_surface"], "s", f"{r['layout']} nearest s/surface",
            base["seconds_per_surface"]))
    t = session_frame_seconds(quick)
    budget = 1.0 / (SESSION_FPS * SESSION_SPEEDUP)
    for dim in ("1d", "2d"):
        figures.append(Figure(AREA, f"{dim} beam_profiles/frame vs nearest 19x19 surface",
                              t[f"{dim}_profiles"], "s", f"{dim} nearest surface",
                              t[f"{dim}_nearest"]))
    limit = 4e-4
    figures.append(Figure(AREA, f"2d beam_profiles/frame vs {1e3 * limit:g} ms target",
                          t["2d_profiles"], "s", f"{1e3 * limit:g} ms", limit,
                          "ratio <= 1", t["2d_profiles"] <= limit))
    figures.append(Figure(AREA, "2d beam profiles/frame vs 100x-at-15fps budget",
                          t["2d_profiles"], "s", "budget 1/1500 s", budget, "ratio <= 1",
                          t["2d_profiles"] <= budget))
    figures.append(Figure(AREA, "2d beam profiles + 19x19 surface/frame vs budget",
                          t["2d_observer"], "s", "budget 1/1500 s", budget, "ratio <= 1",
                          t["2d_observer"] <= budget))
    for key, label in (("2d_profiles", "beam_profiles"),
                       ("2d_observer", "beam_profiles + 19x19 surface")):
        speed = 1.0 / (SESSION_FPS * t[key])
        figures.append(Figure(AREA, f"simulated s per wall s, 15 fps, {label}", speed,
                              "x", "100x real time", SESSION_SPEEDUP, "ratio >= 1",
                              speed >= SESSION_SPEEDUP))
    figures.append(Figure(AREA, "2d beam 64x64 surface/frame vs 5 ms", t["2d_surface_64"],
                          "s", "5 ms", 5e-3, "ratio <= 1", t["2d_surface_64"] <= 5e-3))
    return figures
