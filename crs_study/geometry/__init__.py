"""The geometry stage: a CRS display's device file as a :class:`Layout`.

:mod:`~crs_study.geometry.layout` reads a device file (TOML): pixels on a lattice, beams as
ordered lines of pixels, the boundary servo at each beam end, the servo channels on each
controller, the calibration (mm to pulse width) and limits. The published 2D and 1D devices
ship as ``crs_study/data/devices/crs2d.toml`` and ``crs1d.toml``, chosen by name.
"""

from crs_study.geometry.layout import (
    BUILTIN_DEVICES,
    Actuator,
    Beam,
    BeamSection,
    Calibration,
    Controller,
    Layout,
    device_file_path,
    layout_from_dict,
    load_layout,
)

__all__ = ["BUILTIN_DEVICES", "Actuator", "Beam", "BeamSection", "Calibration", "Controller",
           "Layout", "device_file_path", "layout_from_dict", "load_layout"]
