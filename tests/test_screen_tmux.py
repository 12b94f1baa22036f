"""The keypad session's screen in a real terminal: ``crs-study run --responder keypad`` inside
an 80 x 24 tmux session, keys sent with ``send-keys`` (arrows and function keys as the escape
sequences a terminal sends), the screen read with ``capture-pane``.

What is checked is what a person sees: the status line, the instruction and the state each on
their own line, within 80 x 24; Space at a prompt shows it registered; "ANSWER NOW" once the
stimulus ends; a break counts its rest down; arrow and function keys (a numeric keypad with
NumLock off) do not pause and are reported; a lone Escape pauses.
"""

from __future__ import annotations

import csv
import re
import sys
import time

from _session_helpers import record_consent, tiny_protocol
from _tmux import Tmux


def protocol_with_breaks(tmp_path):
    path = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.2, break_every=1)
    text = path.read_text(encoding="utf-8")
    path.write_text(re.sub(r"(?m)^break_duration_s\s*=.*$", "break_duration_s = 3.0", text),
                    encoding="utf-8")
    return path


def rows_of(tmp_path):
    tsv = tmp_path / "ds/sub-p01/ses-1/beh/sub-p01_ses-1_task-digitid_beh.tsv"
    with open(tsv, newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


def lines(screen: str) -> list[str]:
    return [line.rstrip() for line in screen.splitlines()]


def test_screen_layout_keys_break_and_pause_in_tmux(tmp_path):
    record_consent("p01")  # a person's label: the consent gate holds on sim:// too
    protocol = protocol_with_breaks(tmp_path)
    command = (f"{sys.executable} -m crs_study run {protocol} --participant p01 "
               "--device sim:// --out ds --responder keypad")
    with Tmux(command, tmp_path) as term:
        # the block's prompt: status, rule, instruction, state and the experimenter's line
        screen = lines(term.wait_for("Space or Enter continues"))
        assert screen[0] == "participant p01  session 1  block 1/2  trial 1/4  pixel-only", screen
        assert screen[1].startswith("-----")
        assert screen[2].startswith("Rest your fingertips on the display.")
        assert "Waiting for the experimenter" in screen
        experimenter = [x for x in screen if x.startswith("Experimenter: ")]
        assert experimenter and "block" in experimenter[0].lower(), screen
        assert len([x for x in screen if x]) <= 24 and max(map(len, screen)) <= 80
        term.send("Space")
        shown = term.wait_for("ANSWER NOW")  # after the stimulus: the participant must answer
        assert "Continuing" in shown or "Stimulus playing" in shown or "ANSWER NOW" in shown
        assert lines(shown)[0].endswith("trial 1/4  pixel-only"), shown
        # arrows and a function key (what NumLock off sends) are ignored, not a pause
        term.send("Up", "Down", "F5", "Home")
        shown = term.wait_for("was ignored")
        assert "Paused" not in shown and "ANSWER NOW" in shown
        term.send("7")
        # the break before trial 2 counts its rest down, second by second
        first = term.wait_for("Break: rest 0:0")
        left = int(re.search(r"Break: rest 0:0(\d) left", first).group(1))
        time.sleep(1.3)
        later = term.wait_for("Break")
        match = re.search(r"Break: rest 0:0(\d) left", later)
        assert (match and int(match.group(1)) < left) or "Break over" in later, later
        term.send("Space")
        term.send("Space")  # twice: one Space alone does not cut a break's rest short
        term.wait_for("trial 2/4")
        term.wait_for("ANSWER NOW")
        term.send("Escape")  # alone: the pause key
        paused = term.wait_for("Paused")
        assert "run the same command to resume" in paused
        assert term.exit_code() == 130
    rows = rows_of(tmp_path)
    assert [r["response"] for r in rows] == ["7"]  # trial 2 was paused, not answered


def test_the_experimenter_view_split_to_a_log(tmp_path):
    """``--experimenter-view LOG``: the participant's terminal shows the instruction and the
    state only; the experimenter's lines (status, state, what to do) go to the log, timed."""
    record_consent("p01")
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.2)
    log = tmp_path / "experimenter.log"
    command = (f"{sys.executable} -m crs_study run {protocol} --participant p01 "
               f"--device sim:// --out ds --responder keypad --experimenter-view {log}")
    with Tmux(command, tmp_path) as term:
        shown = term.wait_for("Waiting for the experimenter")
        assert "participant p01" not in shown and "Experimenter:" not in shown
        assert lines(shown)[0].startswith("Rest your fingertips on the display.")
        term.send("Enter")
        term.wait_for("ANSWER NOW")
        term.send("q")
        term.wait_for("Paused")
        assert term.exit_code() == 130
    text = log.read_text()
    assert re.search(r"^\d\d:\d\d:\d\d participant p01  session 1  block 1/2  trial 1/4  "
                     r"pixel-only$", text, re.M), text
    assert re.search(r"^\d\d:\d\d:\d\d experimenter: Pixel-only block: .* -- Space or Enter "
                     r"continues, p pauses, q ends$", text, re.M), text
    assert "state: ANSWER NOW" in text and "state: Paused" in text
