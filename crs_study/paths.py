"""Where protocols, analysis plans and consent forms are found: shipped defaults and yours.

crs-study ships its default files as package data (``crs_study/data/protocols``,
``crs_study/data/analysis``, ``crs_study/data/consent``, read through
:mod:`importlib.resources`), so an installed wheel runs the main job from any folder. The
repository's ``protocols/``, ``analysis/`` and ``consent/`` are the copies a lab edits; a lab
with only the wheel gets its own editable copies with ``crs-study init DIR``
(:func:`copy_defaults`).

Names and paths: a bare name (letters, digits, ``_``, ``-``; no folder, no suffix) is a
shipped file, ``"pilot"`` the shipped ``pilot.toml`` protocol (:func:`resolve_protocol`),
``"consent_form"`` the shipped form (:func:`resolve_consent_form`); anything else is a path,
taken as given. A file named relative to the project (``consent/consent_form.md``) is the one
in the current directory, else the shipped copy (:func:`shipped_file`); a protocol's consent
form and analysis plan are found beside the protocol first (``crs_study.protocol``).
:func:`find_referenced` also looks in the folder above the protocol, the project folder of
``crs-study init``, so an edited copy there wins from any current directory.

The two copies are kept identical by a test (``tests/test_shipped_files.py``), not by a build
step: both copies are then ordinary files in every kind of install (editable, wheel, sdist),
read the same way, and a change to one that is not made to the other fails the suite with the
command that copies it. A build step (a symlink, or setuptools mapping ``protocols/`` into the
package) would leave an editable install reading other files than a wheel, and symlinks do not
survive every checkout.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from crs_study._files import make_dirs, os_errors, write_atomically
from crs_study.errors import ConfigError, ConsentError, ProtocolError

#: The folders of shipped files and the suffix of the files a name refers to.
SHIPPED_FOLDERS: dict[str, str] = {"protocols": ".toml", "analysis": ".toml", "consent": ".md"}
#: The paper's experiment (``crs-study demo`` and ``device check`` use it when given none).
DEFAULT_PROTOCOL = "digit_identification"

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
_WHAT = {"protocols": "protocol", "analysis": "analysis plan", "consent": "consent form"}


def data_dir() -> Path:
    """The package's data folder (shipped defaults) as a file-system path."""
    return Path(str(resources.files("crs_study") / "data"))


def is_name(text: str | os.PathLike[str]) -> bool:
    """True for a bare name such as ``pilot`` (no folder, no suffix), False for a path."""
    return _NAME_RE.fullmatch(os.fspath(text)) is not None


def shipped(folder: str) -> dict[str, Path]:
    """The shipped files of ``folder`` (``protocols``, ``analysis``, ``consent``) by name.

    The README of each folder is documentation, not a file to name: it is copied by
    :func:`copy_defaults` but has no name here.
    """
    if folder not in SHIPPED_FOLDERS:
        raise ValueError(f"expected one of {sorted(SHIPPED_FOLDERS)}, got {folder!r}")
    suffix = SHIPPED_FOLDERS[folder]
    files = sorted((data_dir() / folder).glob(f"*{suffix}"))
    return {p.stem: p for p in files if p.name != "README.md"}


def shipped_protocols() -> dict[str, Path]:
    """Name -> path of every shipped protocol (``digit_identification``, ``pilot``, ...)."""
    return shipped("protocols")


def _resolve(folder: str, name_or_path: str | os.PathLike[str],
             error: type[ConfigError] | type[ConsentError]) -> Path:
    text = os.fspath(name_or_path)
    what = _WHAT[folder]
    names = shipped(folder)
    if is_name(text):
        if text in names:
            return names[text]
        raise error(f"{text!r} is not a shipped {what} (shipped: {', '.join(names)}); give "
                    f"the path of your own file")
    path = Path(text)
    if not path.exists() and path.suffix == SHIPPED_FOLDERS[folder] and path.stem in names:
        raise error(f"{text}: no such {what} file; crs-study ships one named {path.stem!r}: "
                    f"give that name, or copy the shipped files to edit them with "
                    "crs-study init DIR")
    return path


