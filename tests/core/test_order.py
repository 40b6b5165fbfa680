"""labkit.core.order.median: the same number as np.median, also where its bracket misses."""

import numpy as np
import pytest

from labkit.core.order import MIN_SIZE, median


def _cases():
    rng = np.random.default_rng(1)
    n = 3 * MIN_SIZE
    yield "normal odd", rng.normal(size=n + 1)
    yield "normal even", rng.normal(size=n)
    yield "heavy tails", rng.standard_cauchy(n)
    yield "many ties", rng.integers(0, 5, n).astype(float)
    yield "sorted", np.sort(rng.normal(size=n))
    yield "reverse sorted", np.sort(rng.normal(size=n))[::-1].copy()
    # the strided sample sees only the large values: its bracket misses the middle ranks
    x = rng.normal(size=n)
    x[:: n // 8192] = 1e6 + np.arange(len(x[:: n // 8192]))
    yield "sample misses", x
    yield "zero median", np.r_[-np.ones(n // 2), 0.0, np.ones(n // 2)]
    z = rng.normal(size=n)
    z[5] = np.nan
    yield "with NaN", z
    yield "small", rng.normal(size=101)


@pytest.mark.parametrize("name, x", list(_cases()), ids=[c[0] for c in _cases()])
def test_median_is_numpys_to_the_bit(name, x):
    got, want = median(x), np.median(x)
    assert (np.isnan(got) and np.isnan(want)) or (got == want and np.signbit(got) == np.signbit(want))


def test_median_leaves_its_input_alone():
    x = np.random.default_rng(2).normal(size=2 * MIN_SIZE)
    before = x.copy()
    median(x)
    assert np.array_equal(x, before)
