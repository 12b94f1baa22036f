"""Synthetic datasets: valid BIDS per crs_study.dataset.schema, checksums the loader accepts, the
generating model recovered by the analysis."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from crs_study.analysis.load import load_datasets
from crs_study.analysis.synthetic import SyntheticSpec, write_dataset
from crs_study.dataset.schema import TRIAL_COLUMNS
from crs_study.paths import data_dir


def test_dataset_loads_without_any_warning(tmp_path):
    root = write_dataset(tmp_path / "ds", SyntheticSpec(n_participants=3, repetitions=2))
    data = load_datasets(root)
    assert not data.warnings and set(TRIAL_COLUMNS) <= set(data.trials.columns)
    # 2 conditions x 10 digits x 2 repetitions + 2 practice trials per participant
    assert len(data.trials) == 3 * (40 + 2)
    assert (data.trials.groupby(["participant", "condition", "digit"]).size() >= 2).all()


def test_same_seed_same_bytes(tmp_path):
    spec = SyntheticSpec(n_participants=2, repetitions=1, seed=4)
    a, b = write_dataset(tmp_path / "a", spec), write_dataset(tmp_path / "b", spec)
    files = sorted(p.relative_to(a) for p in a.rglob("*.tsv"))
    assert files and all((a / f).read_bytes() == (b / f).read_bytes() for f in files)


def test_accuracy_follows_the_spec(tmp_path):
    spec = SyntheticSpec(n_participants=30, repetitions=10, participant_sd=0.0, digit_sd=0.0,
                         accuracy={"pixel-only": 0.5, "crs": 0.7}, seed=6)
    trials = load_datasets(write_dataset(tmp_path / "ds", spec)).trials
    test = trials.loc[trials["trial_type"] == "test"]
    accuracy = test.groupby("condition")["correct"].mean()
    assert accuracy["pixel-only"] == pytest.approx(0.5, abs=0.04)
    assert accuracy["crs"] == pytest.approx(0.7, abs=0.04)


def _validator() -> str | None:
    beside = Path(sys.executable).with_name("bids-validator-deno")
    return str(beside) if beside.exists() else shutil.which("bids-validator-deno")


@pytest.mark.skipif(_validator() is None, reason="bids-validator-deno not installed")
def test_dataset_and_its_derivative_pass_the_bids_validator(tmp_path):
    """The files are the point, not the statistics: analysed under the shipped pilot plan,
    whose primary p is the chi2 LR, the derivative has the same files as under the main
    plan (report, results, figures) without its parametric bootstrap of the maximal model
    on two participants (nine tenths of the two and a half minutes the test took)."""
    from crs_study.analysis.report import analyze_dataset

    root = write_dataset(tmp_path / "ds", SyntheticSpec(n_participants=2, repetitions=1))
    analyze_dataset(root, data_dir() / "analysis" / "pilot.toml")  # derivatives/crs-study
    derivative = root / "derivatives" / "crs-study"
    assert {"dataset_description.json", "report.md", "results.json"} <= \
        {p.name for p in derivative.iterdir()}
    run = subprocess.run([_validator(), str(root)], capture_output=True, text=True,
                         timeout=120)
    assert "[ERROR]" not in run.stdout, run.stdout[-3000:]
