"""``crs-study device``: every action end to end on pseudo-terminal pairs playing the boards."""

from __future__ import annotations

import json
import os
import pty
import re
import threading
import time

import pytest
from _pty_helpers import STALLED_S, boards_fixture, url_of  # noqa: F401 - the boards fixture

from crs_study.cli import main
from crs_study.device import codec, decoder, protocol_lscsim
from crs_study.device.virtual_controller import VirtualController
from crs_study.geometry.layout import device_file_path, load_layout


def test_neutral_puts_valid_servo_moves_on_both_ttys(boards, capsys):
    pair = boards(2, battery_mv=None)  # boards that never answer the battery request
    status = main(["device", "neutral", "--device", url_of(pair), "--battery-timeout-s", "0.05"])
    assert status == 0
    err = capsys.readouterr().err
    assert err.count("warning: controller") == 2 and "no answer to GET_BATTERY_VOLTAGE" in err
    for board, channels in zip(pair, (19, 18), strict=True):
        moves = board.wait_for(1)
        # what the tty carried decodes as SERVO_MOVE frames only, nothing skipped
        frames, skipped = decoder.decode_all(bytes(board.raw))
        assert skipped == [] and len(frames) >= 2  # battery request, then moves
        assert isinstance(frames[0].message, codec.GetBatteryVoltage)
        assert moves and all(m.positions == tuple((ch, 1000) for ch in range(1, channels + 1))
                             for m in moves)
        assert moves[0].time_ms == 500  # the slow neutral move, from wherever they were


def test_check_prints_batteries_balance_and_wire_budget(boards, capsys):
    pair = boards(2, battery_mv=7400)
    assert main(["device", "check", "--device", url_of(pair), "--protocol",
                 "protocols/pilot.toml"]) == 0
    out = capsys.readouterr().out
    assert "controller A: battery 7.40 V" in out and "controller B: battery 7.40 V" in out
    assert "channels per controller A: 19, B: 18 (balanced)" in out
    assert "a full frame takes 66.7 ms" in out and "15.0 frames/s" in out
    assert "crs:" in out and "latency median" in out


