"""Charts that show themselves in a notebook and leave no state behind in a script.

The charts are drawn without pyplot (a :class:`matplotlib.figure.Figure` made directly is not
registered with pyplot's figure manager, so a script that draws a thousand charts holds none
of them, and any backend or thread works). Jupyter's inline backend shows only the figures
pyplot manages, so a plain Figure or its Axes displays as text (``<Figure size 500x400 with 1
Axes>``) until ``%matplotlib inline``. These subclasses add ``_repr_png_``, the hook IPython
calls for ``image/png`` output (IPython documentation, "Rich display"), to the figure and to
its Axes: the chart returned by a ``plot`` method displays as a picture, with no magic, as
the last expression of a cell.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

#: Resolution of the notebook picture (the saved PNGs choose their own).
NOTEBOOK_DPI = 100


class ChartFigure(Figure):
    """A Figure that IPython displays as a PNG."""

    def _repr_png_(self) -> bytes:
        buffer = io.BytesIO()
        self.savefig(buffer, format="png", dpi=NOTEBOOK_DPI, metadata={"Software": None})
        return buffer.getvalue()


class ChartAxes(Axes):
    """Axes that IPython displays as the PNG of their whole figure."""

    def _repr_png_(self) -> bytes | None:
        figure = self.figure
        return figure._repr_png_() if isinstance(figure, ChartFigure) else None


def new_axes(size: tuple[float, float] = (5.0, 4.0)) -> ChartAxes:
    """One Axes on a new :class:`ChartFigure` of ``size`` inches, constrained layout."""
    figure = ChartFigure(figsize=size, layout="constrained")
    return figure.add_subplot(axes_class=ChartAxes)


class ChartGrid(np.ndarray):
    """An array of :class:`ChartAxes` on one figure (``axes[row, column]``, as pyplot's
    ``subplots`` gives them) that IPython displays as the PNG of that figure: a multi-panel
    chart returned as the last expression of a cell shows as a picture, as one Axes does."""

    def _repr_png_(self) -> bytes | None:
        first = self.flat[0] if self.size else None
        return first._repr_png_() if isinstance(first, ChartAxes) else None


def new_axes_grid(rows: int, columns: int, size: tuple[float, float]) -> ChartGrid:
    """``rows x columns`` Axes (a 2-D :class:`ChartGrid`) on one new :class:`ChartFigure` of
    ``size`` inches, constrained layout."""
    figure = ChartFigure(figsize=size, layout="constrained")
    return np.asarray(figure.subplots(rows, columns, squeeze=False,
                                      subplot_kw={"axes_class": ChartAxes})).view(ChartGrid)
