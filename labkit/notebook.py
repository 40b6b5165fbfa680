"""One setup call for the notebooks and for headless runs."""

from __future__ import annotations

import os

from .core.checks import as_seed


def setup_headless() -> None:
    """Make matplotlib and pyvista render without a display.

    Sets VTK's EGL window (no X server needed with the PyPI vtk wheel),
    pyvista's off-screen mode and static Jupyter backend, and matplotlib's Agg
    backend when no display is present. In a Jupyter kernel matplotlib's inline
    backend is kept, so figures reach the page (and the notebook tests count them).
    """
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    if not os.environ.get("DISPLAY"):
        import matplotlib

        if "inline" not in matplotlib.get_backend().lower():
            matplotlib.use("Agg")
    import pyvista

    pyvista.OFF_SCREEN = True
    try:
        pyvista.set_jupyter_backend("static")
    except Exception:  # pragma: no cover - jupyter extras missing
        pass


def setup_notebook(seed: int = 2026) -> "np.random.Generator":  # noqa: F821
    """Setup cell of every labkit notebook; returns a seeded random generator.

    Headless rendering (see :func:`setup_headless`), numpy print options, and
    matplotlib figure defaults in one call.

    References
    ----------
    .. [1] Notebooks 01-10, first code cell (the shared setup and the seeded generator).

    Examples
    --------
    >>> from labkit.notebook import setup_notebook
    >>> rng = setup_notebook(seed=7)
    >>> int(rng.integers(100)) == int(__import__("numpy").random.default_rng(7).integers(100))
    True
    """
    import matplotlib.pyplot as plt
    import numpy as np

    seed = as_seed(seed)  # before any global setting changes
    setup_headless()
    np.set_printoptions(precision=5, suppress=True, linewidth=110)
    plt.rcParams.update({"figure.figsize": (7.5, 4.5), "figure.dpi": 100, "axes.grid": True})
    return np.random.default_rng(seed)
