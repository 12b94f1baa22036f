"""Keys from a terminal's byte stream: single characters, escape sequences, a lone Escape.

An arrow or function key arrives as an escape sequence (ECMA-48): ``ESC [ ... final`` (CSI:
parameter bytes ``0x30-0x3F``, intermediate bytes ``0x20-0x2F``, one final byte
``0x40-0x7E``; arrows ``ESC [ A``, F5 ``ESC [ 1 5 ~``, Ctrl-Up ``ESC [ 1 ; 5 A``) or
``ESC O final`` (SS3: arrows in application mode, F1-F4; a numeric keypad with NumLock off
sends these). ``ESC`` followed by any other character is that character with Alt held. A
lone Escape is an ``ESC`` after which nothing arrives within :data:`ESCAPE_TIMEOUT_S`, the
disambiguation curses (``ESCDELAY``) and vim (``ttimeoutlen``) make. :class:`KeyDecoder`
turns the stream into :class:`Key` events; the digits inside a sequence never answer a trial.

References
----------
ECMA-48, *Control Functions for Coded Character Sets*, 5th ed. (1991), 5.4 (control
sequences) and 8.3.16 (CSI); xterm's *ctlseqs* for the keys' sequences.
"""

from __future__ import annotations

from dataclasses import dataclass

ESC = "\x1b"
#: How long after an ``ESC`` the rest of a sequence may arrive (vim's ``ttimeoutlen``
#: default); after that it is a lone Escape (a terminal sends a key's whole sequence in
#: one write, microseconds apart).
ESCAPE_TIMEOUT_S = 0.1
#: The event of a lone Escape (the character itself, as in ``PAUSE_KEYS``).
LONE_ESCAPE = ESC
#: Longest sequence kept; anything longer is dropped as one unknown sequence.
MAX_SEQUENCE = 32


@dataclass(frozen=True)
class Key:
    """One key: ``text`` is a single character (``"\\x1b"`` for a lone Escape) or, for a
    sequence, the whole sequence with ``sequence`` True; ``time`` is when its first byte
    arrived (:func:`time.monotonic`)."""

    time: float
    text: str
    sequence: bool = False


class KeyDecoder:
    """Characters in, :class:`Key` events out (module docstring); pure, no I/O."""

    def __init__(self) -> None:
        self._pending = ""
        self._since = 0.0

    @property
    def pending(self) -> bool:
        """True while an ``ESC`` waits for the rest of its sequence."""
        return bool(self._pending)

    def deadline(self) -> float | None:
        """When a pending ``ESC`` becomes a lone Escape (None when nothing is pending)."""
        return self._since + ESCAPE_TIMEOUT_S if self._pending else None

    def feed(self, text: str, now: float) -> list[Key]:
        """The keys completed by ``text``, which arrived at ``now``."""
        keys: list[Key] = []
        if self._pending and now > self._since + ESCAPE_TIMEOUT_S:
            keys += self.flush(now)
        for char in text:
            if not self._pending:
                if char == ESC:
                    self._pending, self._since = char, now
                else:
                    keys.append(Key(now, char))
                continue
            self._pending += char
            done = self._complete(self._pending)
            if done is None:
                if len(self._pending) > MAX_SEQUENCE:
                    keys.append(Key(self._since, self._pending, sequence=True))
                    self._pending = ""
                continue
            if done == "lone":  # ESC ESC: the first was a lone Escape, the second may begin
                keys.append(Key(self._since, LONE_ESCAPE))
                self._pending, self._since = ESC, now
            else:
                keys.append(Key(self._since, self._pending, sequence=True))
                self._pending = ""
        return keys

    def flush(self, now: float) -> list[Key]:
        """At or after :meth:`deadline`: a pending lone ``ESC`` is a lone Escape; a sequence
        cut short is dropped as an unknown one."""
        if not self._pending or now < self._since + ESCAPE_TIMEOUT_S:
            return []
        pending, self._pending = self._pending, ""
        if pending == ESC:
            return [Key(self._since, LONE_ESCAPE)]
        return [Key(self._since, pending, sequence=True)]

    @staticmethod
    def _complete(seq: str) -> str | None:
        """``"seq"`` when ``seq`` (starting with ESC) is a whole sequence, ``"lone"`` when its
        first ESC stands alone, None while more is needed."""
        second = seq[1]
        if second == ESC:
            return "lone"
        if second == "[":
            if len(seq) == 2:
                return None
            last = ord(seq[-1])
            if 0x40 <= last <= 0x7E:
                return "seq"
            if 0x20 <= last <= 0x3F:
                return None
            return "seq"  # not a valid CSI byte: the sequence ends here, dropped
        if second == "O":
            return None if len(seq) == 2 else "seq"
        return "seq"  # Alt + character
