"""Bench area ``writes``: the refresh riding on a frame against sending it on its own.

Wire arithmetic (docs/device.md): a 19-servo SERVO_MOVE is 64 bytes, 66.7 ms at 9600 baud. Riding,
the worst frame is the one carrying the refresh: exactly one full frame's wire time. On its
own, a refresh that falls due between two frames makes the next frame wait behind it.
"""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from crs_study.cli import main


def test_riding_is_never_slower_and_sends_fewer_bytes():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["bench", "writes", "--quick", "--json"]) == 0
    largest, p99, sent = [json.loads(line) for line in out.getvalue().splitlines()]
    assert largest["value"] == pytest.approx(64 * 10 / 9600)  # one full frame, no more
    assert largest["baseline"] > 64 * 10 / 9600 + 0.02  # a frame waited behind a refresh
    assert p99["value"] <= p99["baseline"]
    assert sent["unit"] == "bytes" and sent["value"] < sent["baseline"]
