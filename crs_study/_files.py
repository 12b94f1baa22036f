"""Durable file primitives shared by the dataset, the consent register and the analysis.

One place for what must be done in the right order to keep data through a crash or a power
cut (POSIX; see fsync(2) and rename(2)):

* :func:`write_atomically` replaces a file whole or not at all: temporary file beside it,
  write, fsync, ``os.replace``, fsync of the directory (so the new name survives a power cut).
  The temporary file is removed when anything fails, so a full disk leaves no debris.
* :func:`append_durably` appends with a single ``write`` and fsyncs: after a kill the file
  holds all of the data or a torn tail that the reader can recognise and cut.
* :func:`fsync_dir` / :func:`make_dirs` make created or renamed entries durable.

Failures of the operating system (disk full, permission denied, a path that is a file) are
turned into one-line :class:`~crs_study.errors.CrsStudyError` s naming the path, by
:func:`os_errors` and by the ``error`` argument of the writers.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from crs_study.errors import CrsStudyError


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    return sha256_bytes(Path(path).read_bytes())


def not_a_regular_file(path: Path) -> str | None:
    """Why ``path`` cannot be read as a file (a folder, a named pipe, ...), or None when it
    is one. Reading a named pipe would wait for a writer forever; root reads any file, so
    these are the unreadable files root meets too."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder, not a file"
    if stat.S_ISFIFO(mode):
        return "a named pipe, not a file"
    return "not a regular file"


def describe_os_error(error: OSError, what: str = "", path: str | Path | None = None) -> str:
    """``PATH: cannot WHAT: No space left on device`` (one line, the path named).

    ``path`` names the file when the error does not (``os.write`` errors carry no name).
    """
    where = error.filename if error.filename is not None else (path or "")
    action = f"cannot {what}: " if what else ""
    reason = error.strerror or str(error) or type(error).__name__
    return f"{where}: {action}{reason}" if where else f"{action}{reason}"


@contextlib.contextmanager
def os_errors(error: type[CrsStudyError], what: str = "",
              path: str | Path | None = None) -> Iterator[None]:
    """Within the block (or the decorated function) an :class:`OSError` becomes ``error``
    with a one-line message."""
    try:
        yield
    except OSError as exc:
        raise error(describe_os_error(exc, what, path)) from None


def check_writable(out: str | Path, error: type[CrsStudyError], option: str = "--out") -> None:
    """``out`` can be made and written, checked before any work: a folder made and removed at
    once in the nearest folder that exists (the realest test: permissions, read-only or
    virtual file systems, a file where a folder should be)."""
    out = Path(out)
    parent = out if out.is_dir() else next((p for p in out.absolute().parents if p.exists()),
                                           None)
    if parent is None or not parent.is_dir():
        raise error(f"{option}: {out} cannot be made ({parent} is not a folder); nothing was "
                    "computed")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".crs-study-", dir=parent))
    except OSError as exc:
        raise error(f"{option}: cannot write in {parent} ({exc.strerror or exc}); nothing "
                    "was computed") from None


def fsync_dir(directory: str | Path) -> None:
    """Make a directory's entries (a created, renamed or removed file) durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_path(path: str | Path) -> None:
    """fsync a file's data by path (a file written without fsync earlier)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_dirs(directory: str | Path, mode: int = 0o777) -> None:
    """Create ``directory`` and its parents, fsyncing each new entry's parent."""
    missing = []
    path = Path(directory)
    while not path.exists():
        if path.is_symlink():  # exists() follows links: a loop or a missing target
            raise NotADirectoryError(errno.ENOTDIR, "a symbolic link that leads nowhere (a "
                                     "loop, or its target is missing); expected a folder",
                                     str(path))
        missing.append(path)
        path = path.parent
    for path in reversed(missing):
        path.mkdir(mode=mode, exist_ok=True)
        fsync_dir(path.parent)


def write_atomically(path: str | Path, data: bytes | str, *, durable: bool = True,
                     sync_dir: bool = True, mode: int | None = None) -> None:
    """Replace ``path`` whole or not at all: temporary file, fsync, ``os.replace``, dir fsync.

    ``durable=False`` skips the fsyncs: the replacement is still atomic for readers and
    survives the process being killed, but not a power cut. ``mode`` sets the permissions of
    the new file (e.g. ``0o600``) before it takes the name. On any failure the temporary
    file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    if isinstance(data, str):
        data = data.encode("utf-8")
    temp = path.with_name(f".{path.name}.tmp")
    try:
        fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC,
                     0o666 if mode is None else mode)
        try:
            view = memoryview(data)
            while view:  # os.write may write less than asked on some file systems
                view = view[os.write(fd, view):]
            if mode is not None:
                os.fchmod(fd, mode)
            if durable:
                os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            temp.unlink()
        raise
    if durable and sync_dir:
        fsync_dir(path.parent)


def append_durably(path: str | Path, data: bytes, *, create: bool = False, sync: bool = True,
                   mode: int = 0o644) -> None:
    """Append ``data`` with one ``write`` and fsync (``sync``); ``create`` starts the file anew.

    One ``write`` means a kill leaves all of ``data`` or a torn tail, never an interleaving.
    A short write (a full disk) is cut back off before the :class:`OSError` is raised, so
    the file keeps only whole appends. A created file is always fsynced, with its directory.
    """
    path = Path(path)
    flags = os.O_WRONLY | (os.O_CREAT | os.O_TRUNC if create else os.O_APPEND | os.O_CREAT)
    fd = os.open(path, flags, mode)
    try:
        start = os.lseek(fd, 0, os.SEEK_END)
        try:
            written = os.write(fd, data)
            if written != len(data):
                raise OSError(errno.ENOSPC, "short write (disk full?)", os.fspath(path))
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, start)
            raise
        if sync or create:
            os.fsync(fd)
    finally:
        os.close(fd)
    if create:
        fsync_dir(path.parent)


def cut_tail(path: str | Path, data: bytes, keep: int, backup: str | Path, *, backups: str,
             mode: int | None = None) -> None:
    """Truncate ``path`` (whose bytes are ``data``) to ``keep`` bytes, saving the rest in
    ``backup`` first (with ``mode``, as :func:`write_atomically`): the cut bytes are durable
    in their backup before the file is truncated, and the truncation is fsynced, so a crash
    at any point keeps every byte somewhere.

    ``backups`` is the name pattern of this file's backups beside ``backup`` (for instance
    ``beh-torn-*.bin``). A kill while a backup was written leaves its temporary file
    (``.<name>.tmp``) and cuts nothing, so those bytes are still in ``path``; each backup
    has a name of its own, so no later write takes the temporary over. Once this cut is
    done, the temporaries of the pattern are removed: the new backup holds their bytes.
    """
    backup = Path(backup)
    write_atomically(backup, data[keep:], mode=mode)
    with open(path, "r+b") as handle:
        handle.truncate(keep)
        handle.flush()
        os.fsync(handle.fileno())
    for leftover in backup.parent.glob(f".{backups}.tmp"):
        with contextlib.suppress(FileNotFoundError):
            leftover.unlink()
