"""Durable file primitives: atomic replace, one-write appends, one-line OS errors."""

from __future__ import annotations

import errno
import os

import pytest

import crs_study._files as files
from crs_study._files import (
    append_durably,
    describe_os_error,
    make_dirs,
    os_errors,
    sha256_bytes,
    sha256_file,
    write_atomically,
)
from crs_study.errors import DatasetError


def test_sha256_matches_a_published_vector(tmp_path):
    # FIPS 180-2, appendix B.1: sha256("abc")
    abc = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert sha256_bytes(b"abc") == abc
    (tmp_path / "f").write_bytes(b"abc")
    assert sha256_file(tmp_path / "f") == abc


def test_write_atomically_failure_keeps_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    """A full disk while writing the replacement: the old file whole, no .tmp debris."""
    target = tmp_path / "meta.json"
    write_atomically(target, "old")

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", no_space)
    with pytest.raises(OSError, match="No space left"):
        write_atomically(target, "new")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["meta.json"]


def test_write_atomically_sets_the_mode_before_the_name(tmp_path):
    target = tmp_path / "register.jsonl"
    write_atomically(target, "x", mode=0o600)
    assert target.stat().st_mode & 0o777 == 0o600


def test_short_append_is_cut_back(tmp_path, monkeypatch):
    """A write cut short (disk full) leaves only whole appends in the file."""
    target = tmp_path / "rows.tsv"
    append_durably(target, b"header\n", create=True)
    append_durably(target, b"row 1\n")
    real = os.write
    monkeypatch.setattr(files.os, "write", lambda fd, data: real(fd, bytes(data)[:3]))
    with pytest.raises(OSError, match="short write"):
        append_durably(target, b"row 2\n")
    monkeypatch.undo()
    assert target.read_bytes() == b"header\nrow 1\n"


def test_os_errors_are_one_line_and_name_the_path(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(DatasetError, match=r"^.*/file/ds: cannot create: Not a directory$"):
        with os_errors(DatasetError, "create"):
            make_dirs(blocker / "ds")
    error = OSError(errno.ENOSPC, "No space left on device")
    assert describe_os_error(error, "append to", "x.tsv") == \
        "x.tsv: cannot append to: No space left on device"
