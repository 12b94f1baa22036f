"""Every name the documentation writes resolves, and nothing points outside the repository.

A reader follows a dotted name (``crs_study.rendering.render.CONDITIONS``) or a path
(``crs_study/data/devices/*.toml``) written in docs/, the protocols, analysis plans and consent
folders, README.md, the package's data files and READMEs, or a docstring of the package: each
must import (the longest importable module, then attributes) or exist (a glob must match).
Names go stale when code moves (``crs_study.render`` became ``crs_study.rendering.render``);
this is where that is caught.

And a clone holds everything its text refers to: no issue numbers (the tracker is not in the
clone) and no files of the project's working notes outside the repository.
"""

from __future__ import annotations

import ast
import functools
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "crs_study"

#: ``crs_study.a.b`` (a trailing ``*`` stands for any attribute with that prefix).
DOTTED = re.compile(r"\bcrs_study(?:\.[A-Za-z_][A-Za-z0-9_]*)+\*?")
#: ``crs_study/...``: a file, a folder or a glob, relative to the repository's root.
PATH = re.compile(r"\bcrs_study/[A-Za-z0-9_./*-]*")

#: Documentation outside the package, by glob relative to the repository's root.
DOC_GLOBS = ("docs/**/*.md", "protocols/*", "analysis/*", "consent/*", "README.md")

#: Pointers a clone cannot follow: an issue number, or the working notes kept outside it.
OUTSIDE = re.compile(r"\bissues? ?#?[0-9]+\b|crs-paper\.md|hardware\.md|design\.md|style\.md"
                     r"|\.\./shared|shared/[r]eference", re.IGNORECASE)
#: Where to look for them: every text the repository holds, recorded data aside (the sidecars
#: of old sessions under tests/fixtures hold the device files those sessions ran with).
SCANNED_SUFFIXES = {".py", ".md", ".toml", ".R", ".txt", ".cfg", ".ini", ".yml", ".yaml"}


def documents() -> dict[str, str]:
    """Text by where it is (``path`` or ``path:line`` of a docstring)."""
    found = {}
    files = [p for pattern in DOC_GLOBS for p in ROOT.glob(pattern)]
    files += [p for p in PACKAGE.rglob("*") if p.suffix in {".md", ".toml"}]
    for path in sorted(set(files)):
        if path.is_file():
            found[str(path.relative_to(ROOT))] = path.read_text(encoding="utf-8")
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                 ast.AsyncFunctionDef)):
                doc = ast.get_docstring(node, clean=False)
                if doc:
                    line = node.body[0].lineno
                    found[f"{path.relative_to(ROOT)}:{line}"] = doc
    return found


def fields(obj: object) -> set[str]:
    """The annotated fields of a class and its bases (dataclass fields without a default are
    not class attributes)."""
    if not isinstance(obj, type):
        return set()
    return {name for klass in obj.__mro__ for name in getattr(klass, "__annotations__", {})}


def resolve_dotted(name: str) -> str | None:
    """Why ``name`` does not resolve, or None."""
    star = name.endswith("*")
    parts = name.rstrip("*").split(".")
    for end in range(len(parts), 0, -1):
        module_name = ".".join(parts[:end])
        try:
            obj = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name is not None and module_name.startswith(error.name):
                continue
            raise
        break
    else:  # pragma: no cover - crs_study itself imports
        return "crs_study does not import"
    for k, attribute in enumerate(parts[end:], start=end):
        last = k == len(parts) - 1
        if last and star:
            if not any(a.startswith(attribute) for a in dir(obj)):
                return f"{module_name} has no attribute starting {attribute!r}"
            return None
        if not hasattr(obj, attribute):
            if not (last and attribute in fields(obj)):
                return f"{'.'.join(parts[:k])} has no attribute {attribute!r}"
            return None  # a field of a (data)class without a default: no class attribute
        obj = getattr(obj, attribute)
    return None


def resolve_path(path: str) -> str | None:
    """Why ``path`` (relative to the repository's root) names nothing, or None."""
    path = path.rstrip(".,:;")
    if "*" in path:
        return None if any(ROOT.glob(path)) else "no file matches"
    return None if (ROOT / path).exists() else "no such file or folder"


@functools.cache
def scanned_documents() -> dict[str, str]:
    """:func:`documents`, read once, when a test first asks (not as every worker collects)."""
    return documents()


def names(pattern: re.Pattern[str]) -> list[tuple[str, str]]:
    return sorted({(match.group(0), where) for where, text in scanned_documents().items()
                   for match in pattern.finditer(text)})


def test_the_documents_are_found():
    # the scan reads what it should: the docs pages, a protocol, a data file, a docstring
    assert {"docs/physics.md", "protocols/digit_identification.toml", "README.md",
            "crs_study/data/digits.toml", "crs_study/live/README.md"} <= set(scanned_documents())
    assert any(where.startswith("crs_study/live/session.py:") for where in scanned_documents())
    assert len(names(DOTTED)) > 100 and len(names(PATH)) > 20


def test_every_dotted_name_imports():
    broken = [f"{where}: {name}: {why}" for name, where in names(DOTTED)
              if (why := resolve_dotted(name)) is not None]
    assert not broken, "\n".join(broken)


def test_every_package_path_exists():
    broken = [f"{where}: {name}: {why}" for name, where in names(PATH)
              if (why := resolve_path(name)) is not None]
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize(("name", "why"), [
    pytest.param("crs_study.render.CONDITIONS", "crs_study has no attribute 'render'",
                 id="moved-module"),
    pytest.param("crs_study.protocol.level_parameters", "no attribute 'level_parameters'",
                 id="not-re-exported"),
    pytest.param("crs_study.protocol.WARN_NOPE*", "no attribute starting 'WARN_NOPE'",
                 id="glob"),
])
def test_a_stale_name_is_caught(name, why):
    assert why in resolve_dotted(name)


def test_a_stale_path_is_caught():
    assert resolve_path("crs_study/devices/") == "no such file or folder"
    assert resolve_path("crs_study/data/devices/*.toml") is None
    assert resolve_path("crs_study/digits.py.") == "no such file or folder"


def scanned_files() -> list[Path]:
    skip = {".git", ".venv", "__pycache__", "build", "dist", ".pytest_cache", ".ruff_cache"}
    found = [ROOT / "README.md", ROOT / "pyproject.toml", ROOT / ".ci" / "run"]
    for folder in ("crs_study", "protocols", "analysis", "consent", "docs", "tests"):
        for path in (ROOT / folder).rglob("*"):
            if (path.is_file() and path.suffix in SCANNED_SUFFIXES
                    and not skip & set(path.relative_to(ROOT).parts)
                    and not path.name.endswith(".egg-info")):
                found.append(path)
    return [p for p in sorted(found) if p.exists()]


def test_nothing_points_outside_the_repository():
    files = scanned_files()
    assert ROOT / "tests" / "fixtures" / "lme4" / "make_corpus.py" in files
    hits = [f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
            for path in files
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
            if OUTSIDE.search(line)]
    assert not hits, "\n".join(hits)


def test_an_outside_pointer_is_caught():
    # (each example in two pieces, so that this file holds no pointer itself)
    for line in ("see issue" " 13.3", "Issue" " 2: D_P", "(crs-paper" ".md, Eq. 4)",
                 "DESIGN" ".md's check", "../" "shared/notes", "STYLE" ".md point 18",
                 "issue" " #12", "hardware" ".md"):
        assert OUTSIDE.search(line), line
    for line in ("the issue's definition", "tissue 3", "docs/physics.md", "issues remain"):
        assert not OUTSIDE.search(line), line
