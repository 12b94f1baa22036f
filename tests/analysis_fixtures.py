"""Small valid datasets for the analysis tests (BIDS beh, per crs_study.dataset.schema).

``dataset(path, **spec)`` draws one from the analysis' own generating model
(:mod:`crs_study.analysis.synthetic`); ``explicit_dataset(path, cells)`` writes exactly the
trials asked for, for the degenerate cases: every ``(participant, condition, digit,
repetition, correct)`` becomes a test trial with the response the digit itself when correct,
the next digit otherwise.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from crs_study.analysis.synthetic import SyntheticSpec, write_dataset, write_sessions
from crs_study.dataset.schema import MISSING

FAST_PLAN = """
[plan]
name = "test plan"
conditions = ["pixel-only", "crs"]
seed = 7

[primary]
random_effects = ["participant"]
bootstrap_replicates = 99        # the p's Monte Carlo error is not what these tests test

[confusion]
bootstrap = 200

[psychometric]
bootstrap = 20
"""

#: FAST_PLAN with the primary p against chi2, for tests that do not read the p: the plan's
#: rule ("auto") takes a parametric bootstrap of it below 20 participants.
CHI2_PLAN = FAST_PLAN.replace("[primary]\n", '[primary]\np_value = "chi2"\n')


def dataset(path: Path, **changes) -> Path:
    """A synthetic dataset (see :class:`SyntheticSpec`; ``changes`` override fields)."""
    spec = replace(SyntheticSpec(n_participants=6, repetitions=3, seed=11), **changes)
    return write_dataset(path, spec)


def trial_row(index: int, condition: str, digit: int, repetition: int, correct: int | None,
              rt: float = 1.5, kind: str = "test") -> dict[str, object]:
    response = MISSING if correct is None else (digit if correct else (digit + 1) % 10)
    return {
        "trial_index": index, "trial_type": kind, "block": 0, "condition": condition,
        "repetition": repetition, "digit": digit, "response": response,
        "correct": MISSING if correct is None else int(correct),
        "response_time": MISSING if correct is None else rt,
        "response_time_from_offset": MISSING if correct is None else rt - 1.0,
        "onset": 2.0 * index, "stimulus_duration": 1.0,
        "timed_out": int(correct is None), "device_fault": 0, "rerun": 0, "frames": 15,
        "late_frames": 0, "median_wire_latency": 0.012, "responder": "scripted",
        "trial_end": 2.0 * index + 1.9,
    }


def explicit_dataset(path: Path, cells: dict[str, list[tuple]]) -> Path:
    """Write ``{participant: [(condition, digit, repetition, correct[, rt]), ...]}``."""
    sessions = {}
    for label, trials in cells.items():
        sessions[label] = [trial_row(i, *trial) for i, trial in enumerate(trials)]
    return write_sessions(path, sessions)


def write_plan(path: Path, text: str = FAST_PLAN) -> Path:
    path.write_text(text)
    return path


def session_files(root: Path) -> list[tuple[Path, Path]]:
    """(tsv, sidecar) of every session, sorted."""
    tsvs = sorted(root.glob("sub-*/ses-*/beh/*_beh.tsv"))
    return [(t, t.with_suffix(".json")) for t in tsvs]


def edit_sidecar(sidecar: Path, **changes) -> None:
    meta = json.loads(sidecar.read_text())
    meta.update(changes)
    sidecar.write_text(json.dumps(meta))
