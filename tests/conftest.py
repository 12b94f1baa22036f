"""Shared fixtures: the shipped layouts, seeded generators, the Agg backend for charts."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

os.environ.setdefault("MPLBACKEND", "Agg")

# Property tests are seeded like every other test: derandomize draws each test's examples from
# a seed fixed by the test itself, so a failure in CI is the same failure on a laptop; no
# example database carries state between runs. HYPOTHESIS_PROFILE=explore searches afresh.
settings.register_profile("seeded", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", database=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "seeded"))


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
