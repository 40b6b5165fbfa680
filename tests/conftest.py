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


# --- quick default run: slow checks and notebooks only with --all (CI runs everything) ------
def pytest_addoption(parser):
    parser.addoption("--all", action="store_true", dest="run_all",
                     help="also run the tests marked slow or notebook (notebooks, browser, real data, "
                          "Monte Carlo): what CI runs")


def pytest_collection_modifyitems(config, items):
    """Deselect the ``slow`` and ``notebook`` tests unless --all, an explicit -m, or a test file or test
    named on the command line (``pytest tests/test_icp.py`` runs all of that file) asks for them."""
    named = any(a.split("::")[0].endswith(".py") for a in config.args)
    if config.getoption("run_all", False) or config.option.markexpr or named:
        return
    keep, left_out = [], []
    for item in items:
        (left_out if item.get_closest_marker("slow") or item.get_closest_marker("notebook") else keep).append(item)
    if left_out:
        config.hook.pytest_deselected(items=left_out)
        items[:] = keep
