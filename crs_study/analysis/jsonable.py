"""Tables and results as plain JSON: what ``results.json`` and every ``to_json()`` write.

A result object's ``to_dict()`` holds its numbers as Python and numpy values, NaN where a
number does not exist (a median of no trials); :func:`to_jsonable` makes them plain JSON
(NaN and infinities as ``null``, their key paths returned so that ``results.json`` can say
where), and :func:`json_text` writes the text.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd


def records(table: pd.DataFrame) -> list[dict]:
    """Rows as dicts; an empty cell (NaN: a median of no trials, say) becomes None, which the
    table's own counts explain (``n = 0``, ``n_trials = 0``)."""
    return table.astype(object).where(table.notna(), None).to_dict("records")


def to_jsonable(value, path: str = "") -> tuple[object, list[str]]:
    """Plain JSON types; NaN and infinities become null and their key paths are returned."""
    bad: list[str] = []

    def walk(v, where):
        if isinstance(v, dict):
            return {str(k): walk(x, f"{where}.{k}" if where else str(k)) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]
        if isinstance(v, np.generic):
            v = v.item()
        if v is pd.NA or v is pd.NaT:
            return None
        if isinstance(v, float) and not math.isfinite(v):
            bad.append(where)
            return None
        if isinstance(v, Path):
            return str(v)
        return v

    return walk(value, path), bad


def json_text(value) -> str:
    """``value`` as indented JSON text (non-finite numbers as null), with a final newline."""
    return json.dumps(to_jsonable(value)[0], indent=2, allow_nan=False) + "\n"
