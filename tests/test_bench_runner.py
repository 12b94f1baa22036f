"""Bench area ``runner`` runs to its figure as ``crs-study bench runner --quick`` (a real
process, the consent gate included: its participants are simulated ones)."""

from __future__ import annotations

import subprocess
import sys


def test_bench_runner_quick_runs_to_its_figure(tmp_path):
    done = subprocess.run([sys.executable, "-m", "crs_study", "bench", "runner", "--quick"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == int("MISSED" in done.stdout), done.stderr  # 1: a target missed
    assert "Traceback" not in done.stderr and "consent" not in done.stderr
    lines = [line for line in done.stdout.splitlines() if "dry-run session s per wall s" in line]
    assert len(lines) == 1, done.stdout
    # reported, never asserted: the line's last word is its verdict (a word such as
    # "woken" holds "ok" too, so only the verdict itself is read)
    assert lines[0].split()[-1] in ("ok", "MISSED"), lines[0]
    stamps = [line for line in done.stdout.splitlines() if "keypad key stamp" in line]
    assert len(stamps) == 1 and stamps[0].split()[-1] in ("ok", "MISSED"), done.stdout
