"""The same answer whatever runs it: this process, a local pool, a Dask cluster (seeds belong
to the unit of work, never to the worker: docs/conventions.md)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.power_analysis import (
    PowerError,
    api,
    backends,
    design_from_protocol,
    model_from_parameters,
    power,
)


@pytest.fixture(scope="module")
def model():
    design = design_from_protocol("digit_identification")
    return model_from_parameters(design, {"pixel-only": 0.5, "crs": 0.56},
                                 participant_sd=0.4, digit_sd=0.4)


STUDIES = 24


def _run(model, **where):
    return power("digit_identification", model=model, participants=4, studies=STUDIES,
                 seed=7, **where)


@pytest.mark.slow
def test_one_job_two_jobs_and_a_dask_cluster_give_identical_results(model, monkeypatch):
    """One point of 24 studies in tasks of 8 and, at the end, 4 (five tasks, so the pools
    and the cluster each share them out; below 20 studies the bootstrap-calibrated p,
    against as many null studies, could never be below 0.05): the same bits everywhere,
    the bootstrap's null studies too. One point is enough: a task computes every point of
    its studies itself (how the points of a chunk hand on their starts is the same in any
    process, and tests/test_power_study.py checks it against the chunking); what differs
    here is the process, the pool or the cluster that runs each task."""
    from distributed import Client, LocalCluster

    monkeypatch.setattr(api, "STUDIES_PER_TASK", 8)
    one = _run(model, jobs=1)
    two = _run(model, jobs=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      **backends.QUIET_SCHEDULER) as cluster:
        by_address = _run(model, scheduler=cluster.scheduler_address)
        with Client(cluster) as client:
            by_client = _run(model, scheduler=client)
    assert one.backend == "this process" and two.backend.startswith("local process pool")
    assert by_address.backend.startswith("dask tcp://127.0.0.1:")
    counts = one.to_frame()["significant"].tolist()
    assert 0 < sum(counts) < STUDIES          # an informative point, not all or nothing
    for other in (two, by_address, by_client):
        assert other.to_frame()["significant"].tolist() == counts
        for key in ("p_value", "theta", "loglike", "null_statistic"):
            assert np.array_equal(other.raw[key], one.raw[key], equal_nan=True)
    assert one.headline() == by_address.headline()


def test_an_unreachable_scheduler_is_one_line_naming_the_option(model, monkeypatch):
    import socket

    with socket.socket() as probe:                # a loopback port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    monkeypatch.setattr(backends, "CONNECT_TIMEOUT", 2.0)
    with pytest.raises(PowerError, match=rf"^--scheduler tcp://127.0.0.1:{port}: cannot "
                                         r"reach a Dask scheduler there"):
        _run(model, scheduler=f"tcp://127.0.0.1:{port}")
    with pytest.raises(PowerError, match=r"^--scheduler: expected a Dask scheduler address"):
        _run(model, scheduler="localhost")


def test_jobs_must_be_a_whole_number(model):
    with pytest.raises(PowerError, match=r"^--jobs: expected a whole number >= 1, got 0"):
        _run(model, jobs=0)


# -- the bench's local cluster starts on a busy machine ---------------------------------------
# tests/test_power_bench.py once failed under load: distributed's "Cluster closed without
# starting up" (a worker not connected within the 30 s default). local_cluster gives the start
# time and tries again; these make the start fail on purpose.

def test_a_local_cluster_has_every_worker_in_its_own_single_threaded_process():
    import os

    with backends.local_cluster(2) as client:
        workers = client.scheduler_info()["workers"]
        assert len(workers) == 2
        seen = client.run(lambda: (os.getpid(), os.environ.get("OMP_NUM_THREADS")))
        assert {pid for pid, _ in seen.values()} - {os.getpid()} == \
            {pid for pid, _ in seen.values()}                      # processes, not threads
        assert {threads for _, threads in seen.values()} == {"1"}
        assert all(w["nthreads"] == 1 for w in workers.values())


def test_a_failed_start_is_tried_again_and_then_said_in_one_line(monkeypatch):
    import distributed

    real, calls = distributed.LocalCluster, []

    def failing_first(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("Cluster failed to start. (injected)")
        return real(*args, **kwargs)

    monkeypatch.setattr(distributed, "LocalCluster", failing_first)
    with backends.local_cluster(1) as client:
        assert len(client.scheduler_info()["workers"]) == 1
        assert client.submit(sum, [1, 2]).result() == 3
    assert len(calls) == 2

    def never(*args, **kwargs):
        raise TimeoutError("no worker (injected)")

    monkeypatch.setattr(distributed, "LocalCluster", never)
    with pytest.raises(PowerError, match=r"did not start in 3 attempts of 180 s \(no worker "
                       r"\(injected\); no worker") as info:
        with backends.local_cluster(1):
            pass
    assert "\n" not in str(info.value)


def test_a_local_cluster_starts_beside_another_program_on_8787(model):
    # the scheduler's HTTP server used to take the dashboard's default port, and warned
    # (an error here) when another cluster or program had it
    import socket

    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            taken.bind(("0.0.0.0", 8787))
        except OSError:
            pass  # someone has it already: the same situation
        else:
            taken.listen()
        with backends.local_cluster(1) as client:
            assert client.submit(sum, [1, 2]).result() == 3


@given(st.integers(1, 5000))
def test_the_units_of_work_cover_every_study_once_the_last_ones_half_size(studies):
    """Units of 50 studies in order, the last two units' worth (and what is left over) in
    units of 25: whatever the workers, the last units to finish are short ones."""
    bounds = [task.studies for task in api._tasks(None, None, 7, (4,), (1,), studies)]
    assert bounds[0][0] == 0 and bounds[-1][1] == studies
    assert all(a[1] == b[0] for a, b in zip(bounds[:-1], bounds[1:], strict=True))
    sizes = [end - start for start, end in bounds]
    assert all(size > 0 for size in sizes)
    whole = [size for size in sizes if size == api.STUDIES_PER_TASK]
    assert sizes[:len(whole)] == whole            # the whole units first
    assert all(size <= api.STUDIES_PER_TASK // 2 for size in sizes[len(whole):])
    assert len(whole) == max(0, studies // api.STUDIES_PER_TASK - 2)


def test_a_worker_imports_the_fits_not_the_reports_and_charts():
    """A spawned worker unpickles its task from crs_study.power_analysis.study: that import
    leaves out matplotlib, the analysis report and the protocol package with the device's
    modules it imports (a second of every worker's start in the timed power point, measured
    with python -X importtime)."""
    code = ("import sys, crs_study.power_analysis.study\n"
            "print(sorted(m for m in ('matplotlib', 'crs_study.analysis.report', "
            "'crs_study.analysis.charts', 'crs_study.power_analysis.api', "
            "'crs_study.protocol', 'crs_study.device', 'serial') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "[]", done.stderr
