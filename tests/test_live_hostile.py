"""Hostile input to the live link as the user meets it: damaged recordings replayed by
``crs-study live-send`` (its ``main``, in the test's process), sequence numbers that wrap or
restart sent over real UDP to a real ``crs-study live`` process, and a second signal while
``live`` closes.

Every damaged recording is a one-line error (exit 2) or is replayed at a sane pace, never a
traceback, a hang or a huge allocation (each live process has a generous timeout; none is timed).
"""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from _cli import crs_study
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.live import FingerPacket, LiveError, encode_packet, read_trace
from crs_study.live.packet import MAX_U32, newer
from crs_study.live.record import MAX_GAP_S

CLI = [sys.executable, "-m", "crs_study"]
HEADER = {"format": "crs-study live recording", "version": 1}


def recording(tmp_path, packets, name: str = "r.jsonl", raw: str = "") -> str:
    """A recording whose accepted packets are ``packets`` ((t, x, y, z) each), then ``raw``."""
    lines = [json.dumps(HEADER)] + [
        json.dumps({"packet": {"t": t, "status": "accepted", "x": x, "y": y, "z": z}})
        for t, x, y, z in packets]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n" + raw, encoding="utf-8")
    return str(path)


def replay(path: str, *options: str) -> subprocess.CompletedProcess:
    """``live-send --replay path`` to a socket of ours (held open: no other test's), in this
    process."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:
        sink.bind(("127.0.0.1", 0))
        return crs_study("live-send", "--to", f"127.0.0.1:{sink.getsockname()[1]}",
                         "--replay", path, "--json", *options)


def one_line_error(done: subprocess.CompletedProcess, message: str) -> None:
    assert done.returncode == 2, (done.stdout, done.stderr)
    err = done.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(message, err), err


@pytest.mark.parametrize("packets, raw, message", [
    pytest.param([(0.0, 1e308, 0.0, 3.0), (0.1, 1.0, 0.0, 3.0)], "",
                 r"r\.jsonl:2: an accepted packet's x \(mm\) must be a finite number a packet "
                 r"can carry \(float32\), got 1e\+308", id="x-1e308"),
    pytest.param([(0.0, 1.0, 0.0, 3.0), (0.1, 1.0, 0.0, -1e308)], "",
                 r"r\.jsonl:3: .* z \(mm\)", id="z-1e308"),
    pytest.param([(0.0, 1.0, 0.0, 3.0)], "[" * 100_000 + "]" * 100_000 + "\n",
                 r"r\.jsonl:3: not a recording's line \(nested too deeply\)", id="nested"),
    pytest.param([(0.0, 1.0, 0.0, 3.0)], '{"x": "' + "a" * (1 << 21) + '"}\n',
                 r"r\.jsonl:3: a line longer than", id="two-megabyte-line"),
    pytest.param([(5.0, 1.0, 0.0, 3.0), (6.0, 1.0, 0.0, 3.0), (1.0, 2.0, 0.0, 3.0)], "",
                 r"r\.jsonl:4: packet times go backwards .* --rate", id="backwards"),
    pytest.param([(7.0, float(k), 0.0, 3.0) for k in range(50)], "",
                 r"all 50 accepted packets have one time; .* --rate", id="all-equal"),
    pytest.param([(0.0, 1.0, 0.0, 3.0), (None, 1.0, 0.0, 3.0)], "",
                 r"r\.jsonl:3: an accepted packet's time must be a finite number, got None",
                 id="no-time"),
])
def test_a_damaged_recording_is_a_one_line_error(tmp_path, packets, raw, message):
    one_line_error(replay(recording(tmp_path, packets, raw=raw)), message)


def test_a_gap_of_a_billion_seconds_is_shortened_not_waited_for(tmp_path):
    path = recording(tmp_path, [(0.0, 1.0, 0.0, 3.0), (1e9, 2.0, 0.0, 3.0),
                                (1e9 + 0.1, 3.0, 0.0, 3.0)])
    done = replay(path)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["packets"] == 3 and report["trace"].endswith("(1 pause over 2 s shortened)")
    assert report["duration_s"] >= MAX_GAP_S + 0.1 - 0.01  # the pause kept, shortened
    # at a fixed rate the times are not used at all: 3 packets, no 536 GiB of samples
    done = replay(path, "--rate", "72")
    assert done.returncode == 0 and json.loads(done.stdout)["packets"] == 3, done.stderr


def test_broken_times_replay_at_a_fixed_rate_and_speed_scales_the_recorded_ones(tmp_path):
    backwards = recording(tmp_path, [(5.0, 1.0, 0.0, 3.0), (1.0, 2.0, 0.0, 3.0)], "b.jsonl")
    done = replay(backwards, "--rate", "100")
    assert done.returncode == 0 and json.loads(done.stdout)["packets"] == 2, done.stderr
    steady = recording(tmp_path, [(0.01 * k, float(k), 0.0, 3.0) for k in range(41)], "s.jsonl")
    done = replay(steady, "--speed", "2")
    report = json.loads(done.stdout)
    assert report["packets"] == 41 and report["trace"].endswith("x2")
    assert report["duration_s"] >= 0.2 - 0.01  # 0.4 s of recording played twice as fast
    one_line_error(replay(steady, "--speed", "0"), "speed: expected a factor")


def test_replay_times_spread_a_batch_and_keep_a_small_step_back_in_order(tmp_path):
    # a batch of 4 read together (one read time) between packets at 1.0 and 1.04, and a packet
    # 0.5 ms before its predecessor (stamps of one batch): times spread, nothing goes at once
    path = recording(tmp_path, [(1.0, 0, 0, 1), (1.02, 1, 0, 1), (1.02, 2, 0, 1),
                                (1.02, 3, 0, 1), (1.02, 4, 0, 1), (1.04, 5, 0, 1),
                                (1.0395, 6, 0, 1), (1.06, 7, 0, 1)])
    trace = read_trace(path)
    assert np.allclose(trace.times, [0, 0.02, 0.025, 0.03, 0.035, 0.04, 0.05, 0.06])


def _any_json(depth: int = 3):
    leaves = st.none() | st.booleans() | st.integers() | st.text(max_size=5) | st.floats()
    return st.recursive(leaves, lambda inner: st.lists(inner, max_size=3)
                        | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                        max_leaves=8)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(packets=st.lists(st.dictionaries(
    st.sampled_from(["t", "x", "y", "z", "status"]),
    st.one_of(st.floats(), st.integers(-10**400, 10**400), st.none(), st.text(max_size=4),
              st.just("accepted"), _any_json()), max_size=5), min_size=1, max_size=6),
    tail=st.text(max_size=30))
def test_any_recording_reads_or_is_a_live_error(tmp_path, packets, tail):
    path = tmp_path / "fuzz.jsonl"
    body = "\n".join(json.dumps({"packet": p}) for p in packets)
    path.write_text(json.dumps(HEADER) + "\n" + body + "\n" + tail, encoding="utf-8")
    try:
        trace = read_trace(path)
    except LiveError as exc:
        assert "\n" not in str(exc)
        return
    assert np.all(np.diff(trace.times) > 0) and trace.times[-1] < MAX_GAP_S * len(trace) + 1


def test_serial_number_comparison_is_rfc_1982():
    # RFC 1982 section 5.2, SERIAL_BITS = 8: "0 < 1, 0 < 44, 0 < 100, 44 < 100, 100 < 200,
    # 200 < 255, 255 < 0, 255 < 100, 200 < 0, 200 < 44"
    for low, high in ((0, 1), (0, 44), (0, 100), (44, 100), (100, 200), (200, 255), (255, 0),
                      (255, 100), (200, 0), (200, 44)):
        assert newer(high, low, bits=8) and not newer(low, high, bits=8), (low, high)
    assert not newer(128, 0, bits=8) and not newer(0, 128, bits=8)  # undefined: neither
    assert newer(0, MAX_U32) and newer(5, MAX_U32 - 5) and not newer(MAX_U32, 0)
    assert not newer(7, 7) and newer(0, -1)


def _live(*options: str) -> tuple[subprocess.Popen, int]:
    live = subprocess.Popen(CLI + ["live", "--device", "sim://", "--listen", "127.0.0.1:0",
                                   *options], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    line = live.stderr.readline()
    assert "listening on" in line, line + live.stderr.read()
    return live, int(re.search(r"127\.0\.0\.1:(\d+)", line).group(1))


def _send(port: int, stream: int, sequences, gap_s: float = 0.01) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for k, sequence in enumerate(sequences):
            if sequence is None:  # silent past the timeout
                time.sleep(1.0)
                continue
            sock.sendto(encode_packet(FingerPacket(stream, sequence, 0.0, k * 0.5, 0.0, 4.0)),
                        ("127.0.0.1", port))
            time.sleep(gap_s)


@pytest.mark.parametrize("sequences, accepted, stale", [
    pytest.param([MAX_U32 - 2, MAX_U32 - 1, MAX_U32, 0, 1, 2], 6, 0, id="wraps"),
    pytest.param([1000, 3, 4, None, 5, 6, 7], 4, 2, id="behind-until-silence"),
    pytest.param([100, 101, 102, None, 0, 1, 2], 6, 0, id="restart-after-silence"),
    pytest.param([10, 11, 9, 11, 12], 3, 2, id="late-and-repeated-stay-stale"),
])
def test_sequence_numbers_wrap_and_restart_over_udp(sequences, accepted, stale):
    live, port = _live("--json", "--silence-s", "0.3",
                       "--max-packets", str(sum(s is not None for s in sequences)))
    try:
        _send(port, 0xC0FFEE, sequences)
        out, err = live.communicate(timeout=60)
    finally:
        live.kill()
    assert live.returncode == 0, err
    packets = json.loads(out)["packets"]
    assert (packets["accepted"], packets["stale"]) == (accepted, stale), packets


def test_a_second_signal_while_live_closes_still_exits_cleanly():
    for delay in (0.0, 0.2, 0.6):
        live, port = _live("--no-view")
        try:
            _send(port, 1, range(30))
            live.send_signal(signal.SIGINT)
            time.sleep(delay)
            live.send_signal(signal.SIGINT)
            out, err = live.communicate(timeout=60)
        finally:
            live.kill()
        assert live.returncode == 0, (delay, out, err)
        assert "stopped: Ctrl-C; display neutral, ports released" in out, (delay, out, err)
        assert "Traceback" not in err and "interrupted" not in err, (delay, err)
