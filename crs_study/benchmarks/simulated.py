"""Bench area ``simulated``: what a frame costs on the simulated device, and how fast it runs.

Figures (virtual clock, 2D device, the default protocol's ten digit stimuli, CRS condition):

* per-frame cost of ``send`` + ``displayed_setpoints`` in a dry-run session, where each
  digit's stimulus recurs (encoded and decoded frames are remembered by content); target
  <= 50 us. Baseline: encoding the two controllers' full frames with the codec alone, the
  least a serial send does.
* the same for a first presentation (caches cleared before every frame), and for the worst
  case, every channel changing every frame (informative).
* simulated seconds per wall second for a 15 frames/s stream, against real time (1 s/s);
  target ratio >= 100.
"""

from __future__ import annotations

import time

from crs_study.benchmarks import Figure, median_seconds

AREA = "simulated"
DESCRIPTION = "simulated device: per-frame cost of send + displayed_setpoints, speed vs real time"

#: Median per-frame budget of send + displayed_setpoints in a dry-run (s).
TARGET_FRAME_S = 50e-6
#: Least simulated seconds per wall second for a 15 frames/s stream.
TARGET_SPEEDUP = 100.0
FRAME_RATE_HZ = 15.0


def _digit_frames():
    import numpy as np

    from crs_study.paths import shipped_file
    from crs_study.protocol import load_protocol
    from crs_study.render import Renderer
    from crs_study.stimulus import make_stimulus, render_frames

    protocol = load_protocol(shipped_file("protocols/digit_identification.toml"))
    layout = protocol.layout()
    renderer = Renderer(layout, "crs")
    neutral = layout.neutral_setpoints()[None, :]
    frames = [np.vstack([render_frames(make_stimulus(protocol, layout, d), renderer), neutral])
              for d in range(10)]
    return layout, np.vstack(frames)


def run(quick: bool) -> list[Figure]:
    import numpy as np

    from crs_study.clock import VirtualClock
    from crs_study.device.simulated import SimulatedDevice

    repeat = 5 if quick else 11
    layout, frames = _digit_frames()
    n = len(frames)
    clock = VirtualClock()
    device = SimulatedDevice.from_url("sim://", layout, clock)
    device.open()
    split, pulse_map = device.builder.split, device.builder.pulse_map
    full = [np.arange(len(m)) for m in split.members]
    all_pulses = pulse_map.to_pulses(frames)
    step = 1.0 / FRAME_RATE_HZ
    cursor = iter(range(10**12))

    def encode_alone():
        pulses = all_pulses[next(cursor) % n]
        for c in range(len(full)):
            split.frame(c, pulses, full[c], 67)

    def session_frame():
        device.send(frames[next(cursor) % n])
        device.displayed_setpoints()
        clock.advance(step)

    def first_presentation():
        device.clear_caches()
        session_frame()

    rng = np.random.default_rng(0)
    noisy = rng.uniform(0.0, layout.travel_mm, (256, layout.n_actuators))
    noisy[:, [b.start_servo for b in layout.beams] + [b.end_servo for b in layout.beams]] = \
        rng.uniform(0.0, layout.boundary_travel_mm, (256, 2 * len(layout.beams)))

    def worst_case():
        device.clear_caches()
        device.send(noisy[next(cursor) % 256])
        device.displayed_setpoints()
        clock.advance(step)

    base = median_seconds(encode_alone, repeat, 200)
    for _ in range(n):  # one pass through every digit: the session's steady state
        session_frame()
    steady = median_seconds(session_frame, repeat, n)
    cold = median_seconds(first_presentation, repeat, 100)
    worst = median_seconds(worst_case, repeat, 100)

    # simulated seconds per wall second: a whole pass of the ten digits at 15 frames/s
    walls = []
    for _ in range(repeat):
        start_sim, start = clock.now(), time.perf_counter()
        for _ in range(n):
            session_frame()
        walls.append((clock.now() - start_sim) / (time.perf_counter() - start))
    speed = float(np.median(walls))

    name = f"{layout.name} send + displayed_setpoints"
    baseline = "codec encoding of both full frames alone"
    return [
        Figure(AREA, f"{name}, dry-run session (digits recur)", steady * 1e6, "us", baseline,
               base * 1e6, target=f"<= {TARGET_FRAME_S * 1e6:g} us",
               passed=steady <= TARGET_FRAME_S),
        Figure(AREA, f"{name}, first presentation (no remembered frames)", cold * 1e6, "us",
               baseline, base * 1e6),
        Figure(AREA, f"{name}, every channel changing, no remembered frames", worst * 1e6,
               "us", baseline, base * 1e6),
        Figure(AREA, f"simulated s per wall s at {FRAME_RATE_HZ:g} frames/s", speed, "s/s",
               "real time", 1.0, target=f"ratio >= {TARGET_SPEEDUP:g}",
               passed=speed >= TARGET_SPEEDUP),
    ]
