"""The keypad responder in a real terminal: a pseudo-terminal pair, keys written to the master.

Response times are checked against time.monotonic (CLOCK_MONOTONIC, one clock for every
process on Linux): the key's time stamp is never before the moment the key was written and at
most a few milliseconds after it (the reader thread wakes on select()).
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
import termios
import textwrap
import threading
import time

import numpy as np
import pytest
from _session_helpers import record_consent

from crs_study.clock import RealClock
from crs_study.session.responders.base import StimulusRecord
from crs_study.session.responders.keypad import KeypadResponder, PauseRequested


@pytest.fixture(autouse=True)
def _consented():
    """p01: people's labels, gated by consent on every device, sim:// too."""
    record_consent("p01")


#: Allowed delay between writing a key and its time stamp (s): a behaviour bound (the stamp
#: is the key's, not the next poll's), generous for a loaded machine. How close the stamp
#: typically is (a median within a millisecond) is a figure of ``crs-study bench runner``.
STAMP_SLACK_S = 0.05


class Trial:
    index, digit, block, condition, trial_type = 0, 7, 1, "crs", "test"


@pytest.fixture
def terminal():
    master, slave = os.openpty()
    yield master, slave
    os.close(master)
    os.close(slave)


def stimulus(onset, duration):
    return StimulusRecord(None, "crs", np.zeros(1), np.zeros((1, 1)), tuple(range(10)), onset,
                          onset + duration)


def test_one_key_no_enter_stamped_when_it_is_written(terminal):
    master, slave = terminal
    before = termios.tcgetattr(slave)
    clock = RealClock()
    errors = []
    with KeypadResponder(fd=slave, output=io.StringIO()) as keypad:
        assert not termios.tcgetattr(slave)[3] & termios.ICANON  # cbreak: no Enter needed
        for digit in (7, 3, 0, 5, 9):
            onset = clock.now()
            keypad.begin_trial(Trial, onset, clock)
            time.sleep(0.05)
            written = time.monotonic()
            os.write(master, str(digit).encode())
            answer = keypad.respond(Trial, stimulus(onset, 0.02), clock, 5.0)
            keypad.end_trial()
            assert answer.symbol == digit
            errors.append(answer.response_time_s - (written - onset))
    assert termios.tcgetattr(slave) == before  # the terminal is restored
    assert min(errors) >= 0 and max(errors) < STAMP_SLACK_S, errors


def test_keys_during_the_stimulus_count(terminal):
    master, slave = terminal
    clock = RealClock()
    with KeypadResponder(fd=slave, output=io.StringIO()) as keypad:
        onset = clock.now()
        keypad.begin_trial(Trial, onset, clock)
        time.sleep(0.03)
        os.write(master, b"x5")  # an unknown key is ignored, 5 answers mid-stimulus
        time.sleep(0.1)  # the stimulus goes on; respond() is called after the offset
        answer = keypad.respond(Trial, stimulus(onset, 0.12), clock, 5.0)
    assert answer.symbol == 5
    assert 0.03 <= answer.response_time_s < 0.03 + 0.03
    assert answer.response_time_s - 0.12 < 0  # negative RT from offset


def test_keys_before_onset_are_dropped_and_time_out(terminal):
    master, slave = terminal
    clock = RealClock()
    with KeypadResponder(fd=slave, output=io.StringIO()) as keypad:
        os.write(master, b"4")
        time.sleep(0.05)
        onset = clock.now()
        keypad.begin_trial(Trial, onset, clock)
        answer = keypad.respond(Trial, stimulus(onset, 0.01), clock, 0.1)
    assert answer.symbol is None and answer.response_time_s == pytest.approx(0.11)
    assert clock.now() - onset >= 0.11


def write_when_shown(keypad, master, text, data):
    """Write ``data`` to the terminal once the screen shows ``text`` to the experimenter (a
    thread), so the key cannot arrive before the prompt it answers."""
    def wait_and_write():
        deadline = time.monotonic() + 10
        while text not in keypad.screen.state.experimenter and time.monotonic() < deadline:
            time.sleep(0.002)
        os.write(master, data)
    writer = threading.Thread(target=wait_and_write, daemon=True)
    writer.start()
    return writer


