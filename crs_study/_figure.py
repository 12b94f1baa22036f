"""Charts that show themselves in a notebook and leave no state behind in a script.

The charts are drawn without pyplot (a :class:`matplotlib.figure.Figure` made directly is not
registered with pyplot's figure manager, so a script that draws a thousand charts holds none
of them, and any backend or thread works). Jupyter's inline backend shows only the figures
pyplot manages, so a plain Figure or its Axes displays as text (``<Figure size 500x400 with 1
Axes>``) until ``%matplotlib inline``. These subclasses add ``_repr_png_``, the hook IPython
calls for ``image/png`` output (IPython documentation, "Rich display"), to the figure and to
its Axes: the chart returned by a ``plot`` method displays as a picture, with no magic, as
the last expression of a cell.

matplotlib is imported when the first chart is made, not with this module: a module that can
draw (a measurement's report, the ``quality`` command) starts half a second sooner, and its
``--help`` without matplotlib. The two classes are made then (:func:`chart_classes`) and are
this module's attributes from then on (``crs_study._figure.ChartFigure``, as pickle finds
them).
"""

from __future__ import annotations

import functools
import io

import numpy as np

#: Resolution of the notebook picture (the saved PNGs choose their own).
NOTEBOOK_DPI = 100


@functools.cache
def chart_classes() -> tuple[type, type]:
    """``(ChartFigure, ChartAxes)``: a Figure that IPython displays as a PNG, and Axes that
    display as the PNG of their whole figure; matplotlib is imported on the first call."""
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    class ChartFigure(Figure):
        def _repr_png_(self) -> bytes:
            buffer = io.BytesIO()
            self.savefig(buffer, format="png", dpi=NOTEBOOK_DPI, metadata={"Software": None})
            return buffer.getvalue()

    class ChartAxes(Axes):
        def _repr_png_(self) -> bytes | None:
            figure = self.figure
            return figure._repr_png_() if isinstance(figure, ChartFigure) else None

    for made in (ChartFigure, ChartAxes):
        made.__module__, made.__qualname__ = __name__, made.__name__
    return ChartFigure, ChartAxes


def __getattr__(name: str) -> type:
    """``ChartFigure`` and ``ChartAxes`` (:func:`chart_classes`)."""
    if name in ("ChartFigure", "ChartAxes"):
        return chart_classes()[name == "ChartAxes"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _new_figure(size: tuple[float, float]):
    """A new ``ChartFigure`` of ``size`` inches, constrained layout."""
    return chart_classes()[0](figsize=size, layout="constrained")


def new_axes(size: tuple[float, float] = (5.0, 4.0)):
    """One ``ChartAxes`` on a new ``ChartFigure`` of ``size`` inches, constrained layout."""
    return _new_figure(size).add_subplot(axes_class=chart_classes()[1])


class ChartGrid(np.ndarray):
    """An array of ``ChartAxes`` on one figure (``axes[row, column]``, as pyplot's
    ``subplots`` gives them) that IPython displays as the PNG of that figure: a multi-panel
    chart returned as the last expression of a cell shows as a picture, as one Axes does."""

    def _repr_png_(self) -> bytes | None:
        first = self.flat[0] if self.size else None
        return first._repr_png_() if isinstance(first, chart_classes()[1]) else None


def new_axes_grid(rows: int, columns: int, size: tuple[float, float]) -> ChartGrid:
    """``rows x columns`` Axes (a 2-D :class:`ChartGrid`) on one new ``ChartFigure`` of
    ``size`` inches, constrained layout."""
    axes = _new_figure(size).subplots(rows, columns, squeeze=False,
                                      subplot_kw={"axes_class": chart_classes()[1]})
    return np.asarray(axes).view(ChartGrid)
