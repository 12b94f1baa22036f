"""Rehearsal without hardware: ``crs-study device boards`` (virtual boards on ptys, a tap per
board, a decoded live view) and every device step of the README run against it; ``device
identify`` in a real terminal (tmux) on pty boards; ``device check`` telling boards apart by
what the hardware reports, refusing swapped USB boards."""

from __future__ import annotations

import contextlib
import json
import os
import re
import select
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _tmux import Tmux

from crs_study.cli import main
from crs_study.device import codec, identity
from crs_study.device.identity import BoardRegister, PortIdentity, port_identity
from crs_study.device.virtual_boards import VirtualBoards
from crs_study.geometry.layout import load_layout

README = Path(__file__).resolve().parent.parent / "README.md"
CLI = [sys.executable, "-m", "crs_study"]


class BoardsCommand:
    """``crs-study device boards`` in a child process; its ports read from what it prints."""

    def __init__(self, *extra: str) -> None:
        self.child = subprocess.Popen([*CLI, "device", "boards", *extra],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.text = ""
        self.read_until("device URL: ")
        self.read_until("\n", after="device URL: ")
        self.url = re.search(r"device URL: (\S+)", self.text).group(1)
        self.taps = dict(re.findall(r"^  (\w): \S+\s+tap: (\S+)$", self.text, re.M))

    def read_until(self, marker: str, timeout: float = 30.0, after: str = "") -> str:
        deadline = time.monotonic() + timeout
        while marker not in self.text[self.text.find(after) + len(after):]:
            if time.monotonic() > deadline or self.child.poll() is not None:
                err = self.child.stderr.read().decode() if self.child.poll() is not None else ""
                raise AssertionError(f"{marker!r} not printed:\n{self.text}{err}")
            ready, _, _ = select.select([self.child.stdout], [], [], 0.1)
            if ready:
                self.text += os.read(self.child.stdout.fileno(), 65536).decode()
        return self.text

    def stop(self) -> str:
        self.child.send_signal(signal.SIGINT)
        out, err = self.child.communicate(timeout=30)
        self.text += out.decode()
        assert self.child.returncode == 0, err.decode()
        return self.text


def wait_until_open(process: subprocess.Popen, path: str, timeout: float = 60.0) -> None:
    """Until ``process`` has ``path`` open (its file descriptors, in /proc)."""
    target = os.path.realpath(path)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, f"ended before opening {path}"
        with contextlib.suppress(OSError):  # a descriptor may close while it is read
            fds = Path(f"/proc/{process.pid}/fd")
            if any(os.path.realpath(fd) == target for fd in fds.iterdir()):
                return
        time.sleep(0.02)
    raise AssertionError(f"{path} not opened within {timeout} s")


def read_until(process: subprocess.Popen, marker: str, timeout: float) -> str:
    """What ``process`` printed until ``marker`` (or it ended, or ``timeout`` passed)."""
    seen = ""
    deadline = time.monotonic() + timeout
    while marker not in seen and time.monotonic() < deadline:
        ready, _, _ = select.select([process.stdout], [], [], 0.1)
        if ready:
            chunk = os.read(process.stdout.fileno(), 65536).decode()
            if not chunk:
                break
            seen += chunk
    return seen


def readme_device_steps() -> list[str]:
    """The device step of the README's study, as written (``crs-study device ...`` lines),
    found by its title whatever its number: up to the next numbered step."""
    text = README.read_text(encoding="utf-8")
    (block,) = re.findall(r"^# \d+\. The device.*?(?=^# \d+\. )", text, re.M | re.S)
    return [line.split(" #")[0].strip() for line in block.splitlines()
            if line.startswith("crs-study device ")]


@pytest.mark.slow
def test_the_readmes_device_steps_run_against_virtual_boards(tmp_path, monkeypatch):
    steps = readme_device_steps()
    assert [s.split()[2] for s in steps] == ["identify", "check", "sweep", "calibrate"]
    env = {**os.environ, "CRS_STUDY_BOARDS": str(tmp_path / "boards.json")}
    boards = BoardsCommand()
    try:
        for step in steps:
            argv = shlex.split(step.replace("serial:///dev/ttyUSB0,/dev/ttyUSB1", boards.url))
            # kept short, as written otherwise: sweep and calibrate one channel of each board
            if argv[2] in ("sweep", "calibrate"):
                argv += ["--channel", "A:1", "--channel", "B:1"]
            if argv[2] == "sweep":
                argv += ["--seconds", "0.4"]
            answers = {"identify": "y\ny\n", "calibrate": "ok\nok\nok\nok\n"}.get(argv[2], "")
            done = subprocess.run([*CLI, *argv[1:]], input=answers, capture_output=True,
                                  text=True, cwd=tmp_path, env=env, timeout=120)
            assert done.returncode == 0, f"{step}\n{done.stdout}\n{done.stderr}"
            assert "Traceback" not in done.stderr
        assert (tmp_path / "calibrated.toml").exists()
        # a tap shows what board A receives, decoded by device monitor
        # (opened before neutral is sent; stopped with Ctrl-C, its way to end, once it has
        # printed the move, or after 30 s)
        monitor = subprocess.Popen([*CLI, "device", "monitor", "--port", boards.taps["A"],
                                    "--seconds", "30"], stdout=subprocess.PIPE, env=env)
        wait_until_open(monitor, boards.taps["A"])
        subprocess.run([*CLI, "device", "neutral", "--device", boards.url], check=True,
                       capture_output=True, env=env, timeout=60)
        seen = read_until(monitor, "ServoMove [19]", timeout=30.0)
        monitor.send_signal(signal.SIGINT)
        rest, _ = monitor.communicate(timeout=60)
        seen += rest.decode()
        assert monitor.returncode == 0 and "stopped" in seen, seen
        assert "ServoMove [19]" in seen, seen
    finally:
        text = boards.stop()
    # the live view decoded every step's frames: the battery requests and the sweep's moves
    assert "A  GetBatteryVoltage" in text and "B  ServoMove" in text
    assert re.search(r"received: A \d+ frame\(s\) \(0 bad\), B \d+ frame\(s\) \(0 bad\)", text)


def test_identify_in_a_terminal_wiggles_each_board_and_refuses_a_swap(tmp_path):
    layout = load_layout("crs2d")
    env = {"CRS_STUDY_BOARDS": str(tmp_path / "boards.json")}
    with VirtualBoards(layout, tap=False) as boards:
        a, b = boards.ports
        command = f"{sys.executable} -m crs_study device identify --device serial://{a},{b}"
        with Tmux(command, tmp_path, env=env) as term:
            shown = term.wait_for("Is the board labelled A the one moving? [y/n]")
            assert f"board A (port {a}): its first servo, channel A:1 (pixel 0)" in shown
            time.sleep(1.0)
            moves = [h for h in boards.heard() if isinstance(h.message, codec.ServoMove)]
            wiggled = {h.board for h in moves if len(h.message.positions) < 5}
            assert wiggled == {"A"}, moves  # board A's first servo, nothing on B
            term.send("y", "Enter")
            term.wait_for("Is the board labelled B the one moving? [y/n]")
            term.send("maybe", "Enter")
            term.wait_for("answer y or n")
            term.send("y", "Enter")
            assert "remembered in" in term.wait_for("remembered in")
            assert term.exit_code() == 0
        stored = json.loads((tmp_path / "boards.json").read_text())["crs2d"]
        assert stored["A"]["port"] == a and stored["A"]["kind"] == "pty"
        # plugged the other way round: the servo wiggling is on board B; the person says no
        command = f"{sys.executable} -m crs_study device identify --device serial://{b},{a}"
        with Tmux(command, tmp_path, env=env) as term:
            term.wait_for("Is the board labelled A the one moving? [y/n]")
            term.send("n", "Enter")
            shown = term.wait_for("nothing was remembered")
            assert f"the ports are swapped: try --device serial://{a},{b}" in shown
            assert term.exit_code() == 2


def test_check_says_pty_boards_are_told_apart_by_path_only(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CRS_STUDY_BOARDS", str(tmp_path / "boards.json"))
    with VirtualBoards(load_layout("crs2d"), tap=False) as boards:
        assert main(["device", "check", "--device", boards.url]) == 0
    out = capsys.readouterr().out
    assert "pseudo-terminals with no USB serial number or by-id path, so by path only" in out
    assert main(["device", "check", "--device", "sim://"]) == 0
    assert "told apart: simulated" in capsys.readouterr().out


class FakePort:
    def __init__(self, device, serial_number, location):
        self.device, self.serial_number, self.location = device, serial_number, location


def test_usb_boards_are_remembered_by_serial_number_and_a_swap_is_refused(tmp_path,
                                                                          monkeypatch):
    """pyserial's list_ports reports each adapter's serial number (faked here: no USB)."""
    usb = [FakePort("/dev/ttyUSB0", "A50285BI", "1-1.2"), FakePort("/dev/ttyUSB1",
                                                                   "FT9X3KQ1", "1-1.3")]
    monkeypatch.setattr(identity.list_ports, "comports", lambda: usb)
    a, b = port_identity("/dev/ttyUSB0"), port_identity("/dev/ttyUSB1")
    assert a == PortIdentity("/dev/ttyUSB0", "A50285BI", None, "1-1.2", kind="usb")
    register = BoardRegister(tmp_path / "boards.json")
    assert "not yet confirmed" in register.check("crs2d", {"A": a, "B": b}).how
    register.remember("crs2d", {"A": a, "B": b})
    fine = register.check("crs2d", {"A": a, "B": b})
    assert fine.ok and fine.how.startswith("by A = /dev/ttyUSB0: USB serial number A50285BI")
    # replugged the other way round: the adapters' serial numbers now sit on swapped paths
    usb[0].device, usb[1].device = "/dev/ttyUSB1", "/dev/ttyUSB0"
    swapped = register.check("crs2d", {"A": port_identity("/dev/ttyUSB0"),
                                       "B": port_identity("/dev/ttyUSB1")})
    assert not swapped.ok
    assert "the ports are swapped; use --device serial:///dev/ttyUSB1,/dev/ttyUSB0" in \
        swapped.how
    other = PortIdentity("/dev/ttyUSB0", "NEWBOARD", kind="usb")
    assert "replaced" in register.check("crs2d", {"A": other, "B": b}).how


def test_check_refuses_swapped_usb_ports_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CRS_STUDY_BOARDS", str(tmp_path / "boards.json"))
    BoardRegister().remember("crs2d", {
        "A": PortIdentity("/dev/ttyUSB0", "A50285BI", kind="usb"),
        "B": PortIdentity("/dev/ttyUSB1", "FT9X3KQ1", kind="usb")})
    swapped = [FakePort("/dev/ttyUSB1", "A50285BI", None),
               FakePort("/dev/ttyUSB0", "FT9X3KQ1", None)]
    monkeypatch.setattr(identity.list_ports, "comports", lambda: swapped)
    assert main(["device", "check", "--device", "serial:///dev/ttyUSB0,/dev/ttyUSB1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "swapped" in err[0]


@pytest.mark.parametrize("argv, message", [
    (["--baud", "1"], "--baud"), (["--seconds", "nan"], "--seconds"),
    (["--seconds", "-1"], "--seconds")])
def test_boards_options_are_checked(argv, message, capsys):
    assert main(["device", "boards", *argv]) == 2
    assert message in capsys.readouterr().err
