"""How result objects show themselves: one short line as text, a small table in a notebook.

A result object (an analysis, a power curve, a dry-run, ...) holds tables of thousands of
rows; the dataclass's generated ``repr`` prints them all (tens of thousands of characters).
:class:`Displayed` gives a class a concise ``__repr__`` (what it is and its key numbers on
one line, as ``scipy.stats``' result objects do) and ``_repr_html_``, the hook IPython and
Jupyter call for rich output (IPython documentation, "Rich display": an object's
``_repr_html_`` returns an HTML fragment), as a small table: what it is, the key numbers, its
warnings. A class lists them in ``_display()``; a dataclass using it is declared with
``repr=False`` so that the generated ``repr`` does not replace this one.
"""

from __future__ import annotations

import html
from dataclasses import dataclass

#: A value longer than this is cut with an ellipsis in the text form.
VALUE_WIDTH = 90
#: Warnings listed in the HTML table (the rest counted).
WARNINGS_SHOWN = 8


@dataclass(frozen=True)
class Display:
    """What a result object shows: ``title`` (what it is), ``rows`` (name, value) of its key
    numbers, its ``warnings`` and a ``hint`` naming the methods that give the rest."""

    title: str
    rows: tuple[tuple[str, str], ...] = ()
    warnings: tuple[str, ...] = ()
    hint: str = ""

    def text(self) -> str:
        """``<Title: name value; name value; 2 warnings; .to_frame()>``."""
        parts = [f"{name} {_cut(value)}" if name else _cut(value) for name, value in self.rows]
        if self.warnings:
            parts.append(f"{len(self.warnings)} warning{'s' * (len(self.warnings) != 1)}")
        if self.hint:
            parts.append(self.hint)
        return f"<{self.title}" + (": " + "; ".join(parts) if parts else "") + ">"

    def html(self) -> str:
        """A small table: the title as its caption, a row per key number, then warnings."""
        cells = "".join(f"<tr><th style=\"text-align:left\">{html.escape(name)}</th>"
                        f"<td style=\"text-align:left\">{html.escape(value)}</td></tr>"
                        for name, value in self.rows)
        shown = self.warnings[:WARNINGS_SHOWN]
        if shown:
            more = len(self.warnings) - len(shown)
            items = "".join(f"<li>{html.escape(w)}</li>" for w in shown)
            if more:
                items += f"<li>... and {more} more</li>"
            cells += (f"<tr><th style=\"text-align:left\">warnings ({len(self.warnings)})</th>"
                      f"<td style=\"text-align:left\"><ul style=\"margin:0\">{items}</ul>"
                      "</td></tr>")
        hint = (f"<tr><td colspan=\"2\" style=\"text-align:left\"><code>"
                f"{html.escape(self.hint)}</code></td></tr>") if self.hint else ""
        return (f"<table><caption style=\"text-align:left\"><b>{html.escape(self.title)}"
                f"</b></caption>{cells}{hint}</table>")


class Displayed:
    """Mixin: ``__repr__`` and ``_repr_html_`` from the class's :meth:`_display`."""

    def _display(self) -> Display:  # pragma: no cover - every user overrides it
        raise NotImplementedError

    def __repr__(self) -> str:
        return self._display().text()

    def _repr_html_(self) -> str:
        return self._display().html()


def _cut(value: str) -> str:
    value = " ".join(str(value).split())
    return value if len(value) <= VALUE_WIDTH else value[:VALUE_WIDTH - 3] + "..."


def percent(value: float | None, digits: int = 1) -> str:
    """``83.3 %`` (``n/a`` for a missing value)."""
    if value is None or value != value:
        return "n/a"
    return f"{100 * value:.{digits}f} %"
