"""Does a reanalysis give the numbers an earlier one wrote? ``results.json`` against a new one.

A reviewer, years later, reruns the analysis of a stored dataset and wants to know whether
the numbers are the ones published. :func:`compare_results` walks an earlier ``results.json``
and a new one side by side and lists every place they differ; ``crs-study analyze DATASET
--check RESULTS`` and :meth:`Analysis.compare <crs_study.analysis.report.Analysis.compare>`
use it.

What is compared
    Every value of both files, in the same place: numbers within ``rtol`` of each other
    (relative to the larger, with ``atol`` near 0; the GLMM's maximiser stops within ~1e-8 of
    its optimum, so bit-for-bit equality would fail across BLAS builds while the published
    digits hold); whole numbers in both files (counts, seeds) and everything else exactly; a
    key or list item present in one file only as a difference. The datasets' paths are
    compared as written relative to each dataset (an absolute path names the machine, not the
    data).

What is not
    Where and when the analysis ran and with what it drew: ``generated_at``, the ``charts``
    list (file names, present only once written) and ``software`` (reported beside the
    verdict: a reanalysis with a newer crs-study is the usual case, and its numbers are what
    is in question). A different analysis plan is a difference (``plan.sha256``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from crs_study._display import Display, Displayed
from crs_study._files import not_a_regular_file
from crs_study.errors import AnalysisError

#: The tolerance of ``--check`` (relative; see the module docstring).
DEFAULT_RTOL = 1e-6
#: Below this a number counts as 0 in the comparison.
DEFAULT_ATOL = 1e-12
#: Keys of results.json that say where, when and with what the analysis ran.
NOT_RESULTS = ("generated_at", "charts", "software")
#: Differences printed before "and N more".
SHOWN = 10


@dataclass(frozen=True)
class Difference:
    """One place where the two files differ: a JSON path (``primary.model.coefficients``)
    and the two values (``None`` where one file has nothing there)."""

    where: str
    earlier: object
    now: object

    def describe(self) -> str:
        return f"{self.where}: {_short(self.earlier)} then, {_short(self.now)} now"


@dataclass(frozen=True, repr=False)
class ResultsComparison(Displayed):
    """The verdict of :func:`compare_results`."""

    differences: tuple[Difference, ...]
    compared: int  # values compared
    largest_relative: float  # largest relative difference among numbers within tolerance
    rtol: float
    software_then: str
    software_now: str

    @property
    def same(self) -> bool:
        return not self.differences

    def _display(self) -> Display:
        rows = [("verdict", "the same numbers" if self.same else
                 f"{len(self.differences)} of {self.compared} values differ"),
                ("values compared", str(self.compared)), ("tolerance", f"relative {self.rtol:g}")]
        rows += [(d.where, f"{_short(d.earlier)} then, {_short(d.now)} now")
                 for d in self.differences[:SHOWN]]
        return Display("ResultsComparison", tuple(rows), (), ".describe(), .to_dict()")

    def describe(self) -> str:
        """A sentence, then one line per difference (at most :data:`SHOWN`)."""
        versions = (f"crs-study {self.software_then} then, {self.software_now} now"
                    if self.software_then != self.software_now
                    else f"crs-study {self.software_now} both times")
        if self.same:
            return (f"the same numbers: {self.compared} values agree within a relative "
                    f"{self.rtol:g} (largest difference {self.largest_relative:.1e}; "
                    f"{versions})")
        lines = [f"the numbers differ in {len(self.differences)} of {self.compared} values "
                 f"(tolerance: relative {self.rtol:g}; {versions}):"]
        lines += [f"  {d.describe()}" for d in self.differences[:SHOWN]]
        if len(self.differences) > SHOWN:
            lines.append(f"  and {len(self.differences) - SHOWN} more")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"same": self.same, "compared": self.compared, "rtol": self.rtol,
                "largest_relative_difference": self.largest_relative,
                "software": {"then": self.software_then, "now": self.software_now},
                "differences": [{"where": d.where, "then": d.earlier, "now": d.now}
                                for d in self.differences]}


def read_results(path: str | Path) -> dict:
    """An earlier ``results.json`` (a one-line :class:`AnalysisError` when it is not one)."""
    path = Path(path)
    why = not_a_regular_file(path)
    if why is not None:
        raise AnalysisError(f"{path}: cannot read the earlier results ({why})")
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise AnalysisError(f"{path}: not a results.json ({type(exc).__name__}: "
                            f"{str(exc).splitlines()[0] if str(exc) else 'unreadable'})"
                            ) from None
    if not isinstance(content, dict) or "headline" not in content or "primary" not in content:
        raise AnalysisError(f"{path}: not a results.json of crs-study analyze (no headline "
                            "or primary result)")
    return content


def compare_results(earlier: dict, now: dict, rtol: float = DEFAULT_RTOL,
                    atol: float = DEFAULT_ATOL) -> ResultsComparison:
    """Every place where ``now`` differs from ``earlier`` (module docstring)."""
    check_tolerance(rtol, atol)
    walk = _Walk(rtol, atol)
    walk.compare("", _without_provenance(earlier), _without_provenance(now))
    return ResultsComparison(tuple(walk.differences), walk.compared, walk.largest, rtol,
                             _version(earlier), _version(now))


def check_tolerance(rtol: float, atol: float = DEFAULT_ATOL) -> None:
    """A one-line :class:`AnalysisError` unless ``0 <= rtol < 1`` and ``atol >= 0``."""
    if not (_number(rtol) and math.isfinite(rtol) and 0 <= rtol < 1) \
            or not (_number(atol) and math.isfinite(atol) and atol >= 0):
        raise AnalysisError(f"tolerance: expected 0 <= relative < 1 and absolute >= 0, got "
                            f"{rtol!r} and {atol!r}")


def _without_provenance(results: dict) -> dict:
    """``results`` without :data:`NOT_RESULTS`, each dataset's absolute path (in its entry
    and inside any text, a warning naming a file) replaced by the dataset folder's name."""
    kept = {k: v for k, v in results.items() if k not in NOT_RESULTS}
    places = [d["path"] for d in kept.get("datasets") or []
              if isinstance(d, dict) and isinstance(d.get("path"), str) and d["path"]]
    # the longest first: a dataset folder inside another's is replaced whole
    moves = [(place, Path(place).name) for place in sorted(places, key=len, reverse=True)]

    def relative(value: object) -> object:
        if isinstance(value, str):
            for place, name in moves:
                value = value.replace(place, name)
            return value
        if isinstance(value, dict):
            return {k: relative(v) for k, v in value.items()}
        if isinstance(value, list):
            return [relative(v) for v in value]
        return value

    return relative(kept)  # type: ignore[return-value]


