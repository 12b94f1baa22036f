"""Bench area ``render``: time to render one frame (target -> setpoints) per condition.

Baseline, measured in the same run: sampling the target at the pixels alone
(``Bump.height`` on the pixel positions), the least any condition must do. The CRS condition
adds one arc-length integral per beam; the figure is the median per-frame time and its ratio
to the baseline. Target: a 2D CRS frame well under a millisecond (a rounding error beside
the 67 ms a full frame spends on the 9600-baud wire), here <= 100 us (a tenth of it; about
45 us on a quiet machine with the renderer's feed cap).
"""

from __future__ import annotations

import numpy as np

from crs_study.benchmarks import Figure, median_seconds
from crs_study.geometry.layout import load_layout
from crs_study.rendering.render import Renderer
from crs_study.stimuli.targets import Bump

AREA = "render"
DESCRIPTION = "median time to render one frame (target -> setpoints), per device and condition"

#: Median per-frame budget for a 2D CRS frame (s).
TARGET_2D_CRS_S = 100e-6


def run(quick: bool) -> list[Figure]:
    repeat, number = (5, 200) if quick else (15, 2000)
    rng = np.random.default_rng(0)
    figures = []
    for device in ("crs2d", "crs1d"):
        layout = load_layout(device)
        centres = rng.uniform(-45.0, 45.0, size=(64, 2))
        bumps = [Bump((float(x), float(y)), 90.0, 5.0) for x, y in centres]
        cycle = iter(range(10**12))

        def baseline(bumps=bumps, layout=layout, cycle=cycle):
            bumps[next(cycle) % 64].height(layout.pixel_xy)

        base = median_seconds(baseline, repeat, number)
        for condition in ("pixel-only", "crs"):
            renderer = Renderer(layout, condition)

            def frame(renderer=renderer, bumps=bumps, cycle=cycle):
                renderer.render(bumps[next(cycle) % 64])

            seconds = median_seconds(frame, repeat, number)
            checked = device == "crs2d" and condition == "crs"
            figures.append(Figure(
                area=AREA,
                name=f"{device} {condition} frame ({layout.n_actuators} setpoints)",
                value=seconds * 1e6, unit="us",
                baseline_name="pixel heights alone", baseline=base * 1e6,
                target=f"<= {TARGET_2D_CRS_S * 1e6:g} us" if checked else "",
                passed=(seconds <= TARGET_2D_CRS_S) if checked else None,
            ))
    return figures
