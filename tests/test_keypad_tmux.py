"""The keypad's pause, end, hints and participant screens in a real 80 x 24 terminal.

``crs-study run --responder keypad`` runs inside tmux; keys go in with ``send-keys`` and what
a person would see is read with ``capture-pane``. Timeouts are generous (a busy machine).
"""

from __future__ import annotations

import csv
import json
import re
import sys
import time
from pathlib import Path

from _session_helpers import record_consent, tiny_letter_protocol, tiny_protocol
from _tmux import Tmux

from crs_study.paths import shipped_file

WAIT_S = 60.0


def _run(protocol: Path, label: str = "p01") -> str:
    return (f"{sys.executable} -m crs_study run {protocol} --participant {label} "
            "--device sim:// --out ds --responder keypad")


def _lines(screen: str) -> list[str]:
    return [line.rstrip() for line in screen.splitlines()]


def _fits(screen: str) -> None:
    lines = _lines(screen)
    assert len(lines) <= 24 and max(map(len, lines)) <= 80, screen


def _rows(tmp_path: Path, task: str = "digitid") -> list[dict[str, str]]:
    tsv = tmp_path / f"ds/sub-p01/ses-1/beh/sub-p01_ses-1_task-{task}_beh.tsv"
    with open(tsv, newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


def _sidecar(tmp_path: Path, task: str = "digitid") -> dict:
    path = tmp_path / f"ds/sub-p01/ses-1/beh/sub-p01_ses-1_task-{task}_beh.json"
    return json.loads(path.read_text(encoding="utf-8"))


def _translated_letters(tmp_path: Path) -> Path:
    """The tiny letter protocol on a copy of the letter set whose screens are in German."""
    text = shipped_file("letters.toml").read_text(encoding="utf-8")
    screens = ('\n[set.screens]\nanswer = "JETZT ANTWORTEN: die Taste des Buchstabens"\n'
               'time_left = "noch {seconds} s"\n'
               'unmapped = "die Taste {key} antwortet nichts: eine von {keys}"\n'
               'paused = "PAUSE: bitte warten"\n'
               'practice_over = "Die Übung ist vorbei: jetzt beginnt der Test"\n'
               'thank_you = "Vielen Dank! Die Sitzung ist beendet."\n')
    text = re.sub(r"(?m)^(instructions = .*)$", lambda m: m.group(1) + screens, text, count=1)
    (tmp_path / "letters_de.toml").write_text(text, encoding="utf-8")
    protocol = tiny_letter_protocol(tmp_path, symbols=("C", "L"))
    body = protocol.read_text(encoding="utf-8").replace('set = "letters"',
                                                        'set = "letters_de.toml"')
    protocol.write_text(body, encoding="utf-8")
    return protocol


def test_p_pauses_in_place_and_the_trial_is_played_again(tmp_path):
    """p during a stimulus: PAUSED (in the set's language), Space goes on with the same trial
    played again (rerun = 1, no second block prompt); a key that answers nothing gets a
    hint; the answer counts down; practice over and thank-you screens; exit 0."""
    record_consent("p01")
    protocol = _translated_letters(tmp_path)
    with Tmux(_run(protocol), tmp_path) as term:
        _fits(term.wait_for("Space or Enter continues", WAIT_S))
        term.send("Space")
        term.wait_for("Stimulus playing", WAIT_S)
        term.send("p")
        paused = term.wait_for("PAUSE: bitte warten", WAIT_S)
        _fits(paused)
        assert "Space or Enter goes on" in paused
        term.send("Space")
        term.wait_for("Stimulus playing", WAIT_S)  # the same trial again, no prompt first
        answer = term.wait_for("JETZT ANTWORTEN", WAIT_S)
        assert re.search(r"noch \d+ s", answer), answer
        term.send("x")
        hint = term.wait_for("die Taste x antwortet nichts: eine von c l", WAIT_S)
        _fits(hint)
        term.send("c")
        # the practice trial is over: the screen says so and waits for the experimenter
        over = term.wait_for("Die Übung ist vorbei", WAIT_S)
        _fits(over)
        term.send("Space")
        _answer_all(term, "l", "Vielen Dank")  # the test trials and the block prompt
        _fits(term.wait_for("Vielen Dank! Die Sitzung ist beendet.", WAIT_S))
        assert term.exit_code(WAIT_S) == 0
    rows = _rows(tmp_path, "letterid")
    assert [r["rerun"] for r in rows] == ["1"] + ["0"] * (len(rows) - 1)
    assert rows[0]["response"] == "C" and rows[0]["trial_type"] == "practice"


def _answer_all(term: Tmux, key: str, end: str) -> None:
    """Answer every trial with ``key`` and continue every prompt until ``end`` shows (a key
    sent twice is harmless: keys before a trial's onset or a prompt do not count)."""
    deadline = time.monotonic() + 3 * WAIT_S
    while time.monotonic() < deadline:
        screen = term.screen()
        if end in screen:
            return
        if "Space or Enter continues" in screen:
            term.send("Space")
        elif "ANTWORTEN" in screen or "ANSWER NOW" in screen:
            term.send(key)
        time.sleep(0.3)
    raise AssertionError(f"{end!r} never appeared; the screen:\n{term.screen()}")


def test_escape_during_a_long_stimulus_ends_at_once(tmp_path):
    """A stimulus of about half a minute: Escape ends the session long before it would
    have ended (display neutral, Paused, exit 130, the trial cut for a rerun on resume)."""
    record_consent("p01")
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, speed=2.0)
    with Tmux(_run(protocol), tmp_path) as term:
        term.wait_for("Space or Enter continues", WAIT_S)
        term.send("Space")
        term.wait_for("Stimulus playing", WAIT_S)
        sent = time.monotonic()
        term.send("Escape")
        paused = term.wait_for("Paused", WAIT_S)
        took = time.monotonic() - sent
        assert "ANSWER NOW" not in paused and "run the same command to resume" in paused
        assert term.exit_code(WAIT_S) == 130
    # the stimulus lasts 10 s or more: acting at its end would have taken that long
    stimulus = _stimulus_s(protocol)
    assert stimulus > 10 and took < stimulus / 2, (took, stimulus)
    sidecar = _sidecar(tmp_path)
    assert sidecar["Interruptions"][-1]["Cause"] == "pause-key"
    assert sidecar["Interruptions"][-1]["TrialCut"] is True


