"""A real terminal for tests: a detached tmux session of a chosen size, keys sent with
``send-keys`` and the screen read with ``capture-pane`` (what a person would see)."""

from __future__ import annotations

import shlex
import shutil
import subprocess
import time
import uuid
from pathlib import Path

import pytest


class Tmux:
    """One detached tmux session (its own server socket) running ``command``."""

    def __init__(self, command: str, cwd: Path, width: int = 80, height: int = 24,
                 env: dict[str, str] | None = None) -> None:
        if shutil.which("tmux") is None:
            pytest.skip("tmux is not installed")
        self.socket = f"crs-test-{uuid.uuid4().hex[:8]}"
        self.name = "t"
        self.done = cwd / f".tmux-{self.socket}.rc"
        exports = " ".join(f"{k}={shlex.quote(v)}" for k, v in (env or {}).items())
        # the exit code is kept in a file; the pane stays so the last screen can be read
        shell = f"{exports} {command}; echo $? > {shlex.quote(str(self.done))}; sleep 600"
        self._tmux("new-session", "-d", "-s", self.name, "-x", str(width), "-y", str(height),
                   "-c", str(cwd), "bash", "--norc", "-c", shell)

    def _tmux(self, *args: str) -> str:
        return subprocess.run(["tmux", "-L", self.socket, *args], check=True,
                              capture_output=True, text=True).stdout

    def send(self, *keys: str) -> None:
        """``tmux send-keys`` (key names such as ``Up``, ``F5``, ``Escape``, ``Space``)."""
        self._tmux("send-keys", "-t", self.name, *keys)

    def send_raw(self, data: str) -> None:
        """Exactly these characters, in one write (``send-keys -l``)."""
        self._tmux("send-keys", "-t", self.name, "-l", data)

    def screen(self) -> str:
        return self._tmux("capture-pane", "-p", "-t", self.name)

    def wait_for(self, text: str, timeout: float = 30.0) -> str:
        """The screen once it shows ``text``; fails with the last screen after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            shown = self.screen()
            if text in shown:
                return shown
            if time.monotonic() > deadline:
                raise AssertionError(f"{text!r} never appeared; the screen:\n{shown}")
            time.sleep(0.05)

    def exit_code(self, timeout: float = 60.0) -> int:
        deadline = time.monotonic() + timeout
        while not self.done.exists() or not self.done.read_text().strip():
            if time.monotonic() > deadline:
                raise AssertionError(f"still running; the screen:\n{self.screen()}")
            time.sleep(0.05)
        return int(self.done.read_text())

    def close(self) -> None:
        subprocess.run(["tmux", "-L", self.socket, "kill-server"], capture_output=True)

    def __enter__(self) -> Tmux:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
