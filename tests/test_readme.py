"""The README's Python session runs as written (so it cannot rot): its code block is executed
in a fresh interpreter in an empty folder, and what it says it makes is there."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

pytestmark = pytest.mark.slow  # a dry-run of 4 participants and the full analysis: ~15 s


def python_session() -> str:
    """The first ```python block of the README's "In Python" section."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## In Python\n"):]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README.md: no ```python block under '## In Python'"
    return match.group(1)


def test_the_readme_python_session_runs(tmp_path):
    code = python_session()
    assert "crs_study.dry_run(" in code and "crs_study.analyze(" in code
    env = dict(os.environ, MPLBACKEND="Agg")
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert "('pixel-only', 'crs') 1" in out
    assert out.count(" complete ") == 4 and "GLMM odds ratio" in out
    assert (tmp_path / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = tmp_path / "rehearsal" / "derivatives" / "crs-study" / "report.md"
    assert report.is_file() and str(report.relative_to(tmp_path)) in out