def _stimulus_s(protocol: Path) -> float:
    from crs_study.protocol import load_protocol
    from crs_study.stimuli.stimulus import make_stimulus

    loaded = load_protocol(protocol)
    layout = loaded.layout()
    return min(make_stimulus(loaded, layout, d).duration_s for d in loaded.symbols)


def test_one_space_does_not_end_a_break_and_unmapped_keys_get_a_hint(tmp_path):
    record_consent("p01")
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0, iti=0.2, break_every=1)
    text = protocol.read_text(encoding="utf-8")
    protocol.write_text(re.sub(r"(?m)^break_duration_s\s*=.*$", "break_duration_s = 30.0",
                               text), encoding="utf-8")
    with Tmux(_run(protocol), tmp_path) as term:
        term.wait_for("Space or Enter continues", WAIT_S)
        term.send("Space")
        term.wait_for("ANSWER NOW", WAIT_S)
        term.send("1")
        term.wait_for("Break: rest 0:", WAIT_S)
        term.send("Space")
        held = term.wait_for("the rest is not over", WAIT_S)
        _fits(held)
        assert "Break: rest 0:" in held and "Stimulus playing" not in held
        term.send("x")
        term.wait_for("Space or Enter continues (p pauses, q ends)", WAIT_S)
        term.send("Space")
        term.send("Space")  # two in a row: the experimenter means it
        term.wait_for("Stimulus playing", WAIT_S)
        term.send("q")
        term.wait_for("Paused", WAIT_S)
        assert term.exit_code(WAIT_S) == 130
    assert len(_rows(tmp_path)) == 1


def test_closing_the_terminal_is_a_clean_interruption(tmp_path):
    record_consent("p01")
    protocol = tiny_protocol(tmp_path, digits=(1, 7), practice=0)
    term = Tmux(_run(protocol), tmp_path)
    try:
        term.wait_for("Space or Enter continues", WAIT_S)
    finally:
        term.close()  # the terminal goes away: SIGHUP, then reads and writes fail
    deadline = time.monotonic() + WAIT_S
    sidecar = _sidecar(tmp_path)
    while sidecar["Status"] == "running" and time.monotonic() < deadline:
        time.sleep(0.2)
        sidecar = _sidecar(tmp_path)
    assert sidecar["Status"] == "interrupted"
    (last,) = sidecar["Interruptions"]
    assert last["Cause"] == "signal" and "terminal was closed" in last["Detail"], last
