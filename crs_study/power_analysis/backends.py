"""Where the units of work run: this process, a local process pool, or a Dask cluster.

:func:`map_tasks` maps one pure function over the tasks and returns the results in the
tasks' order, whatever order they finish in. The function and each task are the same on
every backend, and a task carries its own seeds (:mod:`crs_study.power_analysis.simulate`), so the
answer is the same wherever it ran (seeds belong to the unit of work, never to the worker:
docs/conventions.md; Dask's ``client.map``, numpy's ``SeedSequence``).

* ``jobs = 1``, no scheduler: in this process, one task after another;
* ``jobs > 1``: a :class:`concurrent.futures.ProcessPoolExecutor` of ``jobs`` spawned
  processes (each with single-threaded BLAS, so the pool does not oversubscribe the cores);
* ``scheduler``: a Dask distributed scheduler's address (``tcp://HOST:8786``) or a
  :class:`distributed.Client`; every worker needs crs-study installed (the same version).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from crs_study.power_analysis.design import PowerError
from crs_study.signals import die_with_parent

#: Progress callback: (units of work done, units in all, seconds elapsed).
Progress = Callable[[int, int, float], None]

_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: glibc's allocator in the worker processes (mallopt(3): the environment's
#: ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``; other C libraries ignore them).
#: The fits' temporaries of a few hundred kB were each mapped from the kernel and unmapped
#: again, a page fault per 4 kB touched: on 200 studies of the shipped protocol at 12
#: participants with the bootstrap's null studies (2 workers) 630,000 minor faults and 2.4-2.6
#: s of system time, against 147,000 and 0.8-0.9 s with blocks up to 32 MB kept in the heap
#: and up to 256 MB of freed heap kept for the next evaluation.
_ALLOCATOR = {"MALLOC_MMAP_THRESHOLD_": str(32 * 2**20),
              "MALLOC_TRIM_THRESHOLD_": str(256 * 2**20)}
#: Seconds to wait for a Dask scheduler before saying it cannot be reached.
CONNECT_TIMEOUT = 10.0


class Backend:
    """An open backend: this process, a process pool or a Dask client, kept for several
    maps (the pool's processes start once). Use as a context manager (:func:`open_backend`).
    """

    def __init__(self, jobs: int = 1, scheduler: Any = None):
        if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
            raise PowerError(f"--jobs: expected a whole number >= 1, got {jobs!r}")
        self.jobs, self.scheduler = jobs, scheduler
        self.pool = self.client = None
        self._owned = False
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> Backend:
        if self.scheduler is not None:
            self.client, self._owned = connect(self.scheduler)
        elif self.jobs > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._stack.enter_context(single_threaded_blas())
            # a SIGKILL of this process ends the workers too (the parent-death signal)
            self.pool = self._stack.enter_context(ProcessPoolExecutor(
                max_workers=self.jobs, mp_context=multiprocessing.get_context("spawn"),
                initializer=die_with_parent, initargs=(os.getpid(),)))
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self.client is not None and self._owned:
            self.client.close()
        self._stack.close()

    def map(self, function: Callable[[Any], Any], tasks: Sequence[Any],
            progress: Progress | None = None,
            weight: Callable[[Any], int] = lambda task: 1) -> list[Any]:
        """``[function(t) for t in tasks]`` in the tasks' order; ``progress`` is called after
        each task with the summed ``weight`` of the tasks done."""
        total = sum(weight(t) for t in tasks)
        start = time.perf_counter()
        results: list[Any] = [None] * len(tasks)
        done = 0
        for index, result in self._completed(function, tasks):
            results[index] = result
            done += weight(tasks[index])
            if progress:
                progress(done, total, time.perf_counter() - start)
        return results

    def runs_here(self, tasks: Sequence[Any]) -> bool:
        """Whether :meth:`map` runs ``tasks`` in this process (no scheduler, and no pool or a
        single task)."""
        return self.client is None and (self.pool is None or len(tasks) <= 1)

    def cpu_elsewhere(self, tasks: Sequence[Any], seconds: Sequence[float]) -> float:
        """The CPU seconds ``tasks`` took outside this process, given each one's own
        ``seconds``: none when they ran here, where this process's CPU time holds them."""
        return 0.0 if self.runs_here(tasks) else float(sum(seconds))

    def _completed(self, function, tasks) -> Iterator[tuple[int, Any]]:
        if self.client is not None:
            yield from _dask(self.client, function, tasks)
        elif not self.runs_here(tasks):
            yield from _pool(self.pool, function, tasks)
        else:
            for index, task in enumerate(tasks):
                yield index, function(task)

    def describe(self) -> str:
        """The backend in a few words (for the result's JSON)."""
        if self.client is not None:
            return f"dask {self.client.scheduler.address}"
        return "this process" if self.pool is None else f"local process pool, {self.jobs} jobs"


def open_backend(jobs: int = 1, scheduler: Any = None) -> Backend:
    """``with open_backend(jobs, scheduler) as backend: backend.map(...)``."""
    return Backend(jobs, scheduler)


def map_tasks(function: Callable[[Any], Any], tasks: Sequence[Any], *, jobs: int = 1,
              scheduler: Any = None, progress: Progress | None = None,
              weight: Callable[[Any], int] = lambda task: 1) -> list[Any]:
    """One map on a backend opened for it (see :class:`Backend`)."""
    with open_backend(jobs, scheduler) as backend:
        return backend.map(function, tasks, progress, weight)


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Processes started inside see one BLAS thread each, and keep their freed memory for
    the next fit (:data:`_ALLOCATOR`); the environment is restored afterwards."""
    setting = {**dict.fromkeys(_THREAD_VARIABLES, "1"), **_ALLOCATOR}
    saved = {name: os.environ.get(name) for name in setting}
    os.environ.update(setting)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _pool(pool, function, tasks) -> Iterator[tuple[int, Any]]:
    from concurrent.futures import as_completed

    futures = {pool.submit(function, task): index for index, task in enumerate(tasks)}
    try:
        for future in as_completed(futures):
            yield futures[future], future.result()
    except BaseException:
        for future in futures:
            future.cancel()
        raise


def check_address(address: object) -> tuple[str, int]:
    """``(host, port)`` of a ``tcp://HOST:PORT`` scheduler address, or a one-line
    :class:`PowerError` naming ``--scheduler``, before any connection is tried.

    Only plain TCP: a ``tls://`` scheduler needs certificates (a ``distributed.Security``)
    that the command line does not take, ``ucx://`` a transport library, and ``inproc://``
    lives in another process's memory; handing those to ``Client`` ended in an uncaught
    error, or in a 20 s stall and a traceback from the half-made client's ``__del__``.
    (A ``Client`` made in Python, with its security, is taken as it is.)
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    # (a control character would break the one-line error)
    if not isinstance(address, str) or "://" not in address or not address.isprintable():
        raise PowerError(f"--scheduler: expected a Dask scheduler address such as "
                         f"tcp://HOST:8786, got {address!r}")
    try:
        protocol, location = parse_address(address, strict=True)
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise PowerError(f"--scheduler {address}: not a scheduler address ({exc!s:.200}); "
                         "expected tcp://HOST:PORT, such as tcp://127.0.0.1:8786") from None
    if protocol != "tcp":
        why = ("it needs certificates: pass a distributed.Client made with them from Python"
               if protocol == "tls" else "a Dask scheduler listens on tcp://")
        raise PowerError(f"--scheduler {address}: {protocol}:// is not supported here ({why}); "
                         "expected tcp://HOST:PORT")
    if not host or " " in host or not 1 <= port <= 65535:
        raise PowerError(f"--scheduler {address}: expected tcp://HOST:PORT with a host and "
                         f"a port from 1 to 65535, got host {host!r} and port {port!r}")
    return host, port


def connect(scheduler: Any, timeout: float | None = None):
    """``(client, owned)``: a :class:`distributed.Client` for ``scheduler`` (an address, or a
    client taken as it is); an unreachable address is a :class:`PowerError` naming
    ``--scheduler``."""
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - a dependency of crs-study
        raise PowerError(f"--scheduler needs the dask[distributed] packages ({exc})") from None
    if isinstance(scheduler, Client):
        return scheduler, False
    check_address(scheduler)
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT if timeout is None else timeout,
                      set_as_default=False), True
    except (OSError, TimeoutError, ValueError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PowerError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there "
                         f"({reason})") from None


