"""The same answer whatever runs it: this process, a local pool, a Dask cluster (STYLE.md
point 18: seeds belong to the unit of work, never to the worker)."""

from __future__ import annotations

import numpy as np
import pytest

from crs_study.power_analysis import (
    PowerError,
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


def _run(model, **where):
    return power("digit_identification", model=model, participants="4:12:4", studies=120,
                 seed=7, **where)


def test_one_job_two_jobs_and_a_dask_cluster_give_identical_results(model):
    from distributed import Client, LocalCluster

    one = _run(model, jobs=1)
    two = _run(model, jobs=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        by_address = _run(model, scheduler=cluster.scheduler_address)
        with Client(cluster) as client:
            by_client = _run(model, scheduler=client)
    assert one.backend == "this process" and two.backend.startswith("local process pool")
    assert by_address.backend.startswith("dask tcp://127.0.0.1:")
    counts = one.to_frame()["significant"].tolist()
    assert 0 < sum(counts) < 3 * 120          # an informative curve, not all or nothing
    for other in (two, by_address, by_client):
        assert other.to_frame()["significant"].tolist() == counts
        for key in ("p_value", "theta", "loglike"):
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
