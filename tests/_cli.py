"""``crs-study ARGS`` for the tests: in this process by default, or as a process of its own.

In this process, :func:`crs_study.cli.main` runs the same code as the installed command, with
stdout and stderr captured and warnings shown as the command shows them (the suite makes them
errors), without the 2 to 4 s of CPU a new interpreter spends importing numpy, scipy, pandas
and matplotlib. A test that needs a process (a signal, a kill, a terminal, an environment or
working folder of its own, the module entry point itself) asks for one with ``process=True``.
"""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from crs_study.cli import main


def crs_study(*args: object, process: bool = False, cwd: Path | None = None,
              env: dict[str, str] | None = None, timeout: float = 300
              ) -> subprocess.CompletedProcess:
    """Run ``crs-study ARGS``; its exit status, stdout and stderr as a CompletedProcess.

    ``env`` adds variables to (or, for a process, replaces) the environment; ``cwd`` is the
    working folder; ``timeout`` bounds a process only.
    """
    argv = [str(a) for a in args]
    if process:
        return subprocess.run([sys.executable, "-m", "crs_study", *argv], cwd=cwd,
                              env={**os.environ, **(env or {})}, capture_output=True,
                              text=True, timeout=timeout, check=False)
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as patch, warnings.catch_warnings():
        warnings.simplefilter("default")   # shown as the command shows them, not raised
        for name, value in (env or {}).items():
            patch.setenv(name, value)
        if cwd is not None:
            patch.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exit_:   # argparse's usage errors
                code = exit_.code
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())