def test_quit_key_pauses_and_prompt_waits_for_space(terminal):
    master, slave = terminal
    clock = RealClock()
    with KeypadResponder(fd=slave, output=io.StringIO()) as keypad:
        write_when_shown(keypad, master, "Mount the skeleton", b" ")
        keypad.prompt("Mount the skeleton", clock)
        onset = clock.now()
        keypad.begin_trial(Trial, onset, clock)
        os.write(master, b"q")
        with pytest.raises(PauseRequested):
            keypad.respond(Trial, stimulus(onset, 0.0), clock, 5.0)
        assert issubclass(PauseRequested, KeyboardInterrupt)


def test_stdin_of_a_child_process(terminal):
    """The keypad on a child's stdin (a real tty), as in `crs-study run --responder keypad`."""
    master, slave = terminal
    script = textwrap.dedent("""
        import sys, time
        import numpy as np
        from crs_study.clock import RealClock
        from crs_study.session.responders.base import StimulusRecord
        from crs_study.session.responders.keypad import KeypadResponder
        class Trial:
            index, digit, block, condition, trial_type = 0, 2, 1, "crs", "test"
        clock = RealClock()
        with KeypadResponder(output=sys.stderr) as keypad:
            onset = clock.now()
            keypad.begin_trial(Trial, onset, clock)
            print(f"ready {onset!r}", flush=True)
            rec = StimulusRecord(None, "crs", np.zeros(1), np.zeros((1, 1)), tuple(range(10)),
                                 onset, onset)
            answer = keypad.respond(Trial, rec, clock, 10.0)
        print(f"answer {answer.symbol} {answer.response_time_s!r}", flush=True)
    """)
    child = subprocess.Popen([sys.executable, "-c", script], stdin=slave,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready = child.stdout.readline().split()
        assert ready[0] == "ready", child.stderr.read()
        onset = float(ready[1])
        time.sleep(0.2)
        written = time.monotonic()
        os.write(master, b"2")
        answer = child.stdout.readline().split()
        child.wait(timeout=10)
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
        child.stderr.close()
    assert answer[:2] == ["answer", "2"]
    error = float(answer[2]) - (written - onset)
    assert 0 <= error < STAMP_SLACK_S


@pytest.mark.slow
def test_crs_study_run_with_the_keypad_in_a_terminal(tmp_path, terminal):
    """`crs-study run --responder keypad` with a pty as its terminal: prompts wait for Space,
    digits answer without Enter (here during the stimulus), every trial is stored."""
    import csv
    import select

    from _session_helpers import tiny_protocol

    master, slave = terminal
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.2)
    dataset = tmp_path / "ds"
    child = subprocess.Popen(
        [sys.executable, "-m", "crs_study", "run", str(protocol), "--participant", "p01",
         "--device", "sim://", "--out", str(dataset), "--responder", "keypad"],
        stdin=slave, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    seen = []
    buffer = b""
    try:
        deadline = time.monotonic() + 120
        pending = None  # the trial whose answer is due
        while child.poll() is None and time.monotonic() < deadline:
            ready, _, _ = select.select([child.stderr], [], [], 0.1)
            if ready:  # raw reads: a buffered readline would hide lines from select()
                buffer += os.read(child.stderr.fileno(), 4096)
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                line = raw.decode()
                seen.append(line)
                if "Space or Enter continues" in line:
                    os.write(master, b" ")
                elif "trial " in line and "/4" in line:  # the status line: a trial begins
                    pending = time.monotonic()  # (its prompt, if any, came before)
            if pending is not None and time.monotonic() - pending > 0.3:
                os.write(master, b"7")
                pending = None
        child.wait(timeout=30)
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
        child.stderr.close()
    assert child.returncode == 0, "\n".join(seen)
    tsv = dataset / "sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.tsv"
    with open(tsv, newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    assert [r["response"] for r in rows] == ["7"] * 4
    assert all(r["responder"] == "keypad" for r in rows)
    assert all(float(r["response_time_from_offset"]) < 0 for r in rows)  # during the stimulus
