"""Display models: setpoints to the surface the skin meets (see :mod:`crs_study.display.base`).

Importing this package imports every model module, so :data:`~crs_study.display.base.MODELS`
holds them all: ``nearest``, ``linear``, ``spline``, ``beam`` (the CRS) and ``reference``.
"""

from crs_study.display import beam, linear, nearest, reference, spline  # noqa: F401
from crs_study.display.base import MODELS, DisplayModel, get_model, register

__all__ = ["MODELS", "DisplayModel", "get_model", "register"]
