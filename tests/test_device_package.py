"""The device package: devices chosen by URL scheme, one typed interface, layers that show.

The layering checked here is the one ``crs_study/device/__init__.py`` lists: each module imports
only modules above it, none imports the package's own modules inside a function (which hid
``device/base.py`` importing its own backends), and ``open_device`` finds the implementation
in a registry instead of importing it.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

import crs_study.device as device_package
from crs_study.clock import VirtualClock
from crs_study.device import (
    Device,
    FrameReport,
    SerialDevice,
    SimulatedDevice,
    open_device,
    register_scheme,
)
from crs_study.device import base as device_base
from crs_study.errors import DeviceError

PACKAGE = Path(device_package.__file__).parent

#: The device package's modules, each allowed to import only those before it.
LAYERS = ("base", "identity", "calibration", "codec", "decoder", "writes", "schedule",
          "virtual_controller", "protocol_lscsim", "virtual_pty", "virtual_boards", "serial_port",
          "serial_device", "sim_options", "simulated", "__init__")


def test_open_device_picks_the_implementation_by_the_urls_scheme(layout1d):
    assert type(open_device("sim://", layout1d, VirtualClock())) is SimulatedDevice
    device = open_device("serial://loop://", layout1d, check_battery=False)
    assert type(device) is SerialDevice and device.options.check_battery is False
    # the old import path still reaches the same function (the runner and its tests use it)
    assert device_base.open_device is open_device
    for url in ("usb://x", "sim:/", "/dev/ttyUSB0", ""):
        with pytest.raises(DeviceError, match=r"unknown device URL .*; expected "
                           r"serial:///dev/ttyUSB0\[,/dev/ttyUSB1\] or sim://"):
            open_device(url, layout1d)


def test_a_registered_scheme_is_opened_by_open_device(layout1d, monkeypatch):
    made = []

    def factory(url, layout, clock=None, **options):
        made.append((url, options))
        return SimulatedDevice.from_url("sim://", layout, clock)

    monkeypatch.setitem(device_base._SCHEMES, "replay", factory)
    device = open_device("replay://session-3", layout1d, VirtualClock(), speed=2)
    assert isinstance(device, Device) and made == [("replay://session-3", {"speed": 2})]
    register_scheme("sim", SimulatedDevice.from_url)  # registering again is harmless


def test_both_devices_implement_the_whole_interface():
    for cls in (SerialDevice, SimulatedDevice):
        assert issubclass(cls, Device) and not inspect.isabstract(cls), cls
    assert set(Device.__abstractmethods__) == {"open", "send", "close", "displayed_setpoints"}
    signature = inspect.signature(Device.send)
    assert signature.return_annotation in (FrameReport, "FrameReport")


def _imports(path: Path) -> tuple[list[str], list[str]]:
    """The package's own modules ``path`` imports: (at module level, inside functions)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    inside: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            inside += [name for child in ast.walk(node) for name in _names(child)]
    top = [name for node in tree.body for name in _names(node)]
    return top, inside


def _names(node: ast.AST) -> list[str]:
    if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("crs_study"):
        if node.module == "crs_study.device":
            return [f"crs_study.device.{a.name}" for a in node.names]
        return [node.module]
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.startswith("crs_study")]
    return []


def test_every_device_module_is_in_a_layer():
    assert sorted(p.stem for p in PACKAGE.glob("*.py")) == sorted(LAYERS)


@pytest.mark.parametrize("module", LAYERS)
def test_device_modules_import_only_the_layers_above_them_and_never_inside_a_function(module):
    top, inside = _imports(PACKAGE / f"{module}.py")
    assert inside == [], f"{module}.py imports {inside} inside a function"
    above = set(LAYERS[:LAYERS.index(module)])
    for name in top:
        if name.startswith("crs_study.device."):
            assert name.removeprefix("crs_study.device.") in above, (module, name)
        else:  # below the device stage: the foundations and the device file's geometry
            assert name in ("crs_study.clock", "crs_study.errors", "crs_study.geometry.layout"), \
                (module, name)
