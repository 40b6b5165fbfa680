"""One name per concept in labkit.registration, and ``labkit.registration.icp`` is always the function."""

import importlib
import inspect
import pkgutil
import subprocess
import sys
import warnings

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
    assert labkit.icp is icp and icp.__module__ == "labkit.registration.icp_loop"


def test_icp_is_the_function_in_a_fresh_interpreter_after_importing_the_loop_module():
    code = ("import labkit.registration.icp_loop, inspect; from labkit.registration import icp; "
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


def test_old_consensus_keywords_warn_and_give_the_same_cube():
    rng = np.random.default_rng(3)
    tgt = _plane(1500, rng)
    src = tgt[::3] + [0.04, -0.02, 0.0]
    new = consensus_cube(src, tgt, extent=0.06, step=0.02, metric="point_to_point", max_angle_deg=20.0,
                         k=10, target_normals=None)
    with pytest.warns(DeprecationWarning) as record:
        old = consensus_cube(src, tgt, extent=0.06, step=0.02, criterion="point_to_point", max_angle=20.0,
                             normal_k=10, normals=(None, None))
    said = " ".join(str(w.message) for w in record)
    for old_name, new_name in (("criterion", "metric"), ("max_angle", "max_angle_deg"), ("normal_k", "k")):
        assert f"'{old_name}' is deprecated" in said and f"use '{new_name}'" in said
    np.testing.assert_array_equal(old.counts, new.counts)
    with pytest.warns(DeprecationWarning, match="use .metric"):
        assert old.criterion == new.metric == "point_to_point"
    with pytest.warns(DeprecationWarning, match="use .max_angle_deg"):
        assert old.max_angle == 20.0


def test_old_deletion_keyword_of_max_consensus_warns_and_gives_the_same_result():
    rng = np.random.default_rng(4)
    tgt = _plane(1500, rng)
    src = tgt[::3] + [0.03, 0.01, -0.02]
    kw = dict(extent=0.1, tol=0.02, max_time=5.0, max_points=300)
    new = max_consensus(src, tgt, reject_sigma=2.5, **kw)
    with pytest.warns(DeprecationWarning, match="'deletion_k' is deprecated.*'reject_sigma'"):
        old = max_consensus(src, tgt, deletion_k=2.5, **kw)
    np.testing.assert_allclose(old.translation, new.translation, rtol=0, atol=1e-12)


def test_new_names_do_not_warn():
    rng = np.random.default_rng(5)
    tgt = _plane(800, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        consensus_cube(tgt[::4], tgt, extent=0.04, step=0.02, metric="point_to_plane", k=8)
