"""The README's notebook cells run in a real Jupyter kernel (nbclient + ipykernel) and show
what it says: result objects as HTML tables, charts as PNG pictures with no %matplotlib
magic, and a chart the analysis lacks as one line naming those it has.

IPython's display protocol is the outside reference: a cell's output carries a MIME bundle,
``text/html`` from an object's ``_repr_html_`` and ``image/png`` from ``_repr_png_`` (IPython
documentation, "Rich display"; nbformat's output schema).
"""

from __future__ import annotations

import base64
import re
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

README = Path(__file__).resolve().parents[1] / "README.md"

pytestmark = pytest.mark.slow  # a dry-run of 3 participants and the pilot's analysis


def notebook_cells() -> list[str]:
    """The ```python block under '### In a notebook', cut at its ``# %%`` markers."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("### In a notebook\n"):]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README.md: no ```python block under '### In a notebook'"
    cells = [c.strip() for c in match.group(1).split("# %%") if c.strip()]
    assert len(cells) == 5
    return cells


@pytest.fixture(scope="module")
def executed(tmp_path_factory):
    folder = tmp_path_factory.mktemp("notebook")
    book = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c)
                                           for c in notebook_cells()])
    client = nbclient.NotebookClient(book, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(folder)}})
    client.execute()
    return book, folder


def _bundle(cell) -> dict:
    results = [o for o in cell.outputs if o.output_type == "execute_result"]
    assert len(results) == 1, cell.outputs
    return results[0]["data"]


def test_result_objects_display_as_html_tables(executed):
    book, _ = executed
    rehearsal, analysis, accuracy = (_bundle(book.cells[i]) for i in (0, 1, 2))
    assert "<table>" in rehearsal["text/html"] and "3 simulated participants" in \
        rehearsal["text/html"]
    html = analysis["text/html"]
    assert html.index(">headline<") < html.index(">pixel-only<")   # the answer first
    assert "GLMM odds ratio" in html and "warnings (" in html
    assert "<table>" in accuracy["text/html"] and "AccuracyResult" in accuracy["text/html"]
    for bundle in (rehearsal, analysis, accuracy):        # the text form is one short line
        text = bundle["text/plain"]
        assert "\n" not in text and len(text) < 1200 and text.startswith("<")


def test_a_chart_displays_as_a_png_with_no_magic(executed):
    book, _ = executed
    assert "%matplotlib" not in book.cells[3].source
    png = base64.b64decode(_bundle(book.cells[3])["image/png"])
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_a_chart_the_analysis_lacks_is_one_line_naming_those_it_has(executed):
    book, _ = executed
    streams = [o for o in book.cells[4].outputs if o.output_type == "stream"]
    text = "".join(o.text for o in streams).strip()
    assert "\n" not in text
    assert text.startswith("no chart 'tracks' (not in this analysis: no session is adaptive)")
    assert "this analysis has accuracy, speed_accuracy, caf" in text
