"""One name per concept in labkit.registration, and ``labkit.registration.icp`` is always the function."""

import importlib
import inspect
import pkgutil
import subprocess
import sys

import numpy as np
import pytest

import labkit
import labkit.registration
from labkit.registration import consensus_cube, icp, match, max_consensus


def test_icp_is_the_function_after_every_submodule_was_imported():
    names = [m.name for m in pkgutil.iter_modules(labkit.registration.__path__)]
    assert "icp" not in names  # no module may carry the function's name
    for name in names:
        importlib.import_module(f"labkit.registration.{name}")
    from labkit.registration import icp as again

    assert inspect.isfunction(labkit.registration.icp) and labkit.registration.icp is again is icp
    assert labkit.icp is icp and icp.__module__ == "labkit.registration.closest_point.loop"


@pytest.mark.slow
def test_icp_is_the_function_in_a_fresh_interpreter_after_importing_the_loop_module():
    code = ("import labkit.registration.closest_point.loop, inspect; from labkit.registration import icp; "
            "print(inspect.isfunction(icp))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"


# concept -> the functions that take it, all under one name
SHARED = {
    "metric": (icp, consensus_cube, max_consensus),
    "max_angle_deg": (icp, match, consensus_cube, max_consensus),
    "k": (icp, match, consensus_cube, max_consensus),
    "source_normals": (icp, match, consensus_cube, max_consensus),
    "target_normals": (icp, match, consensus_cube, max_consensus),
    "reject_sigma": (icp, max_consensus),
}
OLD = ("criterion", "max_angle", "normal_k", "normals", "deletion_k")


@pytest.mark.parametrize("name", sorted(SHARED))
def test_one_name_per_concept(name):
    for func in SHARED[name]:
        params = inspect.signature(func).parameters
        assert name in params, f"{func.__name__} lacks {name}"
        assert not set(OLD) & set(params), f"{func.__name__} still has an old name"


def _plane(n, rng):
    xy = rng.uniform(0, 6, (n, 2))
    z = 0.4 * np.sin(xy[:, 0]) + 0.4 * np.cos(xy[:, 1])
    return np.column_stack([xy, z])


@pytest.mark.parametrize("old", OLD)
def test_old_names_are_refused(old):
    rng = np.random.default_rng(5)
    tgt = _plane(800, rng)
    with pytest.raises(TypeError, match=old):
        max_consensus(tgt[::4], tgt, extent=0.04, **{old: None})
    with pytest.raises(TypeError, match=old):
        consensus_cube(tgt[::4], tgt, extent=0.04, step=0.02, **{old: None})
