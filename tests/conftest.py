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


# --- the same bits on any number of cores ---------------------------------------------------
@pytest.fixture
def all_cores_and_one():
    """Run two Python snippets side by side in fresh interpreters: the first on every core, the second
    pinned to one core with one thread per pool (numba, BLAS, OpenMP). Returns their stripped stdouts
    (each run must succeed); a test compares them to show that a result does not depend on the threads.
    """
    import subprocess
    import sys

    def run(code_all, code_one, timeout=600):
        one = {sorted(os.sched_getaffinity(0))[0]} if hasattr(os, "sched_getaffinity") else None
        single = dict(os.environ, NUMBA_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
                      MKL_NUM_THREADS="1")
        pin = None if one is None else (lambda: os.sched_setaffinity(0, one))  # before numpy's pools start
        runs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, env=env, preexec_fn=pre)
                for code, env, pre in ((code_all, None, None), (code_one, single, pin))]
        out = []
        for proc in runs:
            stdout, stderr = proc.communicate(timeout=timeout)
            assert proc.returncode == 0, stderr[-2000:]
            out.append(stdout.strip())
        return out

    return run
