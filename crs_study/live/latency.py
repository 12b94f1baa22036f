"""Latency figures: median, 95th and 99th percentiles of a set of delays.

Percentiles are numpy's default (linear interpolation between order statistics, Hyndman and
Fan's definition 7, as R's ``quantile`` type 7). Values are kept in seconds; ``to_json`` gives
milliseconds, the unit the targets are stated in.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Summary:
    """Count, median, 95th and 99th percentile, largest (s); NaN when there are no values."""

    n: int
    median: float
    p95: float
    p99: float
    max: float

    @classmethod
    def of(cls, values: Iterable[float]) -> Summary:
        v = np.asarray(values if isinstance(values, np.ndarray) else list(values), dtype=float)
        v = v[np.isfinite(v)]
        if not len(v):
            return cls(0, math.nan, math.nan, math.nan, math.nan)
        p50, p95, p99 = np.percentile(v, [50, 95, 99])
        return cls(len(v), float(p50), float(p95), float(p99), float(v.max()))

    def to_json(self, scale: float = 1e3) -> dict:
        """Milliseconds (``null`` where there are no values); ``scale=1``: the values as they
        are (a ratio), keys without ``_ms``."""
        def out(x: float) -> float | None:
            return None if math.isnan(x) else round(x * scale, 6)

        unit = "_ms" if scale == 1e3 else ""
        return {"n": self.n, f"median{unit}": out(self.median), f"p95{unit}": out(self.p95),
                f"p99{unit}": out(self.p99), f"max{unit}": out(self.max)}

    def describe(self) -> str:
        if not self.n:
            return "-"
        return (f"{self.median * 1e3:6.1f} {self.p95 * 1e3:6.1f} {self.p99 * 1e3:6.1f}"
                f" {self.max * 1e3:6.1f}")


class Series:
    """A growing column of float values (compact: 8 bytes a value)."""

    def __init__(self) -> None:
        self.values = array("d")

    def add(self, value: float | None) -> None:
        self.values.append(math.nan if value is None else float(value))

    def __len__(self) -> int:
        return len(self.values)

    def array(self) -> np.ndarray:
        return np.frombuffer(self.values, dtype=float).copy() if self.values else np.zeros(0)

    def summary(self, last: int | None = None) -> Summary:
        data = self.array()
        return Summary.of(data if last is None else data[-last:])