def test_check_json(boards, capsys):
    pair = boards(1, battery_mv=7200)
    assert main(["device", "check", "--device", url_of(pair), "--layout", "crs1d", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["battery_mv"] == {"A": 7200.0}
    assert report["full_frame_ms"] == pytest.approx(28 * 10 / 9.6)  # 7 channels: 28 bytes


def test_check_without_a_protocol_plans_the_default_one_and_says_so(tmp_path, monkeypatch,
                                                                     capsys):
    from crs_study.paths import DEFAULT_PROTOCOL, shipped_file

    monkeypatch.chdir(tmp_path)  # found beside the package, not only from the checkout's root
    assert main(["device", "check", "--device", "sim://"]) == 0
    out = capsys.readouterr().out
    default = shipped_file(DEFAULT_PROTOCOL)
    assert default.name == "digit_identification.toml"
    assert (f"protocol {default} (the default protocol; --protocol FILE plans another): digit "
            f"stimuli on the wire") in out
    assert re.search(r"  crs: \d+ frames at 15/s", out)
    assert main(["device", "check", "--device", "sim://", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["protocol_file"] == str(default) and report["protocol_is_default"]
    assert set(report["protocol"]) == {"pixel-only", "crs"}
    # a protocol named on the command line is planned instead, and not called the default
    assert main(["device", "check", "--device", "sim://", "--json", "--protocol",
                 str(shipped_file("protocols/pilot.toml"))]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["protocol_file"].endswith("pilot.toml") and not report["protocol_is_default"]


def test_sweep_moves_one_channel_through_its_range(boards):
    (board,) = boards(1)
    assert main(["device", "sweep", "--device", url_of([board]), "--layout", "crs1d",
                 "--channel", "A:2", "--seconds", "0.3", "--frame-rate", "20"]) == 0
    # the sweep's frames (50 ms each), then close()'s slow neutral move (500 ms)
    moves = board.wait_for_last(lambda m: m.time_ms == 500, count=4)
    pulses = [dict(m.positions).get(2) for m in moves if m.time_ms == 50]
    pulses = [p for p in pulses if p is not None]
    assert max(pulses) == 2000 and min(pulses) <= 1100  # up to full travel and back
    assert all(set(dict(m.positions)) <= {2} for m in moves[1:] if m.time_ms == 50)


def test_unknown_channel_is_a_one_line_error(boards, capsys):
    (board,) = boards(1)
    assert main(["device", "sweep", "--device", url_of([board]), "--layout", "crs1d",
                 "--channel", "C:9"]) == 2
    assert "--channel: unknown channel(s) 'C:9'" in capsys.readouterr().err


def test_calibrate_records_endpoints_into_a_new_device_file(boards, tmp_path, monkeypatch,
                                                            capsys):
    (board,) = boards(1)
    answers = iter(["+", "ok", "--", ">", "ok"])  # A:1: 1010 us at base, 1951 us at full
    monkeypatch.setattr("builtins.input", lambda prompt="": next(answers))
    out = tmp_path / "calibrated.toml"
    assert main(["device", "calibrate", "--device", url_of([board]), "--layout", "crs1d",
                 "--channel", "A:1", "--output", str(out)]) == 0
    layout = load_layout(out)
    cal = layout.actuators[0].calibration
    assert (cal.zero_us, cal.full_us) == (1010, 1951)
    assert (layout.actuators[1].calibration.zero_us, layout.actuators[1].calibration.full_us) \
        == (1000, 2000)
    moves = board.wait_until(lambda m: {1010, 1951} <= {dict(x.positions).get(1) for x in m})
    positions = [dict(m.positions).get(1) for m in moves]
    assert 1010 in positions and 1951 in positions
    # the original is untouched and the copy is never overwritten silently
    assert main(["device", "calibrate", "--device", url_of([board]), "--layout", "crs1d",
                 "--output", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err


def test_monitor_decodes_frames_and_reports_garbage(capsys):
    master, slave = pty.openpty()
    try:
        stream = (b"\x00\x13" + codec.servo_move({1: 2000}, 1000) + b"\x55\x55\x02\x42"
                  + codec.servo_move([(2, 1200), (9, 2300)], 800))
        # pyserial empties the input buffer when it opens the port: write once it listens
        timer = threading.Timer(0.3, os.write, (master, stream))
        timer.start()
        assert main(["device", "monitor", "--port", os.ttyname(slave), "--max-frames", "2",
                     "--seconds", "2"]) == 0
    finally:
        timer.join()
        os.close(master)
        os.close(slave)
    out = capsys.readouterr().out
    assert "skipped 2 byte(s) (no frame header): 00 13" in out
    assert "ServoMove [1] in 1000 ms: 1:2000" in out
    assert "skipped 4 byte(s) (unknown command 0x42): 55 55 02 42" in out
    assert "ServoMove [2] in 800 ms: 2:1200 9:2300" in out
    assert "2 frame(s), 6 byte(s) skipped" in out


# ---------------------------------------------------------------------------------------------
# the simulator's lscsim:// ports, bad numbers, faults met on the way to neutral


@pytest.fixture
def lscsim_boards(request):
    """Recording virtual boards behind lscsim://NAME-A and lscsim://NAME-B (unique names)."""
    names = [f"{request.node.name}-{c}" for c in "AB"]
    made = [protocol_lscsim.attach(n, VirtualController(n, record=True, t0=time.monotonic()))
            for n in names]
    yield names, made
    for n in names:
        protocol_lscsim.detach(n)


def test_lscsim_ports_work_from_the_command_line(lscsim_boards, capsys):
    (a, b), boards = lscsim_boards
    url = f"serial://lscsim://{a},lscsim://{b}"
    assert main(["device", "neutral", "--device", url]) == 0
    assert "neutral pose sent" in capsys.readouterr().out
    for board, channels in zip(boards, (19, 18), strict=True):
        moves = [r.message for r in board.received if isinstance(r.message, codec.ServoMove)]
        assert moves and moves[-1].positions == tuple((ch, 1000) for ch in range(1, channels + 1))
        assert board.bad_frames == 0


@pytest.mark.parametrize(
    ("flags", "message"),
    [(["--seconds", "inf"], r"--seconds: expected a time per channel in \(0, 600\] s, got inf"),
     (["--seconds", "0"], r"--seconds: .* got 0\.0"),
     (["--seconds", "-1"], r"--seconds: .* got -1\.0"),
     (["--seconds", "nan"], r"--seconds: .* got nan"),
     (["--seconds", "1e9"], r"--seconds: .* got 1000000000\.0"),
     (["--frame-rate", "nan"], r"--frame-rate: expected 0\.0333\.\.100 frames/s .* got nan"),
     (["--frame-rate", "0.001"], r"--frame-rate: .* got 0\.001"),
     (["--frame-rate", "0"], r"--frame-rate: .* got 0\.0"),
     (["--frame-rate", "-10"], r"--frame-rate: .* got -10\.0"),
     (["--frame-rate", "inf"], r"--frame-rate: .* got inf"),
     (["--frame-rate", "1e308"], r"--frame-rate: .* got 1e\+308")])
def test_sweep_refuses_bad_numbers_in_one_line_before_opening(flags, message, capsys):
    # a port that does not exist: the numbers are refused before any port is opened
    assert main(["device", "sweep", "--device", "serial:///nonexistent", "--layout", "crs1d",
                 *flags]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.count("\n") == 1


def test_a_neutral_pose_not_reached_is_never_reported_as_success(capsys):
    # board B's port vanished: A still gets neutral, the command says what failed, exit 2
    assert main(["device", "neutral", "--device", "sim://?disconnect_at=B@0"]) == 2
    out, err = capsys.readouterr()
    assert "neutral pose sent" not in out
    assert "warning: close: neutral pose not reached" in err and "controller B" in err
    assert err.strip().splitlines()[-1].startswith("crs-study device: error: ")


def test_neutral_fails_when_the_pose_cannot_be_confirmed_on_close(monkeypatch, capsys):
    from crs_study.device.simulated import SimulatedDevice

    real_close = SimulatedDevice.close

    def failing_close(self):
        real_close(self)
        self.faults.append("controller A: neutral pose not confirmed sent (timeout)")

    monkeypatch.setattr(SimulatedDevice, "close", failing_close)
    assert main(["device", "check", "--device", "sim://", "--layout", "crs1d"]) == 2
    err = capsys.readouterr().err
    assert ("error: closing the device: controller A: neutral pose not confirmed sent" in err)


def test_calibrate_refuses_an_unwritable_output_before_asking_anything(boards, tmp_path,
                                                                      monkeypatch, capsys):
    (board,) = boards(1)
    monkeypatch.setattr("builtins.input", lambda prompt="": pytest.fail("asked for input"))
    for out, extra in ((tmp_path / "missing" / "x.toml", []), (tmp_path, ["--overwrite"])):
        assert main(["device", "calibrate", "--device", url_of([board]), "--layout", "crs1d",
                     "--output", str(out), *extra]) == 2
        assert "expected a new file in a writable directory" in capsys.readouterr().err
    original = tmp_path / "mine.toml"
    original.write_bytes(device_file_path("crs1d").read_bytes())
    before = original.read_bytes()
    assert main(["device", "calibrate", "--device", url_of([board]), "--layout", str(original),
                 "--output", str(original), "--overwrite"]) == 2
    assert "never the original" in capsys.readouterr().err and original.read_bytes() == before
    assert board.moves() == []  # the port was never opened


def test_calibrate_prints_the_endpoints_when_the_file_cannot_be_written(boards, tmp_path,
                                                                       monkeypatch, capsys):
    (board,) = boards(1)
    answers = iter(["ok", "ok"])
    monkeypatch.setattr("builtins.input", lambda prompt="": next(answers))

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("crs_study.device.calibration.write_calibrated_copy", disk_full)
    out = tmp_path / "calibrated.toml"
    assert main(["device", "calibrate", "--device", url_of([board]), "--layout", "crs1d",
                 "--channel", "A:1", "--output", str(out)]) == 2
    captured = capsys.readouterr()
    assert '"A:1" = {zero_us = 1000, full_us = 2000}' in captured.out  # nothing lost
    assert "No space left on device" in captured.err and not out.exists()


class _ScriptedPort:
    """A monitor's port: hands out ``chunks`` one read at a time, then calls ``at_end``."""

    in_waiting = 0

    def __init__(self, chunks: list[bytes], at_end) -> None:
        self.chunks, self.at_end, self.closed = list(chunks), at_end, False

    def read(self, n: int) -> bytes:
        if self.chunks:
            return self.chunks.pop(0)
        return self.at_end()

    def close(self) -> None:
        self.closed = True


def _monitor_through(monkeypatch, port: _ScriptedPort) -> None:
    monkeypatch.setattr("crs_study.device.serial_port.serial_for_spec",
                        lambda spec, **kw: port)


def test_monitor_ends_cleanly_on_ctrl_c(monkeypatch, capsys):
    def ctrl_c():  # the experimenter presses Ctrl-C during the read after the frame
        raise KeyboardInterrupt

    port = _ScriptedPort([codec.servo_move({1: 2000}, 1000), b"\x55"], ctrl_c)
    _monitor_through(monkeypatch, port)
    assert main(["device", "monitor", "--port", "loop://"]) == 0
    out = capsys.readouterr().out
    assert "ServoMove [1] in 1000 ms: 1:2000" in out and "stopped (Ctrl-C)" in out
    assert "end of stream: skipped 1 byte(s) (truncated frame): 55" in out
    assert "1 frame(s), 1 byte(s) skipped" in out and port.closed


def test_monitor_on_a_silent_port_ends_at_its_time(capsys):
    master, slave = pty.openpty()  # a tty on which nothing ever arrives
    try:
        start = time.monotonic()
        assert main(["device", "monitor", "--port", os.ttyname(slave), "--seconds", "0.3"]) == 0
        assert time.monotonic() - start < 2.0  # reads time out; the loop sees the clock
    finally:
        os.close(master)
        os.close(slave)
    assert "0 frame(s), 0 byte(s) skipped" in capsys.readouterr().out


def test_monitor_on_a_port_that_vanishes_is_one_line(monkeypatch, capsys):
    class Vanished:
        in_waiting = 0

        def read(self, n: int) -> bytes:
            raise OSError(5, "Input/output error")

        def close(self) -> None:
            raise OSError(5, "Input/output error")  # closing a pulled-out adapter fails too

    monkeypatch.setattr("crs_study.device.serial_port.serial_for_spec",
                        lambda spec, **kw: Vanished())
    assert main(["device", "monitor", "--port", "/dev/ttyUSB9"]) == 2
    err = capsys.readouterr().err
    assert err == "crs-study device: error: --port /dev/ttyUSB9: read failed: [Errno 5] " \
                  "Input/output error\n"


def test_sweep_keeps_every_pulse_inside_a_reversed_narrow_calibration(lscsim_boards, tmp_path):
    from crs_study.device.calibration import write_calibrated_copy

    (a, _), (board, _) = lscsim_boards
    device_file = tmp_path / "crs1d-cal.toml"
    limits = {"A:1": (1900, 1100), "A:2": (1400, 1600), "A:7": (2450, 550)}  # 2 reversed
    layout = write_calibrated_copy(device_file_path("crs1d"), device_file, limits)
    assert main(["device", "sweep", "--device", f"serial://lscsim://{a}", "--layout",
                 str(device_file), "--seconds", "0.1", "--frame-rate", "30"]) == 0
    low = {x.channel: min(x.calibration.zero_us, x.calibration.full_us) for x in layout.actuators}
    high = {x.channel: max(x.calibration.zero_us, x.calibration.full_us)
            for x in layout.actuators}
    moves = [r.message for r in board.received if isinstance(r.message, codec.ServoMove)]
    seen = {ch: set() for ch in low}
    for move in moves:
        for channel, pulse in move.positions:
            assert low[channel] <= pulse <= high[channel], (channel, pulse)
            seen[channel].add(pulse)
    # each channel went through its whole range: both endpoints reached
    assert all({low[ch], high[ch]} <= seen[ch] for ch in seen)
    assert moves[-1].time_ms == 500  # neutral on the way out


@pytest.mark.parametrize(
    ("flags", "message"),
    [(["--refresh-s", "-1"], r"sim://': option refresh_s: expected a number in \[0\.0, "),
     (["--deadband-us", "500"], r"option deadband_us: expected a whole number in \[0, 100\]"),
     (["--min-battery-mv", "5", "--no-battery-check"],
      r"error: --min-battery-mv, --no-battery-check: for serial:// devices only")])
def test_serial_flags_reach_the_simulator_or_are_refused_never_ignored(flags, message, capsys):
    assert main(["device", "check", "--device", "sim://", "--layout", "crs1d", *flags]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.count("\n") == 1


# ---------------------------------------------------------------------------------------------
# SIGTERM and SIGHUP (a kill, a closed terminal) end an action as Ctrl-C does


def _last_move_once_neutral(board):
    """The board's last move, once it is the neutral pose after at least one move before it
    (the decoding end reads in a thread of its own: close()'s move can still be on its way
    when the command has returned)."""
    neutral = _neutral_pulses("crs1d")
    return board.wait_for_last(lambda m: m.positions == neutral, count=2)[-1]


def _neutral_pulses(layout_name: str) -> tuple[tuple[int, int], ...]:
    from crs_study.device.calibration import PulseMap

    layout = load_layout(layout_name)
    pulses = PulseMap.from_layout(layout).neutral_pulses(layout)
    return tuple((a.channel, int(p)) for a, p in zip(layout.actuators, pulses, strict=True))


def _terminate_here() -> None:
    """Deliver SIGTERM to this process now; only ever where the command handles it (the
    default action would end the test run)."""
    import signal

    assert threading.current_thread() is threading.main_thread()
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, signal.SIG_IGN, None):
        pytest.fail("SIGTERM is not handled here")
    signal.raise_signal(signal.SIGTERM)


def _released(path: str) -> bool:
    """The port can be opened exclusively again (the command let go of its flock)."""
    import serial

    try:
        serial.serial_for_url(path, exclusive=True).close()
    except serial.SerialException:
        return False
    return True


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGHUP"])
def test_a_signal_during_a_sweep_ends_in_neutral_with_exit_130(boards, signum):
    # a real process on a real pty, killed mid-sweep: the last frame on the wire is the slow
    # neutral move of close(), not wherever the sweep was
    import signal
    import subprocess
    import sys

    (board,) = boards(1)
    process = subprocess.Popen(
        [sys.executable, "-m", "crs_study", "device", "sweep", "--device", url_of([board]),
         "--layout", "crs1d", "--seconds", "60", "--frame-rate", "10"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(m.time_ms == 100 for m in board.moves()):  # the sweep's frames, 100 ms
            assert time.monotonic() < deadline and process.poll() is None, "sweep never began"
            time.sleep(0.01)
        process.send_signal(getattr(signal, signum))
        _, err = process.communicate(timeout=30)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 130, err
    assert err == "crs-study device: interrupted\n"  # one line, no traceback
    last = board.wait_for_last(lambda m: m.time_ms == 500)[-1]   # after the sweep's frames
    assert last.time_ms == 500 and last.positions == _neutral_pulses("crs1d")


@pytest.mark.parametrize("action", ["neutral", "sweep", "calibrate", "check"])
def test_sigterm_in_every_action_sends_neutral_and_releases_the_port(action, boards, tmp_path,
                                                                     monkeypatch, capsys):
    from crs_study.clock import RealClock
    from crs_study.device.serial_device import SerialDevice

    (board,) = boards(1)
    hooks = {"neutral": (SerialDevice, "wait_sent"), "sweep": (RealClock, "sleep_until"),
             "check": (SerialDevice, "battery_mv")}
    if action == "calibrate":
        monkeypatch.setattr("builtins.input", lambda prompt="": _terminate_here())
    else:
        owner, name = hooks[action]
        real = getattr(owner, name)

        def hooked(self, *args, **kwargs):
            if threading.current_thread() is threading.main_thread():
                _terminate_here()
            return real(self, *args, **kwargs)

        monkeypatch.setattr(owner, name, hooked)
    extra = {"sweep": ["--seconds", "30"], "calibrate": ["--output", str(tmp_path / "c.toml")]}
    assert main(["device", action, "--device", url_of([board]), "--layout", "crs1d",
                 *extra.get(action, [])]) == 130
    assert capsys.readouterr().err == "crs-study device: interrupted\n"
    last = _last_move_once_neutral(board)
    assert last.time_ms == 500 and last.positions == _neutral_pulses("crs1d")
    assert _released(board.path)
    assert not (tmp_path / "c.toml").exists()


def test_monitor_stopped_by_sigterm_reports_and_exits_0(monkeypatch, capsys):
    def sigterm():
        _terminate_here()
        return b""

    port = _ScriptedPort([codec.servo_move({1: 2000}, 1000)], sigterm)
    _monitor_through(monkeypatch, port)
    assert main(["device", "monitor", "--port", "loop://"]) == 0
    out = capsys.readouterr().out
    assert "stopped (SIGTERM)" in out and "1 frame(s), 0 byte(s) skipped" in out
    assert port.closed


def test_a_second_signal_while_closing_waits_for_the_neutral_pose(boards, monkeypatch, capsys):
    # the first SIGTERM starts the way out of a sweep; another one (an impatient kill) arrives
    # as the neutral pose is about to be written: it is held until the pose is out
    from crs_study.clock import RealClock
    from crs_study.device.serial_device import SerialDevice

    (board,) = boards(1)
    real_neutral = SerialDevice._neutral_on_close

    def sleep_until(self, deadline):
        if threading.current_thread() is threading.main_thread():
            _terminate_here()

    def neutral_on_close(self):
        _terminate_here()
        return real_neutral(self)

    monkeypatch.setattr(RealClock, "sleep_until", sleep_until)
    monkeypatch.setattr(SerialDevice, "_neutral_on_close", neutral_on_close)
    assert main(["device", "sweep", "--device", url_of([board]), "--layout", "crs1d"]) == 130
    last = _last_move_once_neutral(board)
    assert last.time_ms == 500 and last.positions == _neutral_pulses("crs1d")
    assert _released(board.path)


def test_check_plans_the_protocol_with_the_devices_refresh(capsys):
    # the full refresh (every --refresh-s, default 1 s) is on the wire in the plan too: some
    # frame in every second carries every channel, so 15 frames/s is the bound (docs/device.md:
    # 64 bytes, 66.7 ms on A)
    budgets = {}
    for extra in ([], ["--refresh-s", "0"]):
        assert main(["device", "check", "--device", "sim://", "--protocol",
                     "protocols/pilot.toml", "--json", *extra]) == 0
        budgets[tuple(extra)] = json.loads(capsys.readouterr().out)["protocol"]["crs"]
    on, off = budgets[()], budgets[("--refresh-s", "0")]
    assert on["refresh_s"] == 1.0 and off["refresh_s"] == 0.0
    assert on["rate_bound_hz"] == pytest.approx(15.0)
    assert on["changed_only_rate_hz"] > 15.0
    assert off["rate_bound_hz"] == off["changed_only_rate_hz"]
    assert on["latency_ms_max"] == pytest.approx(64 * 10 / 9.6)  # a refresh frame: 66.7 ms
    assert on["latency_ms_max"] > off["latency_ms_max"]


def test_monitor_finds_a_reply_behind_a_false_header_once_the_line_is_quiet(monkeypatch,
                                                                            capsys):
    # 55 55 05 06 + the reply's first bytes would pass for a frame (codec, "False headers");
    # the read that comes back empty (the line is quiet) decides for the real reply
    class Port:
        in_waiting = 0

        def __init__(self) -> None:
            self.chunks = [bytes.fromhex("55 55 05 06 55 55 04 0F 4C 1D"), b""]

        def read(self, n: int) -> bytes:
            if self.chunks:
                return self.chunks.pop(0)
            raise KeyboardInterrupt

        def close(self) -> None:
            pass

    monkeypatch.setattr("crs_study.device.serial_port.serial_for_spec",
                        lambda spec, **kw: Port())
    assert main(["device", "monitor", "--port", "loop://", "--direction", "board"]) == 0
    out = capsys.readouterr().out
    assert "@4       BatteryVoltage millivolts=7500" in out
    assert "skipped 4 byte(s) (false header: not followed by a header" in out
    assert "1 frame(s), 4 byte(s) skipped" in out



@pytest.mark.parametrize(
    ("flags", "message"),
    [(["--refresh-s", "1e308"], r"refresh_s: expected a number of seconds in \[0, 3600\], "
                                r"got 1e\+308"),
     (["--refresh-s", "-1"], r"refresh_s: .* got -1\.0"),
     (["--refresh-s", "nan"], r"refresh_s: .* got nan"),
     (["--battery-timeout-s", "1e300"], r"battery_timeout_s: expected a number of seconds in "
                                        r"\(0, 60\], got 1e\+300"),
     (["--battery-timeout-s", "0"], r"battery_timeout_s: .* got 0\.0"),
     (["--battery-timeout-s", "inf"], r"battery_timeout_s: .* got inf"),
     (["--deadband-us", "-1"], r"deadband_us: expected a whole number of us 0\.\.100, got -1"),
     (["--deadband-us", "1000000000000"], r"deadband_us: .* got 1000000000000"),
     (["--min-battery-mv", "-5"], r"min_battery_mv: expected a whole number of mV, got -5")])
def test_serial_options_out_of_range_are_one_line_errors(lscsim_boards, flags, message,
                                                         capsys):
    # a refresh of 1e308 s once overflowed time_t in the writer thread (a traceback, then "I/O
    # thread stopped"); a battery timeout of 1e300 s was accepted
    (a, _), (board, _) = lscsim_boards
    assert main(["device", "sweep", "--device", f"serial://lscsim://{a}", "--layout", "crs1d",
                 "--seconds", "0.1", *flags]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.count("\n") == 1 and "Traceback" not in err, err
    assert board.received == []  # refused before the port was opened


@pytest.mark.parametrize(
    ("flags", "message"),
    [(["--seconds", "-1"], r"--seconds: expected a time in \(0, 86400\] s \(leave it out to "
                           r"run until Ctrl-C\), got -1\.0"),
     (["--seconds", "0"], r"--seconds: .* got 0\.0"),
     (["--seconds", "nan"], r"--seconds: .* got nan"),
     (["--seconds", "inf"], r"--seconds: .* got inf"),
     (["--seconds", "1e12"], r"--seconds: .* got 1000000000000\.0"),
     (["--max-frames", "0"], r"--max-frames: expected 1\.\.1000000000 frames, got 0"),
     (["--max-frames", "-5"], r"--max-frames: .* got -5"),
     (["--max-frames", "10000000000000"], r"--max-frames: .* got 10000000000000"),
     (["--baud", "0"], r"--baud: expected 300\.\.4000000 \(the LSC boards use 9600\), got 0"),
     (["--baud", "-9600"], r"--baud: .* got -9600"),
     (["--baud", "100000000000000"], r"--baud: .* got 100000000000000")])
def test_monitor_refuses_bad_numbers_in_one_line_before_opening(flags, message, capsys):
    # a port that does not exist: the numbers are refused before it is opened (a negative or
    # NaN --seconds used to end at once with exit 0; a huge --baud overflowed in pyserial)
    assert main(["device", "monitor", "--port", "/dev/nonexistent-crs", *flags]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.count("\n") == 1 and "Traceback" not in err, err



# ---------------------------------------------------------------------------------------------
# which channel goes on which controller: pinned by the device file (serial_device docstring)


def _lopsided_device_file(tmp_path):
    """crs2d with pixels 10-14 wired to A:20..A:24 instead of B:1..B:5: 24 on A, 13 on B."""
    text = device_file_path("crs2d").read_text()
    for k in range(5):
        text = text.replace(f'"B:{k + 1}",', f'"A:{20 + k}",', 1)
    path = tmp_path / "lopsided.toml"
    path.write_text(text.replace('name = "crs2d"', 'name = "lopsided"', 1))
    return path


def test_check_prints_the_pinned_map_and_how_to_rebalance_it(tmp_path, capsys):
    path = _lopsided_device_file(tmp_path)
    assert main(["device", "check", "--device", "sim://", "--layout", str(path)]) == 0
    out, err = capsys.readouterr()
    # the map in use is the file's, channel by channel: A drives pixels 10-14 on 20..24
    assert "channel map (pinned by the device file; each channel is a servo's wire on a " \
           "board):" in out
    a_line = next(line for line in out.splitlines() if line.startswith("  A: "))
    assert "20 pixel 10, 21 pixel 11, 22 pixel 12, 23 pixel 13, 24 pixel 14" in a_line
    assert "channels per controller A: 24, B: 13 (unbalanced: A's full frame is 23% longer " \
           "than an even split's; rewire channels (5 from A to B)" in out
    # and opening it warns, once, in one line
    assert err.count("crs-study device: warning: lopsided: channels per controller A: 24") == 1
    assert main(["device", "check", "--device", "sim://", "--layout", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["channels_per_controller"] == {"A": 24, "B": 13} and not report["balanced"]
    assert report["rewire"] == [{"from": "A", "to": "B", "channels": 5}]


def test_frames_go_to_the_controller_the_file_names_even_when_unbalanced(tmp_path,
                                                                         lscsim_boards):
    # software never moves a channel to even the load: a frame for another board would move
    # whatever servo is plugged in there. Both devices warn and keep the file's map.
    import numpy as np

    from crs_study.clock import VirtualClock
    from crs_study.device.base import DeviceWarning, open_device

    layout = load_layout(_lopsided_device_file(tmp_path))
    expected = {c.name: {a.channel for a in layout.actuators if a.controller == c.name}
                for c in layout.controllers}
    assert len(expected["A"]) == 24 and len(expected["B"]) == 13
    (a, b), boards = lscsim_boards
    for url, clock in ((f"serial://lscsim://{a},lscsim://{b}", None), ("sim://", VirtualClock())):
        device = open_device(url, layout, clock, **({"record": True} if clock else {}))
        with pytest.warns(DeviceWarning, match=r"rewire channels \(5 from A to B\)"):
            device.open()
        try:
            device.send(np.full(layout.n_actuators, 4.0))
            if clock is None:
                assert device.wait_sent(STALLED_S)
            else:
                clock.advance(0.2)
                device.displayed_setpoints()
        finally:
            device.close()
        seen = boards if clock is None else device.boards
        for board, name in zip(seen, ("A", "B"), strict=True):
            moves = [r.message for r in board.received if isinstance(r.message, codec.ServoMove)]
            assert moves and all({i for i, _ in m.positions} == expected[name] for m in moves)
