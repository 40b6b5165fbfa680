"""The notebooks as a student sees them.

Every notebook in notebooks/ must be a valid nbformat-4 file stored without outputs, and must run top to
bottom in a Jupyter kernel with matplotlib's *inline* backend (the JupyterLab default): the figures then
arrive as ``image/png`` outputs, exactly as in the browser, and each notebook must show at least the
figures listed in ``MIN_FIGURES`` (at least three each; every notebook must be in the table). Exercises need
solutions: in every notebook, every numbered exercise has a solution cell tagged ``solution`` that runs with the
rest and keeps its code and output collapsed until the student opens it, and notebooks 02-10 have one cell tagged ``own-file`` for the analyst's own data. pyvista stays off screen with the static
backend (``labkit.setup_notebook``); its renders reach the page through ``plt.imshow``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))

# Figures (image/png outputs) each notebook shows when executed; a lost figure fails the test.
MIN_FIGURES = {
    "01": 4,
    "02": 7,
    "03": 9,
    "04": 7,
    "05": 8,
    "06": 9,
    "07": 10,
    "08": 3,
    "09": 8,
    "10": 5,
    "11": 4,
}

# Notebooks whose exercises are checked here: one 'solution'-tagged, collapsed cell per numbered exercise.
SOLVED = tuple(f"{k:02d}" for k in range(1, 11))

# Notebooks with one cell, tagged 'own-file', where the analyst puts their own LAS/LAZ file.
OWN_FILE = tuple(f"{k:02d}" for k in range(1, 11))

INLINE = "module://matplotlib_inline.backend_inline"


def _number(path: Path) -> str:
    return path.name[:2]


def _read(path):
    nbformat = pytest.importorskip("nbformat")
    return nbformat.read(path, as_version=4)


def _tagged(nb, tag):
    return [c for c in nb.cells if tag in c.get("metadata", {}).get("tags", [])]


def _exercise_count(nb) -> int:
    """Numbered items of the markdown cell(s) headed 'Exercises'."""
    n = 0
    for cell in nb.cells:
        if cell.cell_type == "markdown" and re.search(r"^#+\s*Exercises|\*\*Exercises\*\*", cell.source, re.M):
            text = re.split(r"^#+\s*Exercises|\*\*Exercises\*\*", cell.source, maxsplit=1, flags=re.M)[1]
            n += len(re.findall(r"^\d+\.\s", text, re.M))
    return n


def _images(cell) -> int:
    return sum("image/png" in out.get("data", {}) for out in cell.get("outputs", []))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_is_valid_and_clean(path):
    """nbformat-valid, stored without outputs or execution counts, free of control characters."""
    nbformat = pytest.importorskip("nbformat")
    nb = _read(path)
    nbformat.validate(nb)
    for i, cell in enumerate(nb.cells):
        assert not re.search(r"[\x00-\x08\x0b\x0c\x0e-\x1f]", cell.source), f"cell {i}: control character in source"
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, f"cell {i} carries outputs"


def test_every_notebook_has_its_figure_count():
    """The table states the figures of every notebook present, at least three each."""
    numbers = sorted(_number(p) for p in NOTEBOOKS)
    assert numbers == sorted(MIN_FIGURES), f"notebooks {numbers} vs table {sorted(MIN_FIGURES)}"
    assert min(MIN_FIGURES.values()) >= 3


@pytest.mark.parametrize("number", SOLVED)
def test_every_exercise_has_a_solution(number):
    """One tagged solution cell per numbered exercise, after the exercises."""
    path = next(NOTEBOOK_DIR.glob(f"{number}-*.ipynb"), None)
    if path is None:
        pytest.skip(f"notebook {number} not present")
    nb = _read(path)
    n_ex = _exercise_count(nb)
    solutions = _tagged(nb, "solution")
    assert n_ex >= 1, "no numbered exercises found"
    assert len(solutions) == n_ex, f"{n_ex} exercises but {len(solutions)} solution cells"
    assert all(c.cell_type == "code" and c.source.strip() for c in solutions)
    assert all(c.metadata.get("jupyter", {}).get("source_hidden") for c in solutions), "solution not collapsed"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_solutions_are_hidden_until_opened(path):
    """Every solution cell keeps its code and its output collapsed (JupyterLab) and hidden behind a toggle (site).

    After *Run All* a student must not find the answer printed under the exercise: ``jupyter.source_hidden`` and
    ``jupyter.outputs_hidden`` collapse both in JupyterLab, the ``hide-cell`` tag folds the cell on the
    documentation site (myst-nb), and a markdown cell before the first solution says how to open them.
    """
    nb = _read(path)
    solutions = [i for i, c in enumerate(nb.cells) if "solution" in c.get("metadata", {}).get("tags", [])]
    if not solutions:
        pytest.skip("no solution cells")
    for i in solutions:
        meta = nb.cells[i].metadata
        hidden = meta.get("jupyter", {})
        assert hidden.get("source_hidden") is True, f"cell {i}: code of the solution is not collapsed"
        assert hidden.get("outputs_hidden") is True, f"cell {i}: output of the solution is not collapsed"
        assert "hide-cell" in meta.get("tags", []), f"cell {i}: solution not folded on the documentation site"
    before = " ".join(c.source for c in nb.cells[: solutions[0]] if c.cell_type == "markdown")
    assert "Expand All Code" in before and "Show code cell content" in before, "no text says how to open a solution"
    text = " ".join(c.source for c in nb.cells if c.cell_type == "markdown")
    assert "run the next cell" not in text, "a solution's text asks to run a cell whose output is already shown"


@pytest.mark.parametrize("number", OWN_FILE)
def test_own_file_cell(number):
    """Exactly one clearly marked code cell where the user puts their own file."""
    path = next(NOTEBOOK_DIR.glob(f"{number}-*.ipynb"), None)
    if path is None:
        pytest.skip(f"notebook {number} not present")
    cells = _tagged(_read(path), "own-file")
    assert len(cells) == 1 and cells[0].cell_type == "code"
    assert "YOUR OWN FILE" in cells[0].source


@pytest.mark.notebook
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs_and_shows_its_figures(path, monkeypatch):
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("matplotlib_inline")
    # The kernel inherits this environment: without MPLBACKEND, ipykernel selects the inline backend.
    monkeypatch.delenv("MPLBACKEND", raising=False)
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    monkeypatch.setenv("PYVISTA_OFF_SCREEN", "true")
    nb = _read(path)
    nb.cells.append(_probe_cell())
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}
    )
    client.execute()

    backend = "".join(o.get("text", "") for o in nb.cells[-1].outputs).strip()
    assert backend == INLINE, f"kernel ran with backend {backend!r}, not the inline one"
    per_cell = [_images(c) for c in nb.cells]
    expected = MIN_FIGURES[_number(path)]
    assert sum(per_cell) >= expected, (
        f"{sum(per_cell)} figures shown, expected at least {expected}; per cell: "
        + ", ".join(f"{i}:{k}" for i, k in enumerate(per_cell) if k)
    )
    for cell in _tagged(nb, "figure"):
        assert _images(cell) >= 1, f"cell tagged 'figure' shows no image:\n{cell.source[:200]}"
    _cache_for_docs(nb, path)


def _cache_for_docs(nb, path):
    """Keep the executed notebook for the documentation site when ``LABKIT_NOTEBOOK_CACHE`` names a folder.

    The site (docs/conf.py, myst-nb in cache mode) looks notebooks up in that jupyter-cache by the hash of
    their code cells and reuses the outputs, so CI executes every notebook once, here.
    """
    folder = os.environ.get("LABKIT_NOTEBOOK_CACHE")
    if not folder:
        return
    jupyter_cache = pytest.importorskip("jupyter_cache")
    from jupyter_cache.base import CacheBundleIn

    nb.cells.pop()  # the backend probe is not part of the notebook
    for cell in nb.cells:  # the cache matches code and cell metadata: drop the kernel's timing records
        cell.metadata.pop("execution", None)
    jupyter_cache.get_cache(folder).cache_notebook_bundle(CacheBundleIn(nb, str(path)), check_validity=False,
                                                          overwrite=True)


def _probe_cell():
    nbformat = pytest.importorskip("nbformat")
    return nbformat.v4.new_code_cell("import matplotlib\nprint(matplotlib.get_backend())")
