"""Helpers shared by the runner's tests: a tiny protocol and a fake device (test-only)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from crs_study.device.base import Device, FrameReport, full_frame_wire_time_s
from crs_study.errors import DeviceError
from crs_study.paths import shipped_file
from crs_study.session.responders.random import RandomResponder


def tiny_protocol(directory: Path, name: str = "tiny.toml", *, digits=(1, 4, 7),
                  repetitions: int = 1, practice: int = 1, speed: float = 60.0,
                  iti: float = 0.5, time_limit: float = 10.0, break_every: int = 0,
                  study_id: str = "tiny") -> Path:
    """The shipped pilot protocol made small: few digits, fast strokes, short holds."""
    text = shipped_file("protocols/pilot.toml").read_text(encoding="utf-8")
    changes = {
        "id": f'"{study_id}"',
        "digits": "[" + ", ".join(map(str, digits)) + "]",
        "keys": "[" + ", ".join(f'"{d}"' for d in digits) + "]",
        "repetitions": str(repetitions), "practice_trials": str(practice),
        "stroke_speed_mm_s": str(speed), "inter_trial_interval_s": str(iti),
        "start_hold_s": "0.1", "end_hold_s": "0.1", "stroke_pause_s": "0.2",
        "time_limit_s": str(time_limit), "break_every": str(break_every),
    }
    for key, value in changes.items():
        text, count = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value}", text)
        assert count == 1, key
    path = directory / name
    path.write_text(text, encoding="utf-8")
    return path


def quick_analysis_protocol(directory: Path, **changes) -> Path:
    """:func:`tiny_protocol` (``changes`` its options) whose analysis plan, written beside it,
    is the pilot's with one random intercept per participant, for the tests of what the
    analysis does with sessions (missing, interrupted, withdrawn) that read none of the GLMM.
    The pilot's maximal model on a few participants of a tiny protocol leaves a flat
    likelihood whose profile limits took half the CPU of every ``crs-study analyze``."""
    text = shipped_file("analysis/pilot.toml").read_text(encoding="utf-8")
    for key, value in (("random_effects", '["participant"]'), ("structure", '"intercepts"')):
        text, count = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value}", text)
        assert count == 1, key
    plan = directory / "quick_plan.toml"
    plan.write_text(text, encoding="utf-8")
    protocol = tiny_protocol(directory, **changes)
    text, count = re.subn(r"(?m)^analysis_plan\s*=.*$", f'analysis_plan = "{plan}"',
                          protocol.read_text(encoding="utf-8"))
    assert count == 1
    protocol.write_text(text, encoding="utf-8")
    return protocol


def tiny_letter_protocol(directory: Path, symbols=("C", "L", "S"), study_id="tinyletters"
                         ) -> Path:
    """The shipped letter protocol made small: three letters once per condition, fast."""
    text = shipped_file("protocols/letter_identification.toml").read_text(encoding="utf-8")
    changes = {"id": f'"{study_id}"',
               "symbols": "[" + ", ".join(f'"{s}"' for s in symbols) + "]",
               "keys": "[" + ", ".join(f'"{s.lower()}"' for s in symbols) + "]",
               "repetitions": "1", "practice_trials": "1", "stroke_speed_mm_s": "60.0",
               "inter_trial_interval_s": "0.5", "start_hold_s": "0.1", "end_hold_s": "0.1"}
    for key, value in changes.items():
        text, count = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value}", text)
        assert count == 1, key
    text = text.replace('consent_form = "consent/consent_form.md"',
                        f'consent_form = "{shipped_file("consent/consent_form.md")}"')
    text = text.replace('analysis_plan = "analysis/letter_identification.toml"',
                        f'analysis_plan = "{shipped_file("analysis/letter_identification.toml")}"')
    path = directory / "tiny_letters.toml"
    path.write_text(text, encoding="utf-8")
    return path


class FakeDevice(Device):
    """Shows what it was told at once; the wire takes one full frame; faults on request."""

    def __init__(self, layout, clock=None, fail_at: int | None = None) -> None:
        super().__init__(layout, clock)
        self.sent: list[np.ndarray] = []
        self.fail_at = fail_at
        self.closed = False
        self.current = layout.neutral_setpoints()

    def open(self) -> None:
        self.closed = False

    def send(self, setpoints_mm, move_ms=None) -> FrameReport:
        if self.fail_at is not None and len(self.sent) == self.fail_at:
            raise DeviceError("fake port vanished")
        now = self.clock.now()
        self.sent.append(np.array(setpoints_mm))
        self.current = np.array(setpoints_mm)
        return FrameReport(now, now + full_frame_wire_time_s(self.layout), (64, 43), 37)

    def close(self) -> None:
        if not self.closed:
            self.current = self.layout.neutral_setpoints()
            self.closed = True

    def displayed_setpoints(self, t=None) -> np.ndarray:
        return self.current.copy()


class PauseAt(RandomResponder):
    """The random responder that presses Ctrl-C when trial ``at`` asks for an answer."""

    def __init__(self, seed: int, at: int) -> None:
        super().__init__(seed)
        self.at = at

    def respond(self, trial, stimulus, clock, time_limit_s):
        if trial.index == self.at:
            raise KeyboardInterrupt
        return super().respond(trial, stimulus, clock, time_limit_s)


def adaptive_protocol(directory: Path, name: str = "adaptive.toml", *,
                      procedure: str = "quest-plus", trials: int = 8, levels: int = 5,
                      stop_reversals: int = 0, digits=(1, 4, 7), practice: int = 1,
                      study_id: str = "tinyadaptive") -> Path:
    """:func:`tiny_protocol` whose digit height a staircase or QUEST+ chooses (0.4 to 1.2
    pitch on a log scale, ``levels`` levels)."""
    path = tiny_protocol(directory, name, digits=digits, practice=practice,
                         study_id=study_id)
    text = path.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^digit_(height|width)_pitch\s*=.*\n", "", text)
    text = re.sub(r"(?m)^analysis_plan\s*=.*$",
                  'analysis_plan = "analysis/digit_size_adaptive.toml"', text)
    table = (f'\n[adaptive]\nparameter = "digit_height_pitch"\nwidth_to_height = 0.605\n'
             f'procedure = "{procedure}"\ntrials = {trials}\nmin = 0.4\nmax = 1.2\n'
             f'scale = "log"\nlevels = {levels}\n')
    if procedure == "quest-plus":
        table += ('target_rate = 0.5\n\n[adaptive.quest_plus]\nthresholds = 9\n'
                  'slopes = [2.0, 6.0]\nlapse_rates = [0.0, 0.05]\n')
    else:
        table += ('\n[adaptive.staircase]\nrule = "1-up-2-down"\nstart = 1.2\nsteps = [2, 1]\n'
                  f'stop_reversals = {stop_reversals}\nestimate_reversals = '
                  f'{min(2, stop_reversals) if stop_reversals else 4}\n')
    path.write_text(text.replace("\n[conditions]", table + "\n[conditions]", 1),
                    encoding="utf-8")
    return path


def assert_same_but_reruns(resumed: Path, whole: Path, cut: set[int]) -> None:
    """A resumed session's trial file equals the uninterrupted run's byte for byte but for
    the ``rerun`` column, which is 1 exactly on the trials an interruption cut after their
    stimulus began (the participant felt part of them before the rerun, and the data say so)."""
    import csv

    def table(path: Path) -> tuple[list[str], list[dict[str, str]]]:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle, delimiter="\t")
            return list(reader.fieldnames or []), list(reader)

    columns, rows = table(resumed)
    whole_columns, whole_rows = table(whole)
    assert columns == whole_columns and "rerun" in columns
    assert len(rows) == len(whole_rows)
    reruns = {int(r["trial_index"]) for r in rows if r["rerun"] == "1"}
    assert reruns == cut, (reruns, cut)
    assert all(r["rerun"] == "0" for r in whole_rows)
    for row, other in zip(rows, whole_rows, strict=True):
        assert {k: v for k, v in row.items() if k != "rerun"} == \
            {k: v for k, v in other.items() if k != "rerun"}
    # nothing else differs: the bytes are those of the uninterrupted file with the marks set
    expected = whole.read_text(encoding="utf-8").splitlines(keepends=True)
    position = columns.index("rerun")
    for k in cut:
        cells = expected[k + 1].rstrip("\n").split("\t")
        cells[position] = "1"
        expected[k + 1] = "\t".join(cells) + "\n"
    assert resumed.read_text(encoding="utf-8") == "".join(expected)


def record_consent(*labels: str, register: Path | None = None) -> None:
    """Record each person's consent on the shipped form in ``register`` (default: the test's
    own register, $CRS_STUDY_CONSENT_DIR from conftest): a person's label passes the consent
    gate on every device, sim:// included (a person's data never enter a dataset without
    their consent, whatever the device)."""
    from crs_study.consent import Register, read_form
    from crs_study.paths import shipped_file

    form = read_form(shipped_file("consent/consent_form.md"))
    for label in labels:
        Register(register).record(form, "AB", label)


def start_command(args, cwd: Path):
    """``crs-study ARGS`` in its own process, stdout and stderr piped."""
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-m", "crs_study", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd)


def wait_for_stderr(process, needle: str, timeout: float = 60.0) -> str:
    """Raw reads of stderr until ``needle`` (a buffered readline would hide data from select)."""
    import os
    import select
    import time

    seen = b""
    deadline = time.monotonic() + timeout
    while needle.encode() not in seen:
        assert time.monotonic() < deadline, seen
        ready, _, _ = select.select([process.stderr], [], [], 0.5)
        if ready:
            chunk = os.read(process.stderr.fileno(), 4096)
            assert chunk, seen
            seen += chunk
    return seen.decode()
