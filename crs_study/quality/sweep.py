"""D_P and D_S against d/l for many models and lattices: cached, in parallel.

Each point (model, lattice, d/l) is one :func:`~crs_study.quality.criteria.distortion` call
on a periodic patch at the shipped device's pitch (30 mm; l = d / (d/l)). Points are cached on
disk as JSON, keyed by the point, the numerical settings and a digest of the source of every
module the result depends on, so a changed model recomputes and an unchanged one is read back.
A point that cannot be computed (a model that does not support the lattice, a beam that
collapses) is kept as a :class:`Point` with ``note`` set and no values, never dropped silently.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from crs_study.errors import CrsStudyError
from crs_study.geometry.layout import load_layout
from crs_study.quality.criteria import distortion, symmetric_by_default

#: d/l values of the default sweep: the paper's range, and 0.1, 0.2, 0.3 and 1/3 always.
DEFAULT_D_OVER_L = (0.1, 0.15, 0.2, 0.25, 0.3, 1 / 3, 0.4, 0.5)
DEFAULT_MODELS = ("nearest", "linear", "spline", "beam")



@dataclass(frozen=True)
class Point:
    """One computed (or failed) point of a sweep."""

    layout: str
    model: str
    d_over_l: float
    D_P: float | None = None
    D_S: float | None = None
    positions: int = 0
    note: str = ""

    def row(self) -> dict:
        return {"layout": self.layout, "model": self.model, "d_over_l": self.d_over_l,
                "D_P": self.D_P, "D_S": self.D_S}


@dataclass(frozen=True)
class Settings:
    """Numerical settings of a sweep (part of the cache key)."""

    order: int = 4
    resolution: int = 12
    height_mm: float = 5.0
    #: device file (name or path) whose pitch, beam and skin the periodic patches take; None:
    #: the shipped crs1d / crs2d. Its sha256 keys the cache, so an edited file is recomputed.
    device: str | None = None
    device_sha256: str = ""


def source_digest() -> str:
    """sha256 over the source of the modules a distortion depends on."""
    root = Path(__file__).resolve().parents[1]
    files = sorted([*root.joinpath("display").glob("*.py"), *root.joinpath("quality").glob("*.py"),
                    *root.joinpath("rendering").glob("*.py"), root / "stimuli" / "targets.py",
                    root / "geometry" / "layout.py",
                    *root.joinpath("data", "devices").glob("*.toml")])
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "crs-study" / "quality"


def compute_point(model: str, lattice: str, d_over_l: float, settings: Settings) -> Point:
    """One point; known failures become a note."""
    symmetric = symmetric_by_default(model, lattice)
    order = settings.order if lattice == "1d" or symmetric else max(2, settings.order // 2)
    try:
        template = load_layout(settings.device) if settings.device else None
        result = distortion(model, lattice, d_over_l, template=template,
                            height_mm=settings.height_mm, order=order,
                            resolution=settings.resolution, symmetric=symmetric)
    except CrsStudyError as exc:
        return Point(lattice, model, d_over_l, note=str(exc).splitlines()[0])
    return Point(lattice, model, d_over_l, result.D_P, result.D_S, result.positions)


def _key(model: str, lattice: str, d_over_l: float, settings: Settings, digest: str) -> str:
    text = json.dumps([model, lattice, round(d_over_l, 12), asdict(settings), digest])
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _task(args: tuple) -> Point:
    return compute_point(*args)


#: BLAS thread variables; a worker computes many small dense problems, where BLAS threads
#: only oversubscribe the cores (measured: the default sweep with 2 workers takes 10 s with
#: threaded OpenBLAS forked into them, 3.6 s with fresh single-threaded workers)
_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _single_threaded_blas():
    """Workers spawned inside start with BLAS at one thread (they read the environment)."""
    saved = {k: os.environ.get(k) for k in _BLAS_THREADS}
    os.environ.update({k: "1" for k in _BLAS_THREADS})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def sweep(models: Sequence[str], lattices: Sequence[str], d_over_l: Iterable[float],
          settings: Settings = Settings(), cache_dir: Path | None = None, jobs: int = 1
          ) -> list[Point]:
    """Every (model, lattice, d/l) point, from the cache where present, else computed."""
    d_values = sorted(set(float(x) for x in d_over_l))
    wanted = [(m, lat, x) for m in models for lat in lattices for x in d_values]
    digest = source_digest() if cache_dir is not None else ""
    found: dict[tuple, Point] = {}
    if cache_dir is not None:
        for m, lat, x in wanted:
            path = cache_dir / f"{_key(m, lat, x, settings, digest)}.json"
            try:
                found[(m, lat, x)] = Point(**json.loads(path.read_text()))
            except (OSError, ValueError, TypeError):
                pass
    # the dearest points first, so parallel workers finish together: 2D cost ~ (l/d)^2, and
    # beam models (solves, fabric) cost far more than the pixel models
    def cost(w: tuple) -> float:
        model, lattice, x = w
        heavy = model not in ("nearest", "linear")
        return (1.0 if lattice == "1d" else x**-2) * (20.0 if heavy else 1.0)

    todo = sorted((w for w in wanted if w not in found), key=cost, reverse=True)
    tasks = [(m, lat, x, settings) for m, lat, x in todo]
    if jobs > 1 and len(tasks) > 1:
        with _single_threaded_blas(), ProcessPoolExecutor(
                max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            computed = list(pool.map(_task, tasks))
    else:
        computed = [_task(t) for t in tasks]
    for (m, lat, x), point in zip(todo, computed, strict=True):
        found[(m, lat, x)] = point
        if cache_dir is not None:
            cache_dir.mkdir(parents=True, exist_ok=True)
            path = cache_dir / f"{_key(m, lat, x, settings, digest)}.json"
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(asdict(point)))
            os.replace(tmp, path)
    return [found[w] for w in wanted]
