"""The package's layers: a folder per stage, imports only downwards, none
hidden inside a function, and no module past 500 lines.

The layers are import-linter contracts in ``pyproject.toml`` (``[tool.importlinter]``), run
here as ``lint-imports`` runs them: the stages in pipeline order (a stage imports only the
stages below it; every child of ``crs_study`` must be placed), the analysis reading the
stored dataset alone, and the protocol package's modules in the order they build on each
other. import-linter (https://import-linter.readthedocs.io) finds the imports with grimp, so
an import inside a function counts like any other.

Imports of the package inside functions hid three cycles (protocol <-> plan <-> stimulus <->
digits; device/base.py importing its own backends) and cost the runner its types. None is
left; the only lazy loading is dynamic (``importlib.import_module``) and for a reason written
beside it, in exactly the modules :data:`LAZY` lists.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import crs_study

PACKAGE = Path(crs_study.__file__).parent
PYPROJECT = PACKAGE.parent / "pyproject.toml"
LINT_IMPORTS = ("import sys; from importlinter.cli import lint_imports_command; "
                "sys.exit(lint_imports_command())")
#: The longest a module may be (docs/conventions.md: a few hundred lines, 500 at most).
MAX_LINES = 500

#: The modules that load parts of the package lazily (``importlib.import_module``), and why.
LAZY = {
    "crs_study.cli": "a subcommand's module when that subcommand is chosen, so that "
                     "crs-study --help and a command's start import only what it needs",
    "crs_study.commands.bench": "the benchmark areas (every module of crs_study.benchmarks) "
                                "when the bench runs",
    "crs_study.analysis": "its entry points on first use, so that importing "
                          "crs_study.analysis.glmm does not import matplotlib (the charts)",
    "crs_study.power_analysis": "its entry points on first use, so that a worker process "
                                "that unpickles a power task imports the fits, not the "
                                "reports and charts (tests/test_power_backends.py)",
    "crs_study._lazy": "lazy_exports, with which the packages above load their names",
    "crs_study": "the Python API on first use, so that import crs_study stays quick and the "
                 "command line loads only what a command needs",
}


def modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its ``__init__``)."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def lint_imports(cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", LINT_IMPORTS, "--no-cache", "--config",
                           str(cwd / "pyproject.toml")], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_the_import_contracts_hold():
    result = lint_imports(PYPROJECT.parent)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "3 kept, 0 broken" in result.stdout


@pytest.mark.parametrize(("importer", "imported", "contract"), [
    pytest.param("geometry/layout.py", "crs_study.session.runner", "A folder is a stage",
                 id="geometry-imports-session"),
    pytest.param("device/base.py", "crs_study.protocol.model", "A folder is a stage",
                 id="device-imports-protocol"),
    pytest.param("analysis/load.py", "crs_study.geometry.layout", "dataset alone",
                 id="analysis-imports-geometry"),
    pytest.param("protocol/model.py", "crs_study.protocol.loader", "protocol stage",
                 id="model-imports-loader"),
])
def test_an_upward_import_breaks_a_contract(tmp_path, importer, imported, contract):
    """The contracts can fail: a copy of the package with one upward import, inside a
    function as the hidden ones were, is refused by the contract it breaks."""
    shutil.copytree(PACKAGE, tmp_path / "crs_study",
                    ignore=shutil.ignore_patterns("__pycache__", "data"))
    shutil.copy(PYPROJECT, tmp_path / "pyproject.toml")
    with (tmp_path / "crs_study" / importer).open("a", encoding="utf-8") as handle:
        handle.write(f"\n\ndef _hidden():\n    import {imported}  # noqa\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    result = lint_imports(tmp_path, env)
    assert result.returncode != 0, result.stdout
    name = "crs_study." + importer.removesuffix(".py").replace("/", ".")
    assert f"{name} -> {imported}" in result.stdout
    assert f"{contract}" in result.stdout and "BROKEN" in result.stdout


def _imports_inside_functions(tree: ast.AST) -> list[tuple[int, str]]:
    found = []
    for function in ast.walk(tree):
        if not isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(function):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "")
                                                      .startswith("crs_study")):
                found.append((node.lineno, f"from {node.module} import ..."))
            elif isinstance(node, ast.Import):
                found += [(node.lineno, f"import {a.name}") for a in node.names
                          if a.name.startswith("crs_study")]
    return found


def _dynamic_imports(tree: ast.AST) -> list[int]:
    """Calls that import by name at run time: ``import_module``, ``__import__``, and
    ``lazy_exports`` (crs_study._lazy), which makes a package's ``__getattr__`` do so."""
    return [node.lineno for node in ast.walk(tree)
            if isinstance(node, ast.Call) and (
                (isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
                or (isinstance(node.func, ast.Name) and node.func.id in (
                    "import_module", "__import__", "lazy_exports")))]


def test_no_module_imports_the_package_inside_a_function():
    hidden, dynamic = [], set()
    for name, path in modules().items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        hidden += [f"{name}:{line}: {what}" for line, what in _imports_inside_functions(tree)]
        if _dynamic_imports(tree):
            dynamic.add(name)
    assert not hidden, "imports inside functions (move them to the top):\n" + "\n".join(hidden)
    # exactly the modules LAZY lists load lazily: a new one needs its reason there
    assert dynamic == set(LAZY)


def test_no_module_runs_past_500_lines():
    long = {name: n for name, path in modules().items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them along a seam): {long}"


def test_a_new_folder_must_be_placed_among_the_stages(tmp_path):
    """The stages contract is exhaustive: a folder or top-level module it does not place is
    refused until it is given its layer."""
    shutil.copytree(PACKAGE, tmp_path / "crs_study",
                    ignore=shutil.ignore_patterns("__pycache__", "data"))
    shutil.copy(PYPROJECT, tmp_path / "pyproject.toml")
    (tmp_path / "crs_study" / "gaze").mkdir()  # (a stage not yet built)
    (tmp_path / "crs_study" / "gaze" / "__init__.py").write_text('"""Eye tracking."""\n')
    result = lint_imports(tmp_path, dict(os.environ, PYTHONPATH=str(tmp_path)))
    assert result.returncode != 0, result.stdout
    assert "not listed as layers" in result.stdout and "- crs_study.gaze" in result.stdout
