"""labkit.core.jit: one compiled kernel per function and options, each with its own disk-cache entry."""

import numpy as np

from labkit.core import jit
from labkit.core.jit import SIMD, compiled, have_numba


def test_options_get_their_own_kernel_and_cache_name():
    """The same function with and without SIMD options: two kernels, named apart (numba's disk cache keys a
    kernel by name and argument types only, so one would otherwise load the other's machine code)."""
    from labkit.ransac._ball import _residuals

    plain, simd = compiled(_residuals), compiled(_residuals, **SIMD)
    assert plain is compiled(_residuals) and simd is compiled(_residuals, **SIMD) and plain is not simd
    if have_numba():
        assert plain.py_func is _residuals and simd.py_func.__qualname__.startswith("_residuals__")
    x = np.random.default_rng(0).normal(size=(3, 1000))
    c = np.array([0.1, 0.2, 0.3])
    diff = x - c[:, None]
    exact = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]) - 1.0
    np.testing.assert_array_equal(plain(x[0], x[1], x[2], c, 1.0), exact)  # no fused multiply-adds
    np.testing.assert_allclose(simd(x[0], x[1], x[2], c, 1.0), exact, rtol=0, atol=1e-15)


def test_option_names_do_not_depend_on_the_hash_seed():
    """A set of fastmath flags gives the same cache name whatever its iteration order."""
    a = jit._canonical({"fastmath": {"reassoc", "nsz", "contract"}, "error_model": "numpy"})
    b = jit._canonical({"error_model": "numpy", "fastmath": {"contract", "reassoc", "nsz"}})
    assert a == b
