"""``crs-study device``: every action end to end on pseudo-terminal pairs playing the boards."""

from __future__ import annotations

import json
import os
import pty
import threading

import pytest
from test_serial_device import PtyBoard

from crs_study.cli import main
from crs_study.device import codec
from crs_study.layout import load_layout


@pytest.fixture
def boards():
    made: list[PtyBoard] = []

    def make(n: int, **kwargs) -> list[PtyBoard]:
        made.extend(PtyBoard(**kwargs) for _ in range(n))
        return made[-n:]

    yield make
    for board in made:
        board.close()


def _url(boards) -> str:
    return "serial://" + ",".join(b.path for b in boards)


def test_neutral_puts_valid_servo_moves_on_both_ttys(boards, capsys):
    pair = boards(2, battery_mv=None)  # boards that never answer the battery request
    status = main(["device", "neutral", "--device", _url(pair), "--battery-timeout-s", "0.05"])
    assert status == 0
    err = capsys.readouterr().err
    assert err.count("warning: controller") == 2 and "no answer to GET_BATTERY_VOLTAGE" in err
    for board, channels in zip(pair, (19, 18), strict=True):
        moves = board.wait_for(1)
        # what the tty carried decodes as SERVO_MOVE frames only, nothing skipped
        frames, skipped = codec.decode_all(bytes(board.raw))
        assert skipped == [] and len(frames) >= 2  # battery request, then moves
        assert isinstance(frames[0].message, codec.GetBatteryVoltage)
        assert moves and all(m.positions == tuple((ch, 1000) for ch in range(1, channels + 1))
                             for m in moves)


def test_check_prints_batteries_balance_and_wire_budget(boards, capsys):
    pair = boards(2, battery_mv=7400)
    assert main(["device", "check", "--device", _url(pair), "--protocol",
                 "protocols/pilot.toml"]) == 0
    out = capsys.readouterr().out
    assert "controller A: battery 7.40 V" in out and "controller B: battery 7.40 V" in out
    assert "channels per controller A: 19, B: 18 (balanced)" in out
    assert "a full frame takes 66.7 ms" in out and "15.0 frames/s" in out
    assert "crs:" in out and "latency median" in out


def test_check_json(boards, capsys):
    pair = boards(1, battery_mv=7200)
    assert main(["device", "check", "--device", _url(pair), "--layout", "crs1d", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["battery_mv"] == {"A": 7200.0}
    assert report["full_frame_ms"] == pytest.approx(28 * 10 / 9.6)  # 7 channels: 28 bytes


def test_sweep_moves_one_channel_through_its_range(boards):
    (board,) = boards(1)
    assert main(["device", "sweep", "--device", _url([board]), "--layout", "crs1d",
                 "--channel", "A:2", "--seconds", "0.3", "--frame-rate", "20"]) == 0
    moves = board.wait_for(4)
    pulses = [dict(m.positions).get(2) for m in moves if m.time_ms == 50]
    pulses = [p for p in pulses if p is not None]
    assert max(pulses) == 2000 and min(pulses) <= 1100  # up to full travel and back
    assert all(set(dict(m.positions)) <= {2} for m in moves[1:] if m.time_ms == 50)


def test_unknown_channel_is_a_one_line_error(boards, capsys):
    (board,) = boards(1)
    assert main(["device", "sweep", "--device", _url([board]), "--layout", "crs1d",
                 "--channel", "C:9"]) == 2
    assert "--channel: unknown channel(s) 'C:9'" in capsys.readouterr().err


def test_calibrate_records_endpoints_into_a_new_device_file(boards, tmp_path, monkeypatch,
                                                            capsys):
    (board,) = boards(1)
    answers = iter(["+", "ok", "--", ">", "ok"])  # A:1: 1010 us at base, 1951 us at full
    monkeypatch.setattr("builtins.input", lambda prompt="": next(answers))
    out = tmp_path / "calibrated.toml"
    assert main(["device", "calibrate", "--device", _url([board]), "--layout", "crs1d",
                 "--channel", "A:1", "--output", str(out)]) == 0
    layout = load_layout(out)
    cal = layout.actuators[0].calibration
    assert (cal.zero_us, cal.full_us) == (1010, 1951)
    assert (layout.actuators[1].calibration.zero_us, layout.actuators[1].calibration.full_us) \
        == (1000, 2000)
    positions = [dict(m.positions).get(1) for m in board.wait_for(5)]
    assert 1010 in positions and 1951 in positions
    # the original is untouched and the copy is never overwritten silently
    assert main(["device", "calibrate", "--device", _url([board]), "--layout", "crs1d",
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
