"""The protocol side of the layers (issue 15, point 3): no hidden imports, no upward imports.

The layers, lowest first: foundations (errors, _files, _toml, _toml_lines, clock, paths,
consent_form) -> geometry and stimuli (layout, targets, digits, stimulus) -> rendering and
display models (render, display, quality) -> protocol (the crs_study.protocol package, its
trial plan included, and the crs_study.protocol.plan re-export) -> device -> dataset -> session ->
analysis -> CLI. A lower layer never imports a higher one, and the modules here import the
package's own modules at the top only, never inside a function (where they hid the cycles
protocol <-> plan <-> stimulus <-> digits).

One exception, named here so it stays visible: the protocol's feasibility check and wire budget
use the LSC wire model (crs_study.device.base's frame timing, crs_study.device.schedule's
wire_plan), pure functions of a layout and setpoints that sit in the device package. They are
allowed below the protocol as long as they import nothing above the rendering layer.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import crs_study

PACKAGE = Path(crs_study.__file__).parent

#: layer of each module (a package stands for its modules); higher numbers are higher layers
LAYERS = {
    "crs_study.errors": 0, "crs_study._files": 0, "crs_study._toml": 0,
    "crs_study._toml_lines": 0, "crs_study.clock": 0, "crs_study.paths": 0,
    "crs_study.consent.form": 0,
    "crs_study.geometry": 1, "crs_study.stimuli": 1,
    "crs_study.rendering": 2, "crs_study.display": 2, "crs_study.quality": 2,
    # the wire model (the exception of the module docstring)
    "crs_study.device.base": 2, "crs_study.device.schedule": 2,
    "crs_study.device.calibration": 2, "crs_study.device.codec": 2,
    "crs_study.protocol": 3, "crs_study.protocol.plan": 3,
}
#: inside the protocol package, each module may import those listed before it
PROTOCOL_ORDER = ["model", "plan", "feasibility", "odd_values", "wire", "loader", "__init__"]

#: the modules this test holds to the rules (the protocol side of issue 15)
CHECKED = ["errors", "_toml", "_toml_lines", "consent.form", "stimuli.targets", "stimuli.digits",
           "stimuli.stimulus",
           *(f"protocol.{m}" for m in PROTOCOL_ORDER)]


def source(name: str) -> Path:
    if name == "protocol.__init__":
        return PACKAGE / "protocol" / "__init__.py"
    return PACKAGE.joinpath(*name.split(".")).with_suffix(".py")


def own_imports(tree: ast.AST) -> list[tuple[str, ast.AST]]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and \
                node.module.startswith("crs_study"):
            names = [f"{node.module}.{a.name}" for a in node.names]
            found += [(node.module if not _is_module(n) else n, node) for n in names]
        elif isinstance(node, ast.Import):
            found += [(a.name, node) for a in node.names if a.name.startswith("crs_study")]
    return found


def _is_module(dotted: str) -> bool:
    path = PACKAGE.joinpath(*dotted.split(".")[1:])
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def layer_of(module: str) -> int:
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return LAYERS[".".join(parts[:n])]
    raise AssertionError(f"{module}: no layer known; add it to LAYERS")


@pytest.mark.parametrize("name", CHECKED)
def test_no_import_of_the_package_inside_a_function(name):
    tree = ast.parse(source(name).read_text(encoding="utf-8"))
    hidden = [f"line {node.lineno}: {module}"
              for function in ast.walk(tree)
              if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef)
              for module, node in own_imports(function)]
    assert not hidden, f"{name} imports inside functions: {hidden}"


@pytest.mark.parametrize("name", CHECKED)
def test_no_import_of_a_higher_layer(name):
    me = "crs_study." + name.removesuffix(".__init__")
    tree = ast.parse(source(name).read_text(encoding="utf-8"))
    for module, node in own_imports(tree):
        if module == "crs_study":
            continue
        assert layer_of(module) <= layer_of(me), \
            f"{me} (layer {layer_of(me)}) imports {module} (layer {layer_of(module)}), " \
            f"line {node.lineno}"
        if me.startswith("crs_study.protocol.") and module.startswith("crs_study.protocol."):
            mine = PROTOCOL_ORDER.index(me.rsplit(".", 1)[1])
            theirs = PROTOCOL_ORDER.index(module.split(".")[2])
            assert theirs < mine, f"{me} imports {module}, which comes after it"


def test_the_wire_model_imports_nothing_of_the_protocol_or_above():
    # what the exception of the module docstring relies on: no cycle through the device
    above = ("crs_study.protocol", "crs_study.protocol.plan", "crs_study.stimuli.stimulus",
             "crs_study.session.runner",
             "crs_study.dataset", "crs_study.consent", "crs_study.session.responders",
             "crs_study.analysis", "crs_study.commands", "crs_study.cli")
    for name in ("device.base", "device.schedule", "device.calibration", "device.codec"):
        tree = ast.parse(source(name).read_text(encoding="utf-8"))
        for module, node in own_imports(tree):
            assert not module.startswith(above), \
                f"crs_study.{name} imports {module} (line {node.lineno})"