def resolve_protocol(name_or_path: str | os.PathLike[str]) -> Path:
    """A protocol's file: a shipped protocol's name (``pilot``) or a path, taken as given."""
    return _resolve("protocols", name_or_path, ProtocolError)


def resolve_consent_form(name_or_path: str | os.PathLike[str]) -> Path:
    """A consent form's file: a shipped form's name (``consent_form``) or a path."""
    return _resolve("consent", name_or_path, ConsentError)


def shipped_file(relative: str | Path) -> Path:
    """A file named relative to the project (``protocols/pilot.toml``,
    ``analysis/digit_identification.toml``): as given when it exists (absolute, or relative to
    the current directory), else the shipped copy. A bare name is a shipped protocol's."""
    if is_name(relative):
        return resolve_protocol(relative)
    path = Path(relative)
    if path.is_absolute() or path.exists():
        return path
    candidate = data_dir() / path
    if candidate.is_file():
        return candidate
    raise ConfigError(f"{relative}: no such file (looked in {Path.cwd()} and among the files "
                      f"shipped with crs-study, {data_dir()})")


def recorded_path(path: str | Path) -> str:
    """How a session records where its protocol came from: the path as given, but a shipped
    file's as its place inside the package (``crs_study/data/protocols/pilot.toml``), not
    the install location (which can name the user's home folder)."""
    path = Path(path)
    try:
        inside = path.resolve().relative_to(data_dir().resolve())
    except (OSError, ValueError):
        return str(path)
    return f"crs_study/data/{inside.as_posix()}"


def find_referenced(protocol_path: str | Path, relative: str | Path) -> Path:
    """A file a protocol names (its consent form, its analysis plan), found where a lab keeps it.

    Looked up beside the protocol, then in the folder above it (the project folder of
    ``crs-study init``, whose ``protocols/`` sits beside ``consent/`` and ``analysis/``), then
    as :func:`shipped_file` does (the current directory, the shipped copies).
    """
    relative = Path(relative)
    if not relative.is_absolute():
        folder = Path(protocol_path).parent
        for base in (folder, folder.parent):
            if (base / relative).is_file():
                return base / relative
    return shipped_file(relative)


@dataclass(frozen=True)
class CopiedFile:
    """One file of :func:`copy_defaults`: where it went and whether it was written."""

    path: Path
    written: bool  # False: an identical file was there already


def _refuse_link(path: Path) -> None:
    """A symbolic link where ``init`` would write is refused: the copy would land wherever it
    points (another lab's folder, a system file), not in the folder the user named."""
    if path.is_symlink():
        raise ConfigError(f"{path}: is a symbolic link (to {os.readlink(path)}); init writes "
                          "only into the folder it is given: nothing was copied (remove the "
                          "link, or give the folder it points to)")


def copy_defaults(directory: str | Path) -> list[CopiedFile]:
    """Copy the shipped protocols, analysis plans and consent forms into ``directory``.

    Makes ``directory/protocols``, ``directory/analysis`` and ``directory/consent`` (each with
    its README), the layout of the repository, so the copies' references to one another
    (``consent/consent_form.md``) hold. Files already there with the same content are left
    alone; if any file there differs, nothing is written and the error names it.
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ConfigError(f"{directory}: exists and is not a directory")
    plan: list[tuple[Path, bytes, bool]] = []
    clashes = []
    for folder in SHIPPED_FOLDERS:
        _refuse_link(directory / folder)
        for source in sorted((data_dir() / folder).iterdir()):
            if not source.is_file():
                continue
            target = directory / folder / source.name
            _refuse_link(target)
            data = source.read_bytes()
            with os_errors(ConfigError, "read", target):
                same = target.is_file() and target.read_bytes() == data
            if target.exists() and not same:
                clashes.append(target)
            plan.append((target, data, not same))
    if clashes:
        more = f" and {len(clashes) - 1} more" if len(clashes) > 1 else ""
        raise ConfigError(f"{clashes[0]}{more}: exists and differs from the shipped copy; "
                          "nothing was copied (choose another folder, or move your edited "
                          "files away first)")
    for target, data, write in plan:
        if write:
            with os_errors(ConfigError, "write", target):
                make_dirs(target.parent)
                write_atomically(target, data)
    return [CopiedFile(target, write) for target, _, write in plan]
