"""Shared fixtures: the shipped layouts, seeded generators, the Agg backend for charts."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def layout2d():
    from crs_study.layout import load_layout

    return load_layout("crs2d")


@pytest.fixture(scope="session")
def layout1d():
    from crs_study.layout import load_layout

    return load_layout("crs1d")


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)
