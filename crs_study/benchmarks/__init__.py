"""Benchmarks run by ``crs-study bench``.

Each module here provides ``AREA`` (a short name, e.g. ``"render"``), ``DESCRIPTION`` and
``run(quick: bool)``, an iterable of :class:`Figure` (an area whose figures take minutes
yields each as it is measured, so ``crs-study bench`` prints it then and an interrupted run
keeps what it measured). Every figure is a ratio against a baseline measured in the same run
on the same machine, so numbers from a noisy two-core laptop stay comparable; timings are
medians of repeats.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Figure:
    """One benchmark figure: ``value`` against ``baseline`` (same unit), and the target."""

    area: str
    name: str
    value: float
    unit: str
    baseline_name: str
    baseline: float
    target: str = ""  # e.g. "ratio >= 100"; empty when the figure is informative only
    passed: bool | None = None  # None when there is no target

    @property
    def ratio(self) -> float:
        return self.value / self.baseline if self.baseline else float("inf")

    def to_dict(self) -> dict:
        return {**asdict(self), "ratio": self.ratio}


def median_seconds(func: Callable[[], object], repeat: int = 7, number: int = 1,
                   timer: Callable[[], float] = time.perf_counter) -> float:
    """Median time (s) of ``number`` calls of ``func``, over ``repeat`` repeats, per call.

    ``timer`` is wall time by default; ``time.process_time`` gives CPU time, which a loaded
    machine inflates less (other processes' time is not counted).
    """
    times = []
    for _ in range(repeat):
        start = timer()
        for _ in range(number):
            func()
        times.append((timer() - start) / number)
    return statistics.median(times)
