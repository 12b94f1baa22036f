"""The keypad's key decoder: escape sequences (ECMA-48 CSI and SS3, as xterm's ctlseqs lists
them for arrows, Home/End and function keys) are whole keys that never answer; a lone Escape,
after the escape timeout, is the pause key; the decoding does not depend on how the bytes were
split into reads."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.session.responders.keys import ESCAPE_TIMEOUT_S, Key, KeyDecoder

# xterm ctlseqs: arrows (normal and application mode), Home/End, Insert/Delete (a keypad with
# NumLock off), F1-F4 (SS3), F5-F12 (CSI n ~), modified arrows (CSI 1 ; m A)
SEQUENCES = ["\x1b[A", "\x1b[B", "\x1b[C", "\x1b[D", "\x1bOA", "\x1bOD", "\x1b[H", "\x1b[F",
             "\x1b[1~", "\x1b[2~", "\x1b[3~", "\x1b[4~", "\x1b[5~", "\x1b[6~", "\x1bOP",
             "\x1bOS", "\x1b[15~", "\x1b[24~", "\x1b[1;5A", "\x1b[1;2D", "\x1bOE", "\x1b[E"]


def decode(chunks, gap=0.0):
    decoder, out, now = KeyDecoder(), [], 0.0
    for chunk in chunks:
        out += decoder.feed(chunk, now)
        now += gap
    return out + decoder.flush(now + ESCAPE_TIMEOUT_S)


@pytest.mark.parametrize("sequence", SEQUENCES)
def test_an_arrow_or_function_key_is_one_ignored_key(sequence):
    keys = decode([sequence])
    assert keys == [Key(0.0, sequence, sequence=True)]


def test_a_lone_escape_pauses_only_after_the_timeout():
    decoder = KeyDecoder()
    assert decoder.feed("\x1b", 1.0) == []
    assert decoder.pending and decoder.deadline() == pytest.approx(1.0 + ESCAPE_TIMEOUT_S)
    assert decoder.flush(1.0 + ESCAPE_TIMEOUT_S / 2) == []  # the rest may still come
    assert decoder.flush(1.0 + ESCAPE_TIMEOUT_S) == [Key(1.0, "\x1b")]
    # a key long after the Escape: the Escape stood alone, the key is itself
    decoder.feed("\x1b", 2.0)
    assert decoder.feed("7", 3.0) == [Key(2.0, "\x1b"), Key(3.0, "7")]


def test_two_escapes_and_alt_keys():
    assert decode(["\x1b\x1b[A"]) == [Key(0.0, "\x1b"), Key(0.0, "\x1b[A", sequence=True)]
    assert decode(["\x1b7"]) == [Key(0.0, "\x1b7", sequence=True)]  # Alt-7 does not answer


token = st.one_of(st.sampled_from(SEQUENCES), st.sampled_from(list("0123456789qx ")))


@settings(max_examples=200, deadline=None)
@given(st.lists(token, max_size=30), st.data())
def test_decoding_does_not_depend_on_the_reads(tokens, data):
    text = "".join(tokens)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(text)), max_size=8)))
    chunks = [text[a:b] for a, b in zip([0, *cuts], [*cuts, len(text)], strict=True)]
    keys = decode(chunks)  # all within the timeout: one burst, however split
    assert [k.text for k in keys] == tokens
    assert [k.sequence for k in keys] == [len(t) > 1 for t in tokens]