def _version(results: dict) -> str:
    software = results.get("software")
    return str(software.get("version", "?")) if isinstance(software, dict) else "?"


class _Walk:
    def __init__(self, rtol: float, atol: float) -> None:
        self.rtol, self.atol = rtol, atol
        self.differences: list[Difference] = []
        self.compared = 0
        self.largest = 0.0

    def compare(self, where: str, earlier: object, now: object) -> None:
        if isinstance(earlier, dict) and isinstance(now, dict):
            for key in list(earlier) + [k for k in now if k not in earlier]:
                self.compare(f"{where}.{key}" if where else str(key), earlier.get(key),
                             now.get(key))
            return
        if isinstance(earlier, list) and isinstance(now, list):
            for i in range(max(len(earlier), len(now))):
                self.compare(f"{where}[{i}]", earlier[i] if i < len(earlier) else None,
                             now[i] if i < len(now) else None)
            return
        self.compared += 1
        if isinstance(earlier, int) and isinstance(now, int) and not (
                isinstance(earlier, bool) or isinstance(now, bool)):
            if earlier != now:  # counts and seeds: exact (a seed's last digits are beyond a
                self.differences.append(Difference(where, earlier, now))  # float's)
            return
        if _number(earlier) and _number(now):
            gap = abs(float(earlier) - float(now))
            scale = max(abs(float(earlier)), abs(float(now)))
            if gap <= self.atol or earlier == now:
                return
            relative = gap / scale
            if relative <= self.rtol:
                self.largest = max(self.largest, relative)
                return
        elif earlier == now and type(earlier) is type(now):
            return
        self.differences.append(Difference(where, earlier, now))


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _short(value: object) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
