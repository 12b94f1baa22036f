"""Shared fixtures: the shipped layouts, seeded generators, the Agg backend for charts."""

from __future__ import annotations

import os
import signal
import sys
import tempfile

import pytest
from hypothesis import settings

# One BLAS thread per test process, set before numpy loads OpenBLAS: the suite runs one worker
# per core, and a second BLAS thread per worker only oversubscribes the cores. OpenBLAS's
# threads spin while they wait: beside another worker's BLAS calls the quality tests ran 10
# to 250 times slower (a helper thread burned 46 s of CPU in one 98 s test). Processes the
# tests start inherit it, as the product's own worker processes set it
# (power_analysis.backends, quality.sweep).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402  (after the variables above)

# Compiled modules are kept for the run, outside the checkout. Where the environment says
# PYTHONDONTWRITEBYTECODE (this project's development machine does), every process of the
# suite (each worker's collection, each command a test starts and each worker process those
# start) would otherwise compile every module it imports from source again, and rewrite every
# test module's asserts again: measured, 3 % of the suite's CPU time (collection alone: 18 s
# a worker against 9 s). The cache lives in the temporary folder, so the clone stays as it
# was; the processes the tests start inherit it.
if sys.dont_write_bytecode:
    sys.dont_write_bytecode = False
    sys.pycache_prefix = sys.pycache_prefix or os.path.join(
        tempfile.gettempdir(), f"crs-study-pycache-{os.getuid() if hasattr(os, 'getuid') else 0}")
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ["PYTHONPYCACHEPREFIX"] = sys.pycache_prefix

os.environ.setdefault("MPLBACKEND", "Agg")

# Property tests are seeded like every other test: derandomize draws each test's examples from
# a seed fixed by the test itself, so a failure in CI is the same failure on a laptop; no
# example database carries state between runs. HYPOTHESIS_PROFILE=explore searches afresh.
settings.register_profile("seeded", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", database=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "seeded"))

# Ctrl-C reaches the processes the tests start as it reaches a command typed at a terminal. A
# suite started in the background by a shell without job control (``pytest ... &`` in a
# script) inherits SIGINT ignored (POSIX: the shell ignores it for asynchronous commands), every
# process it starts inherits that in turn, and Python then never raises KeyboardInterrupt: a
# test's Ctrl-C to ``crs-study run`` did nothing and the session ran to its end. A handled
# signal returns to its default in a started program, an ignored one does not; so SIGINT is
# handled here again, as by a Python started from a terminal.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def layout2d():
    from crs_study.geometry.layout import load_layout

    return load_layout("crs2d")


@pytest.fixture(scope="session")
def layout1d():
    from crs_study.geometry.layout import load_layout

    return load_layout("crs1d")


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


@pytest.fixture(autouse=True)
def _a_consent_register_of_its_own(tmp_path_factory, monkeypatch):
    """Every test (and every process it starts) sees an empty consent register of its own,
    never the machine's ~/.crs-study/consent: a session under a person's label passes the
    consent gate on every device, so a test records the consent it needs."""
    monkeypatch.setenv("CRS_STUDY_CONSENT_DIR",
                       str(tmp_path_factory.mktemp("register") / "consent"))


@pytest.fixture(autouse=True)
def _a_board_register_of_its_own(tmp_path_factory, monkeypatch):
    """Every test (and every process it starts) remembers board identities in a file of its
    own, never the machine's ~/.crs-study/boards.json (``device check`` reads it)."""
    monkeypatch.setenv("CRS_STUDY_BOARDS", str(tmp_path_factory.mktemp("boards") / "boards.json"))


def pytest_collection_modifyitems(config, items):
    """Test files with a slow test go first, each file's tests in their order: the workers
    take one file at a time in this order, so the long files start while the many short
    ones fill the gaps, instead of one long file running alone at the end of the suite."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)
