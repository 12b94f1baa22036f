"""``crs-study power`` under attack: SIGKILL with local workers or a Dask cluster leaves no
process and no client behind and a rerun gives the same curve; scheduler addresses and absurd
options are one line before any work; the CPU time is counted once. Tiny settings (the pilot
protocol, a few studies) keep each case to seconds of work."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crs_study.cli import main
from crs_study.power_analysis import power

TINY = ["--draws", "2", "--studies", "4", "--participants", "2,3", "--seed", "5"]


def command(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "crs_study", "power", "pilot", *TINY, "--out", str(out),
            "--json", *extra]


def curve(data: dict) -> list[tuple]:
    return [(p["participants"], p["significant"], p["power"]) for p in data["points"]]


@pytest.fixture(scope="module")
def uninterrupted() -> list[tuple]:
    """The curve of the tiny run, in this process with one job."""
    result = power("pilot", draws=2, studies=4, participants="2,3", seed=5, jobs=1)
    return curve(json.loads(result.to_json()))


def descendants(pid: int) -> set[int]:
    """Every living process below ``pid`` (from /proc)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[0] != "Z":
                parents[int(entry.name)] = int(fields[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier}
        found |= frontier
    return found


def alive(pid: int) -> bool:
    """``pid`` runs (a zombie, or a process gone, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def kill_all(pids) -> None:
    """SIGKILL what the test started and is still there (a failed test leaves nothing)."""
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def wait_for(condition, seconds: float, what: str):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what} within {seconds} s")


@pytest.mark.slow
@pytest.mark.timeout(1200)  # a busy machine: three power processes start (imports alone 10 s)
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_sigkill_of_power_with_two_jobs_leaves_no_worker_and_a_rerun_gives_the_curve(
        tmp_path, uninterrupted):
    child = subprocess.Popen(command(tmp_path / "killed", "--jobs", "2"),
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        workers = wait_for(lambda: (lambda d: d if len(d) >= 2 else None)(
            descendants(child.pid)), 120, "two workers started")
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
        wait_for(lambda: not descendants(child.pid) and not any(map(alive, workers)), 30,
                 "every worker (and the resource tracker) gone")
    finally:
        kill_all(descendants(child.pid) | {child.pid} | set(locals().get("workers", ())))
    again = subprocess.run(command(tmp_path / "again", "--jobs", "2"), capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert curve(json.loads(again.stdout)) == uninterrupted


@pytest.mark.timeout(1200)
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_busy_pool_worker_dies_with_its_killed_parent(tmp_path):
    """The mechanism, where a tiny power run cannot show it: a worker in the middle of a
    long task (an idle one ends anyway, on the closed queue) dies with its parent at once
    instead of running its task to the end for nobody."""
    script = ("import time\n"
              "from crs_study.power_analysis.backends import open_backend\n"
              "with open_backend(jobs=2) as backend:\n"
              "    backend.map(time.sleep, [120, 120])\n")
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        workers = wait_for(lambda: (lambda d: d if len(d) >= 2 else None)(
            descendants(parent.pid)), 300, "two workers started")
        time.sleep(3)                             # the sleeps begin (a task per worker)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(timeout=30)
        wait_for(lambda: not any(map(alive, workers)), 20,
                 "the busy workers gone (not after their 120 s)")
    finally:
        kill_all(descendants(parent.pid) | {parent.pid} | set(locals().get("workers", ())))


@pytest.mark.slow
def test_sigkill_of_power_on_a_dask_cluster_leaves_no_client_and_a_rerun_gives_the_curve(
        tmp_path, uninterrupted):
    from distributed import Client, LocalCluster

    from crs_study.power_analysis import backends

    def scheduler_state(dask_scheduler):
        return len(dask_scheduler.clients), len(dask_scheduler.tasks)

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      **backends.QUIET_SCHEDULER) as cluster, \
            Client(cluster, set_as_default=False) as watcher:
        idle_clients = watcher.run_on_scheduler(scheduler_state)[0]
        child = subprocess.Popen(command(tmp_path / "killed", "--scheduler",
                                         cluster.scheduler_address),
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait_for(lambda: watcher.run_on_scheduler(scheduler_state)[1] > 0 or
                     child.poll() is not None, 600, "power's tasks on the scheduler")
            assert child.poll() is None, "power ended before it was killed"
            os.kill(child.pid, signal.SIGKILL)
            child.wait(timeout=30)
            assert not descendants(child.pid)
            # the kernel closed power's connections: the scheduler drops its client and
            # releases its tasks (no worker keeps computing for nobody)
            wait_for(lambda: watcher.run_on_scheduler(scheduler_state) == (idle_clients, 0),
                     60, "the killed client and its tasks released")
        finally:
            if child.poll() is None:
                child.kill()
        again = subprocess.run(command(tmp_path / "again", "--scheduler",
                                       cluster.scheduler_address),
                               capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert curve(json.loads(again.stdout)) == uninterrupted


def in_process(argv: list[str], cwd: Path) -> tuple[int, str]:
    """``crs-study`` as :func:`command` builds it, run by :func:`main` in this process (the
    same code without the 10 s of imports a process costs on a busy machine): (exit, stderr).
    """
    err = io.StringIO()
    previous = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv[3:])
    finally:
        os.chdir(previous)
    return code, err.getvalue()


@pytest.mark.parametrize("address, says", [
    ("tls://127.0.0.1:1", "tls:// is not supported here (it needs certificates"),
    ("ucx://127.0.0.1:1", "ucx:// is not supported here"),
    ("http://127.0.0.1:1", "http:// is not supported here"),
    ("inproc://x", "not a scheduler address (missing port number"),
    ("tcp://", "not a scheduler address (missing port number"),
    ("tcp://[::1", "not a scheduler address (invalid address"),
    ("tcp://127.0.0.1:99999", "a port from 1 to 65535, got host '127.0.0.1' and port 99999"),
    ("/tmp/scheduler", "expected a Dask scheduler address such as tcp://HOST:8786"),
])
def test_a_scheduler_address_is_one_line_before_any_work(tmp_path, address, says):
    argv = command(tmp_path / "never", "--scheduler", address)
    if address.startswith(("tls", "tcp://[")):  # as the user met them: a process of its own
        done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
        code, err = done.returncode, done.stderr
    else:
        code, err = in_process(argv, tmp_path)
    assert code == 2 and "Traceback" not in err, err
    assert err.count("\n") == 1 and says in err, err
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("extra, says", [
    (["--participants", "1000000"], "--participants: expected at most 1000, got 1000000"),
    (["--participants", "2:99999999999999999"], "--participants: at most 200 values"),
    (["--repetitions", "1000000"], "--repetitions: expected at most 100, got 1000000"),
    (["--studies", "100000000"], "--studies: expected at most 100000, got 100000000"),
    (["--jobs", "10000"], "--jobs: expected at most 64, got 10000"),
    (["--draws", "99999999999"], "--draws: expected at most 10000, got 99999999999"),
    (["--out", "/proc/crs-power"], "--out: cannot write in /proc"),
])
def test_absurd_power_options_are_one_line_before_any_work(tmp_path, extra, says):
    code, err = in_process(command(tmp_path / "never") + extra, tmp_path)
    assert code == 2 and err.count("\n") == 1 and says in err, err
    assert list(tmp_path.iterdir()) == []                  # nothing computed, nothing left


def test_cpu_seconds_with_one_job_is_this_process_cpu_time_once():
    before = time.process_time()
    result = power("pilot", draws=2, studies=4, participants="2", seed=5, jobs=1)
    spent = time.process_time() - before
    assert 0 < result.cpu_seconds <= spent          # counted twice it was about 2 x spent
    assert result.cpu_seconds > 0.8 * spent
