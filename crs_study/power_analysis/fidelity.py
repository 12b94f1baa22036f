"""Mode 3 (``fidelity="full"``): every simulated study is real dry-runs, analysed for real.

A study is ``max(participants)`` sessions of the protocol by the simulated observer on the
simulated device (:func:`crs_study.session.dry_runs.dry_run`, into a temporary dataset
that is removed afterwards), loaded as ``analyze`` loads a dataset, the plan's exclusions
applied, and the primary test run on its first N participants for every N (participant k is
the same session at every N). Participants of study ``s`` are labelled ``r<seed>s<s>p01
...``: the label makes the plan's seed and so the person, so another ``seed`` gives other
people. Slow (about a second a session): for checking modes 1 and 2 on a few points, not
the default.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass

import numpy as np

from crs_study.analysis.load import load_datasets, with_exclusions
from crs_study.analysis.plan import Exclusions
from crs_study.power_analysis.backends import Backend, Progress
from crs_study.power_analysis.design import PowerDesign
from crs_study.power_analysis.result import merge
from crs_study.power_analysis.study import TaskResult, decide_trials
from crs_study.session.dry_runs import dry_run, simulated_labels


@dataclass(frozen=True)
class FidelityTask:
    """One study of mode 3: its number, the design and the participant counts."""

    design: PowerDesign
    seed: int
    study: int
    participants: tuple[int, ...]


def labels(seed: int, study: int, n: int) -> list[str]:
    """The participant labels of a mode-3 study (BIDS: letters and digits only)."""

    return simulated_labels(n, prefix=f"r{seed}s{study}p")


def run_study(task: FidelityTask) -> TaskResult:
    """Dry-run one study, analyse its first N participants for every N."""

    start = time.process_time()
    design = task.design
    n_max = max(task.participants)
    with tempfile.TemporaryDirectory(prefix="crs-power-") as folder:
        dry_run(design.protocol_path, n_max, folder, prefix=f"r{task.seed}s{task.study}p")
        loaded = with_exclusions(load_datasets([folder]), design.exclusions or Exclusions())
        trials = loaded.analysed
    order = labels(task.seed, task.study, n_max)
    rows = []
    for n in task.participants:
        rows.append(decide_trials(design, trials.loc[trials["participant_id"].isin(order[:n])]))
    stack = {key: np.stack([np.asarray(r[key]) for r in rows])[:, None]
             for key in ("p_value", "kind", "log_odds", "theta", "converged", "boundary",
                         "reduced", "loglike", "loglike_reduced")}
    stack["reference"] = np.ones((len(rows), 1), dtype=bool)
    return TaskResult((task.study, task.study + 1), seconds=time.process_time() - start,
                      **stack)


def run_full(design: PowerDesign, seed: int, participants: tuple[int, ...], studies: int,
             backend: Backend, progress: Progress | None = None) -> dict:
    """Every study of mode 3 on ``backend``; the merged per-study arrays."""

    tasks = [FidelityTask(design, seed, s, participants) for s in range(studies)]
    results = backend.map(run_study, tasks, progress)
    raw = merge(results)
    raw["cpu_seconds"] = backend.cpu_elsewhere(tasks, [r.seconds for r in results])
    return raw
