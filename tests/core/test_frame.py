"""labkit.core.frame: the local origin of UTM-sized coordinates and the reduction to it, without losing digits."""

import numpy as np
import pytest

from labkit.core.frame import local_origin, reduce

UTM = np.array([612_345.0, 5_401_234.0, 287.0])


def _utm_cloud(n, seed=0, size=40.0):
    rng = np.random.default_rng(seed)
    return UTM + rng.uniform(-size, size, (n, 3)) * [1, 1, 0.25]  # full float64 digits, not rounded to mm


def test_origin_is_the_rounded_mean_of_the_first_cloud():
    pts = _utm_cloud(1000)
    origin = local_origin(pts, pts + 1000.0)  # only the first cloud counts
    np.testing.assert_array_equal(origin, np.round(pts.mean(axis=0)))
    assert np.all(origin == np.floor(origin))  # whole metres
    assert local_origin([[0.4, -0.6, 2.5]]).tolist() == [0.0, -1.0, 2.0]  # lists are accepted; half to even


def test_large_cloud_origin_from_a_strided_subset_lies_near_the_data():
    pts = _utm_cloud(200_000, seed=1)
    origin = local_origin(pts)
    assert np.all(np.abs(origin - pts.mean(axis=0)) < 3.0)  # 4096 of 200k points: within a few metres
    assert np.all((origin >= pts.min(axis=0)) & (origin <= pts.max(axis=0)))


def test_reduce_and_back_is_exact_to_the_last_bit_at_utm_size():
    pts = _utm_cloud(5000, seed=2)
    keep = pts.copy()
    origin = local_origin(pts)
    local = reduce(pts, origin)
    np.testing.assert_array_equal(pts, keep)  # the input is not modified
    assert local is not pts and local.dtype == np.float64
    assert np.abs(local).max() < 50  # small numbers: products and squares keep their digits
    np.testing.assert_array_equal(local + origin, pts)  # no digit lost, not even the last one
    # the reduced differences are the exact differences of the UTM coordinates
    d = local[1:] - local[:-1]
    np.testing.assert_array_equal(d, pts[1:] - pts[:-1])


def test_reduction_keeps_the_millimetre_spread_that_raw_utm_squares_lose():
    """The variance of 1 mm noise on a 5.4e6 m northing, by the one-pass formula E[y^2] - E[y]^2."""
    rng = np.random.default_rng(3)
    y = UTM[1] + rng.normal(0, 0.001, 10_000)
    truth = np.var(y - UTM[1])  # two-pass, on small numbers

    def one_pass(v):
        return np.mean(v * v) - np.mean(v) ** 2

    pts = np.c_[np.zeros_like(y), y, np.zeros_like(y)]
    local = reduce(pts, local_origin(pts))
    assert abs(one_pass(local[:, 1]) - truth) < 1e-3 * truth  # reduced: right to 0.1 %
    assert abs(one_pass(y) - truth) > truth  # raw UTM: the 1e-6 m^2 drowns in the rounding of 2.9e13 m^2


def test_origin_by_the_compiled_sums_is_numpys_rounded_mean(monkeypatch):
    """With numba loaded the strided column sums of a C-contiguous cloud run compiled: the same origin, to the
    last bit of the mean, as numpy's mean over axis 0 (which sums a Fortran-ordered cloud pairwise)."""
    from labkit.core import frame

    pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    for n in (1, 3, 4095, 4096, 8193, 100_000, 333_333):
        pts = UTM + rng.normal(scale=rng.uniform(0.01, 500.0), size=(n, 3))
        for arr in (pts, np.asfortranarray(pts), pts[::-1]):
            step = max(1, n // 4096)
            if arr.flags.c_contiguous:  # (the compiled route; other layouts take numpy's)
                sums, m = frame._strided_sums(arr, step)  # the kernel's arithmetic, run by Python
                np.testing.assert_array_equal(sums / m, arr[::step].mean(axis=0))
            np.testing.assert_array_equal(local_origin(arr), np.round(arr[::step].mean(axis=0)))
    assert frame._sums_kernel() is not None  # (numba was imported above: the compiled route ran)
