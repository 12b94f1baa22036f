"""Display models: setpoints to the surface the skin meets (see :mod:`crs_study.display.base`).

Importing this package imports every model module, so :data:`~crs_study.display.base.MODELS`
holds them all: ``nearest``, ``linear``, ``spline``, ``beam`` (the CRS) and ``reference``;
:func:`get_model` builds one by name.
"""

from crs_study.display import beam, linear, nearest, reference, spline  # noqa: F401
from crs_study.display.base import MODELS, DisplayModel, register
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import Layout


def get_model(name: str, layout: Layout, **options: object) -> DisplayModel:
    """The display model ``name`` (a key of :data:`MODELS`) built for ``layout``."""
    if name not in MODELS:
        raise DisplayModelError(
            f"unknown display model {name!r}; known: {', '.join(sorted(MODELS)) or 'none'}"
        )
    return MODELS[name](layout, **options)


__all__ = ["MODELS", "DisplayModel", "get_model", "register"]
