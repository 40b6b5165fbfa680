"""M3C2 parameters against the data (labkit.change, labkit.change.grid): a cylinder far below the point spacing is
refused at once; a thin long cylinder does bounded work; the compiled searches return to Python between calls, so
Ctrl-C stops them."""

import time

import numpy as np
import pytest

from labkit.change import grid as _change_grid, search as _change_search
from labkit.change.m3c2 import m3c2
from labkit.core.errors import LabkitError

pytest.importorskip("numba")


def _plane(n=6000, seed=0, size=20.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, size, (n, 2))
    return np.c_[xy, 0.01 * rng.normal(size=n)]


@pytest.mark.parametrize("radius", [1e-9, 1e-6, 1e-4, 1e-3])
def test_a_cylinder_far_below_the_point_spacing_is_refused_at_once(radius):
    a = _plane()
    t0 = time.perf_counter()
    with pytest.raises(LabkitError, match="far below the point spacing"):
        m3c2(a, a + [0, 0, 0.1], normal_radius=1.0, cylinder_radius=radius, max_depth=1.0)
    assert time.perf_counter() - t0 < 10.0  # (an exploding search would run for minutes)


@pytest.mark.parametrize("radius", [0.02, 0.1, 0.5])
def test_radii_near_the_spacing_are_taken(radius):
    a = _plane()
    res = m3c2(a, a + [0, 0, 0.1], [[10.0, 10.0, 0.0]], normal_radius=1.0, cylinder_radius=radius, max_depth=1.0)
    if np.isfinite(res.distance[0]):
        assert res.distance[0] == pytest.approx(0.1, abs=0.02)


@pytest.mark.parametrize("radius, depth", [(0.002, 5.0), (0.01, 20.0), (0.05, 50.0)])
def test_thin_long_cylinders_agree_with_the_tree_search(radius, depth):
    """The bounded voxel size changes the work, not the answer (kd-tree route as the independent reference)."""
    rng = np.random.default_rng(1)
    local = rng.uniform(-1, 1, (20_000, 3)) * [1.0, 1.0, 0.2]
    cores = local[:300] + 1e-3  # off the points: a point exactly on a slab boundary of the tree route counts twice
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    fast = _change_search.cylinder_stats(local, cores, normals, radius, depth, use_numba=True)
    slow = _change_search.cylinder_stats(local, cores, normals, radius, depth, use_numba=False)
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_allclose(fast[1], slow[1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("per_call", [1, 7, 4096])
def test_results_do_not_depend_on_the_calls(monkeypatch, per_call):
    a = _plane(3000)
    ref = m3c2(a, a + [0, 0, 0.05], 1.0, normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    monkeypatch.setattr(_change_search, "CALL_CORES", per_call)
    got = m3c2(a, a + [0, 0, 0.05], 1.0, normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    np.testing.assert_array_equal(got.distance, ref.distance)
    np.testing.assert_array_equal(got.lod, ref.lod)


@pytest.mark.parametrize("module, search", [(_change_grid, "cylinder_stats"), (_change_search, "ball_covariances")])
def test_an_interrupt_stops_the_search_between_calls(monkeypatch, module, search):
    """Ctrl-C (KeyboardInterrupt) raised after the second compiled call: no further call runs."""
    calls = []
    original = getattr(module, search)

    def counted(*args):
        calls.append(1)
        out = original(*args)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return out

    monkeypatch.setattr(module, search, counted)
    monkeypatch.setattr(_change_search, "CALL_CORES", 10)
    a = _plane(3000)
    with pytest.raises(KeyboardInterrupt):
        m3c2(a, a + [0, 0, 0.05], 0.5, normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    assert len(calls) == 2
