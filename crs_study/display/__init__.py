"""Display models: setpoints to the surface the skin meets (see :mod:`crs_study.display.base`).

Importing this package imports every model module, so :data:`~crs_study.display.base.MODELS`
holds them all: ``nearest``, ``linear``, ``spline``, ``beam`` (the CRS) and ``reference``.
"""

from crs_study.display import beam, reference, spline  # noqa: F401  (register models)
from crs_study.display.base import MODELS, DisplayModel, get_model, register

try:  # owned by another helper; imported plainly once they land
    from crs_study.display import nearest  # noqa: F401
except ImportError:  # pragma: no cover
    pass
try:
    from crs_study.display import linear  # noqa: F401
except ImportError:  # pragma: no cover
    pass

__all__ = ["MODELS", "DisplayModel", "get_model", "register"]