#: Seconds a local cluster's worker may take to start and reach its scheduler. Distributed's
#: default (30 s to connect) is short for a 2-core machine busy with other work, where a
#: spawned worker importing numpy, scipy and statsmodels can take longer than that.
LOCAL_START_TIMEOUT = 180.0
#: Starts of a local cluster tried before giving up (a start that fails measures nothing).
LOCAL_START_ATTEMPTS = 3


#: A LocalCluster's scheduler without the dashboard, and its HTTP server (health and metrics
#: routes, started even without the dashboard) on a free port: on its default, 8787, a second
#: cluster on the machine (another power run, another test process) gets a "Port 8787 is
#: already in use" warning, an error where warnings are errors.
QUIET_SCHEDULER = {"dashboard_address": None,
                   "scheduler_kwargs": {"dashboard_address": "127.0.0.1:0"}}


@contextlib.contextmanager
def local_cluster(workers: int, *, timeout: float = LOCAL_START_TIMEOUT,
                  attempts: int = LOCAL_START_ATTEMPTS) -> Iterator[Any]:
    """A :class:`distributed.Client` of a Dask ``LocalCluster`` on loopback with ``workers``
    worker processes of one thread each (single-threaded BLAS, as the process pool's), every
    worker started and connected before it is yielded; closed afterwards.

    Processes, not threads: each worker must use a core of its own (the fits hold the GIL in
    Python code), or ``workers`` would not measure what that many machines do. Starting is
    not part of any measurement, so a slow start gets ``timeout`` seconds (to connect and for
    every worker to arrive) and a failed one (distributed's "Cluster closed without starting
    up") is tried again, ``attempts`` times in all, before it is a :class:`PowerError`.
    """
    import dask
    from distributed import Client, LocalCluster

    seconds = f"{timeout:g}s"
    failures: list[str] = []
    with dask.config.set({"distributed.comm.timeouts.connect": seconds,
                          "distributed.comm.timeouts.tcp": seconds}), single_threaded_blas():
        for _ in range(attempts):
            with contextlib.ExitStack() as stack:
                try:
                    cluster = stack.enter_context(LocalCluster(
                        n_workers=workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", **QUIET_SCHEDULER))
                    client = stack.enter_context(Client(cluster, timeout=timeout,
                                                        set_as_default=False))
                    client.wait_for_workers(workers, timeout=timeout)
                except (OSError, RuntimeError, TimeoutError) as exc:
                    failures.append(str(exc).splitlines()[0] if str(exc)
                                    else type(exc).__name__)
                    continue
                yield client
                return
    raise PowerError(f"a local Dask cluster of {workers} worker(s) did not start in "
                     f"{attempts} attempts of {timeout:g} s ({'; '.join(failures)})")


def _dask(client, function, tasks) -> Iterator[tuple[int, Any]]:
    from distributed import as_completed

    futures = client.map(function, list(tasks), pure=False)
    index = {future.key: i for i, future in enumerate(futures)}
    try:
        for future in as_completed(futures, loop=client.loop):
            yield index[future.key], future.result()
    except BaseException:
        client.cancel(futures)
        raise
