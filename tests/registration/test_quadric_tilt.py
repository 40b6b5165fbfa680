"""The compiled tilt covariance of quadric normals equals its numpy route (gather and einsum) to the bit."""

import numpy as np

from labkit.registration.matching.quadric_tilt import quadric_tilt


def test_compiled_rows_equal_the_einsum_route():
    rng = np.random.default_rng(3)
    n, m = 500, 2000
    store = {"frame": rng.normal(size=(n, 3, 3)), "slope": rng.normal(size=(n, 3)) * 1e-3}
    slot = rng.integers(-1, n, n)  # -1: a point without a slot (np.take reads the buffer's last row)
    pos = rng.integers(0, n, m)

    def get(name, p):
        return np.take(store[name], slot[p], axis=0)

    got = quadric_tilt(store, slot, pos, get)
    want = quadric_tilt({}, slot, pos, get)  # without the stored frames: the numpy route
    assert got.shape == (m, 3, 3)
    assert np.array_equal(got, want)
    assert np.allclose(got, np.swapaxes(got, 1, 2))  # a covariance: symmetric
