"""Headless rendering for every test: pyvista off screen, matplotlib Agg."""

import os

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import pyvista  # noqa: E402

pyvista.OFF_SCREEN = True


# --- real development data (../shared/realdata, not shipped) --------------------------------
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


def _realdata_dir():
    """The folder of real development clouds, or None where it is absent."""
    candidates = [os.environ.get("LABKIT_REALDATA")]
    candidates += [str(Path(__file__).resolve().parents[2] / "shared" / "realdata"), "/work/shared/realdata"]
    for c in candidates:
        if c and (Path(c) / "README.md").is_file():
            return Path(c)
    return None


REALDATA = _realdata_dir()


@pytest.fixture
def realdata():
    """Path of the real development data; the test is skipped where the folder is absent."""
    if REALDATA is None:
        pytest.skip("real development data not available (set LABKIT_REALDATA)")
    return REALDATA
