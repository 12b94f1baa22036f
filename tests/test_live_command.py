"""``crs-study live`` and ``live-send`` as the user meets them: processes, signals, a terminal
(tmux), one-line errors; the latency summaries and the board tap's bookkeeping."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _cli import crs_study

from crs_study.clock import VirtualClock
from crs_study.device import open_device
from crs_study.device.calibration import PulseMap
from crs_study.live.boards import BoardTap, ShownFrame
from crs_study.live.latency import Summary
from tests._pty_helpers import boards_fixture  # noqa: F401  (the ``boards`` fixture)
from tests._tmux import Tmux

CLI = [sys.executable, "-m", "crs_study"]


def announced_port(text: str) -> int:
    """The port a ``live --listen 127.0.0.1:0`` process says it listens on (the kernel chose
    it: no other test process can be given the same one, as a probed free port could)."""
    found = re.search(r"127\.0\.0\.1:(\d+)", text)
    assert found, text
    return int(found.group(1))


def test_summary_is_r_quantile_type_7():
    # R: quantile(1:100, c(.5, .95, .99)) -> 50.50 95.05 99.01 (type 7, R's default)
    s = Summary.of(np.arange(1.0, 101.0))
    assert (s.n, s.median, s.p95, s.p99, s.max) == (100, 50.5, pytest.approx(95.05),
                                                   pytest.approx(99.01), 100.0)
    assert Summary.of([]).n == 0 and Summary.of([]).to_json()["median_ms"] is None


def test_board_tap_times_frames_and_skips_a_replaced_one(layout2d):
    clock = VirtualClock()
    device = open_device("sim://", layout2d, clock, record=True)
    device.open()
    tap = BoardTap(layout2d, device.boards, advance=device.displayed_setpoints)
    frames = []
    for k, height in enumerate((0.0, 3.0, 4.0, 5.0)):
        setpoints = np.zeros(layout2d.n_actuators)
        setpoints[9] = height  # the centre pixel, A:10
        report = device.send(setpoints, 0)
        frame = ShownFrame(k, "finger", setpoints, report.commanded_at, report.wire_done_at,
                           report.bytes_sent)
        tap.add(frame)
        frames.append(frame)
        # frame 0 (the first write: every channel) has 100 ms; 2 and 3 come while 1 is on the
        # wire, so 3 replaces 2 before it goes
        clock.advance(0.1 if k == 0 else 0.001)
    clock.advance(1.0)
    done = tap.poll(clock.now())
    assert [f.index for f in done] == [0, 1, 2, 3]
    assert frames[2].lost and not frames[1].lost and not frames[3].lost  # 2 was replaced
    assert frames[1].done_at - frames[1].handed_at == pytest.approx(10 * 10 / 9600)  # 1 servo
    assert frames[1].done_at == pytest.approx(frames[1].host_done)  # as the host predicted
    assert frames[3].done_at == pytest.approx(frames[3].host_done)
    # servos in place (0.08 s/cm, docs/device.md): frame 3 lands 10.4 ms after frame 1, the servo
    # then 10.4 / 8 = 1.30 mm up on its way to 3 mm; 3.70 mm more to 5 mm: 29.6 ms
    wire = 10 * 10 / 9600
    assert frames[3].done_at - frames[1].done_at == pytest.approx(wire)
    assert frames[3].in_place_at - frames[3].done_at == pytest.approx((5 - wire / 0.008) * 0.008,
                                                                      rel=2e-3)
    assert tap.unmatched == 0


def test_live_and_live_send_processes_json(tmp_path):
    record = tmp_path / "rec.jsonl"
    live = subprocess.Popen(CLI + ["live", "--device", "sim://", "--listen",
                                   "127.0.0.1:0", "--max-packets", "40", "--json",
                                   "--record", str(record)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = live.stderr.readline()
        assert "listening on" in line
        port = announced_port(line)
        sent = subprocess.run(CLI + ["live-send", "--to", f"127.0.0.1:{port}", "--hold",
                                     "--seconds", "0.6", "--jitter-mm", "0.5", "--json"],
                              capture_output=True, text=True, timeout=30)
        assert sent.returncode == 0, sent.stderr
        assert json.loads(sent.stdout)["packets"] == 44
        out, err = live.communicate(timeout=30)
    finally:
        live.kill()
    assert live.returncode == 0, err
    result = json.loads(out)
    assert result["stopped_by"] == "max packets" and result["packets"]["received"] == 40
    assert result["latency_source"] == "boards" and result["arrival_stamps"] == "kernel"
    assert result["latency"]["wire"]["n"] >= 1  # how many: the machine's load decides
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:  # held: ours alone
        sink.bind(("127.0.0.1", 0))
        replay = crs_study("live-send", "--to", f"127.0.0.1:{sink.getsockname()[1]}",
                           "--replay", record)
    assert replay.returncode == 0 and "sent 40 packets" in replay.stdout, replay.stderr


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_leaves_the_boards_neutral_and_the_ports_free(boards, layout2d, signum):
    a, b = boards(2)
    live = subprocess.Popen(CLI + ["live", "--device", f"serial://{a.path},{b.path}",
                                   "--listen", "127.0.0.1:0", "--no-view"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = live.stderr.readline()
        assert "listening on" in line
        port = announced_port(line)
        sent = crs_study("live-send", "--to", f"127.0.0.1:{port}", "--hold", "--centre", "0,0",
                         "--seconds", "0.4")
        assert sent.returncode == 0, sent.stderr
        assert len(a.wait_for(2)) >= 2  # the start's neutral pose, then the bump
        live.send_signal(signum)
        out, err = live.communicate(timeout=30)
    finally:
        live.kill()
    assert live.returncode == 0, err
    assert f"stopped: {'Ctrl-C' if signum == signal.SIGINT else signum.name}" in out
    neutral = PulseMap.from_layout(layout2d).to_pulses(layout2d.neutral_setpoints())
    for board, name in ((a, "A"), (b, "B")):
        ids = {x.channel: x.index for x in layout2d.actuators if x.controller == name}
        expected = {i: neutral[k] for i, k in ids.items()}
        moves = board.wait_for_last(lambda m, e=expected: dict(m.positions) == e, count=2)
        assert dict(moves[-1].positions) == expected  # every channel neutral
    # the ports are free again: another program may open them at once
    import serial

    serial.Serial(a.path, exclusive=True).close()


@pytest.mark.parametrize("argv, message", [
    (["live", "--device", "sim://", "--listen", "nowhere"], "expected HOST:PORT"),
    (["live", "--device", "sim://", "--silence-s", "0"], "silence_s"),
    (["live", "--device", "sim://", "--no-battery-check"], "serial:// devices only"),
    (["live", "--device", "bogus://"], "unknown device URL"),
    (["live-send", "--digit", "12"], "digit"),
    (["live-send", "--symbol", "A", "--set", "letters"], "letter: expected one of C, J"),
    (["live-send", "--hold", "--set", "letters"], "--set: names the stimulus set of --symbol"),
    (["live-send", "--replay", "/nonexistent.jsonl"], "no such recording"),
    (["live-send", "--hold", "--to", "x"], "expected HOST:PORT"),
])
def test_one_line_errors(argv, message, capsys):
    from crs_study.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_port_in_use_and_an_existing_recording(tmp_path, capsys):
    from crs_study.cli import main

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        busy = sock.getsockname()[1]
        assert main(["live", "--device", "sim://", "--listen", f"127.0.0.1:{busy}"]) == 2
    assert "in use by another program" in capsys.readouterr().err
    existing = tmp_path / "r.jsonl"
    existing.write_text("keep me")
    assert main(["live", "--device", "sim://", "--listen", "127.0.0.1:0",
                 "--record", str(existing)]) == 2
    assert "already exists" in capsys.readouterr().err and existing.read_text() == "keep me"


def test_the_live_view_fits_80_by_24_and_redraws_in_place(tmp_path):
    # a real terminal (tmux) of 80 x 24: every line of the view fits (a wrapped line would
    # break the redraw, which moves the cursor up by the lines it drew), the screen is redrawn
    # in place (one title, however many redraws), with the map of the pixels' heights
    command = " ".join(CLI + ["live", "--device", "sim://", "--listen", "127.0.0.1:0"])
    with Tmux(command, Path(os.getcwd()), width=80, height=24) as term:
        screen = term.wait_for("waiting for packets", timeout=60)
        port = announced_port(screen)  # the view's title: crs-study live  127.0.0.1:PORT
        sent = crs_study("live-send", "--to", f"127.0.0.1:{port}", "--stroke", "--speed-mm-s",
                         "100")
        assert sent.returncode == 0, sent.stderr
        screen = term.wait_for("73 received", timeout=60)
        time.sleep(1.0)  # several redraws after the last packet
        screen = term.screen()
        assert screen.count("crs-study live ") == 1, screen  # redrawn in place, not scrolled
        assert "state     live (stream" in screen or "state     silent" in screen
        assert "arrival -> last byte on wire" in screen and "written" in screen
        assert "predict   1€ + velocity:" in screen and "bump to finger at landing: median" \
            in screen
        rows = screen.splitlines()
        start = rows.index(next(r for r in rows if r.startswith("heights")))
        # crs2d's 19 hexagonal pixels, rows of 3, 4, 5, 4, 3: a height digit or '.' each
        assert [len(r.split()) for r in rows[start + 1:start + 6]] == [3, 4, 5, 4, 3], screen
        assert all(set(r.split()) <= set(".0123456789") for r in rows[start + 1:start + 6])
        assert all(len(r) <= 80 for r in rows) and len(rows) <= 24
        term.send("C-c")
        screen = term.wait_for("stopped: Ctrl-C", timeout=60)
        assert "stopped: Ctrl-C; display neutral, ports released" in screen
        assert term.exit_code(timeout=60) == 0
