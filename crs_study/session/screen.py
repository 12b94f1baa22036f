"""The session's screen: what the participant and the experimenter see during a keypad session.

Three things, each on its own line (wrapped to the terminal's width, 80 columns by default):

* the **status line**: participant, session, block, trial and condition
  (``participant p7k2m9q  session 1  block 2/4  trial 13/120  crs``);
* the **instruction** the participant was given (the stimulus set's ``instructions``);
* the **state**: ``Stimulus playing``, ``ANSWER NOW``, ``Paused``, ``Break`` with the rest
  left, ``Continuing`` once Space was pressed, or the experimenter's prompt;

then a note (the feedback of a practice trial, a key that was ignored). :class:`ScreenState`
holds them; :func:`participant_lines` and :func:`experimenter_lines` are the two views, pure
functions of it. A :class:`TerminalScreen` draws them: both on one terminal (the default:
status, instruction, state, note, then the experimenter's line, 9 rows of an 80 x 24
terminal), or split, the participant's view on one stream and the experimenter's on another
(a second terminal such as ``/dev/pts/4``, or a log file). A terminal is redrawn in place
(cursor home, each line cleared to its end); a file or pipe gets each changed line once, the
experimenter's lines with the wall-clock time.
"""

from __future__ import annotations

import os
import textwrap
import time
from dataclasses import dataclass, replace
from typing import TextIO

#: Width used when a terminal does not say.
DEFAULT_WIDTH = 80
#: Width of a file or pipe (no wrapping).
LOG_WIDTH = 10_000
#: Erase to the end of the line; move the cursor to the top-left; erase below the cursor.
_CLEAR_LINE, _HOME, _CLEAR_BELOW = "\x1b[K", "\x1b[H", "\x1b[J"


@dataclass(frozen=True)
class ScreenState:
    """What the screen shows (module docstring). Counts are 1-based; None: not known yet."""

    participant: str = ""
    session: int | None = None
    block: int | None = None
    n_blocks: int | None = None
    trial: int | None = None
    n_trials: int | None = None
    condition: str = ""
    instruction: str = ""  # the stimulus set's instructions (the keypad sets them)
    state: str = "Getting ready"
    note: str = ""
    experimenter: str = ""  # what the experimenter must do now (a prompt), else empty


def status_line(s: ScreenState) -> str:
    """``participant ID  session N  block b/B  trial t/T  CONDITION`` (parts not yet known are
    left out)."""
    parts = []
    if s.participant:
        parts.append(f"participant {s.participant}")
    if s.session is not None:
        parts.append(f"session {s.session}")
    if s.block is not None:
        parts.append(f"block {s.block}" + (f"/{s.n_blocks}" if s.n_blocks else ""))
    if s.trial is not None:
        parts.append(f"trial {s.trial}" + (f"/{s.n_trials}" if s.n_trials else ""))
    if s.condition:
        parts.append(s.condition)
    return "  ".join(parts)


def _wrap(text: str, width: int) -> list[str]:
    return textwrap.wrap(text, width=max(20, width)) or [""]


def participant_lines(s: ScreenState, width: int = DEFAULT_WIDTH) -> list[str]:
    """The participant's view: the instruction, a blank line, the state and the note."""
    return [*_wrap(s.instruction, width), "", *_wrap(s.state, width), *_wrap(s.note, width)]


def experimenter_lines(s: ScreenState, width: int = DEFAULT_WIDTH) -> list[str]:
    """The experimenter's view: the status line, the state and what to do now."""
    lines = [*_wrap(status_line(s), width), *_wrap(f"state: {s.state}", width)]
    if s.experimenter:
        lines += _wrap(f"experimenter: {s.experimenter}", width)
    if s.note:
        lines += _wrap(f"note: {s.note}", width)
    return lines


def shared_lines(s: ScreenState, width: int = DEFAULT_WIDTH) -> list[str]:
    """Both views on one terminal: status, a rule, instruction, state, note, then the
    experimenter's line."""
    lines = [*_wrap(status_line(s), width), "-" * min(width, DEFAULT_WIDTH),
             *participant_lines(s, width), ""]
    lines += _wrap(f"Experimenter: {s.experimenter}", width) if s.experimenter else [""]
    return lines


class TerminalScreen:
    """Draws a :class:`ScreenState` on the participant's stream and, when given, the
    experimenter's (module docstring). :meth:`show` changes some fields and redraws."""

    def __init__(self, participant: TextIO, experimenter: TextIO | None = None) -> None:
        self.participant = participant
        self.experimenter = experimenter
        self.state = ScreenState()
        self._drawn: dict[int, list[str]] = {}
        self._gone: set[int] = set()  # streams that could not be written (a closed terminal)

    def show(self, **changes: object) -> ScreenState:
        """Set the fields named in ``changes`` (those of :class:`ScreenState`) and redraw."""
        self.state = replace(self.state, **changes)  # type: ignore[arg-type]
        if self.experimenter is None:
            self._draw(self.participant, shared_lines)
        else:
            self._draw(self.participant, participant_lines)
            self._draw(self.experimenter, experimenter_lines, stamp=True)
        return self.state

    def clear(self) -> None:
        """Start from an empty terminal (a file is left alone)."""
        for stream in (self.participant, self.experimenter):
            if stream is not None and _isatty(stream) and id(stream) not in self._gone:
                try:
                    stream.write("\x1b[2J" + _HOME)
                    stream.flush()
                except OSError:
                    self._gone.add(id(stream))
        self._drawn.clear()

    def _draw(self, stream: TextIO, view, stamp: bool = False) -> None:
        if id(stream) in self._gone:
            return
        lines = view(self.state, _width(stream))
        before = self._drawn.get(id(stream))
        if lines == before:
            return
        self._drawn[id(stream)] = lines
        try:
            if _isatty(stream):
                stream.write(_HOME + "".join(line + _CLEAR_LINE + "\r\n" for line in lines)
                             + _CLEAR_BELOW)
            else:
                old = set(before or ())
                prefix = time.strftime("%H:%M:%S ") if stamp else ""
                stream.write("".join(f"{prefix}{line}\n" for line in lines
                                     if line.strip() and line not in old))
            stream.flush()
        except OSError:
            # the terminal is gone (closed: EIO), or the log's disk: nobody to show it to,
            # and what stops the session (SIGHUP, the keypad's end of input) says why
            self._gone.add(id(stream))


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError, OSError):
        return False


def _width(stream: TextIO) -> int:
    """The terminal's width; a file or a pipe is not wrapped (one event, one line)."""
    if not _isatty(stream):
        return LOG_WIDTH
    try:
        return os.get_terminal_size(stream.fileno()).columns or DEFAULT_WIDTH
    except (AttributeError, ValueError, OSError):
        return DEFAULT_WIDTH
