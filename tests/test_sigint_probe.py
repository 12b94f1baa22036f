"""A process the suite starts takes Ctrl-C as from a terminal: the probe the Ctrl-C tests of
``test_run_commands.py`` rely on, in a module of its own so that a pytest started to run it
alone imports nothing heavier than the suite's conftest."""

from __future__ import annotations

import subprocess
import sys


def test_a_started_process_takes_ctrl_c_as_from_a_terminal():
    """What the Ctrl-C tests rely on: a process the suite starts raises KeyboardInterrupt on
    SIGINT (the suite's conftest undoes a SIGINT ignored since the suite started)."""
    probe = [sys.executable, "-c", "import signal; print(signal.getsignal(signal.SIGINT))"]
    shown = subprocess.run(probe, capture_output=True, text=True, check=True).stdout
    assert shown.strip() == "<built-in function default_int_handler>"
