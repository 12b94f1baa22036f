"""The session screen's views, as pure functions of its state, and how a stream gets them."""

from __future__ import annotations

import io

from crs_study.session.screen import (
    ScreenState,
    TerminalScreen,
    experimenter_lines,
    participant_lines,
    shared_lines,
    status_line,
)

STATE = ScreenState(participant="p7k2m9q", session=1, block=2, n_blocks=2, trial=61,
                    n_trials=120, condition="crs", state="ANSWER NOW: press the digit",
                    experimenter="CRS block: mount the skeleton")


def test_the_status_line_names_participant_session_block_trial_and_condition():
    assert status_line(STATE) == "participant p7k2m9q  session 1  block 2/2  trial 61/120  crs"
    assert status_line(ScreenState()) == ""


def test_each_thing_on_its_own_line_within_80_columns():
    shared = shared_lines(STATE)
    assert shared[0] == status_line(STATE)
    assert "ANSWER NOW: press the digit" in shared
    assert shared[-1] == "Experimenter: CRS block: mount the skeleton"
    assert max(map(len, shared)) <= 80 and len(shared) <= 24
    assert status_line(STATE) not in participant_lines(STATE)  # the participant's view
    assert experimenter_lines(STATE)[0] == status_line(STATE)
    narrow = shared_lines(STATE, width=40)
    assert max(map(len, narrow)) <= 40


def test_a_split_screen_logs_changes_to_the_experimenter_with_the_time():
    participant, experimenter = io.StringIO(), io.StringIO()
    screen = TerminalScreen(participant, experimenter)
    screen.show(participant="p1", trial=1, n_trials=4, state="Stimulus playing")
    screen.show(state="ANSWER NOW")
    screen.show(state="ANSWER NOW")  # nothing changed: nothing written
    log = experimenter.getvalue().splitlines()
    assert len(log) == 3 and log[0].endswith(" participant p1  trial 1/4")
    assert log[2].endswith(" state: ANSWER NOW") and log[2][2] == ":"  # HH:MM:SS prefix
    assert "participant p1" not in participant.getvalue()
    assert participant.getvalue().splitlines()[-1] == "ANSWER NOW"
