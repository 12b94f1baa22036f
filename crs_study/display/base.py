"""Display models: from actuator setpoints to the surface the skin meets.

A model is built once per layout and then evaluated per frame::

    model = get_model("beam", layout)          # crs_study.display: "nearest", "linear", ...
    z = model.surface(setpoints_mm, xy_mm)     # heights (mm) at points (n, 2)

Models register themselves in :data:`MODELS` by name when their module is imported; the
``crs_study.display`` package imports them all and looks them up (``get_model``). Collapse
(Wang, Meng & Chen 2025, Eq. 4, or a solver reaching the critical load) is raised as
:class:`~crs_study.errors.CollapseError`, never returned as a shape.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from crs_study.geometry.layout import Layout


class DisplayModel(ABC):
    """Surface of a display for given setpoints; subclasses set ``name`` and ``description``."""

    name: ClassVar[str]
    description: ClassVar[str]

    def __init__(self, layout: Layout) -> None:
        self.layout = layout

    @abstractmethod
    def surface(self, setpoints_mm: np.ndarray, xy_mm: np.ndarray) -> np.ndarray:
        """Heights (mm) of the displayed surface at points ``xy_mm`` of shape (n, 2)."""


#: name -> model class
MODELS: dict[str, type[DisplayModel]] = {}


def register(cls: type[DisplayModel]) -> type[DisplayModel]:
    """Class decorator adding a model to :data:`MODELS`."""
    MODELS[cls.name] = cls
    return cls
