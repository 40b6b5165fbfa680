"""labkit.core.arrays: the fast routes give numpy's own values."""

import numpy as np
import pytest

from labkit.core.arrays import extent, rows


@pytest.mark.parametrize("shape", [(1, 3), (1000, 3), (777, 2), (50, 5)])
def test_extent_equals_min_and_max_over_the_first_axis(shape):
    a = np.random.default_rng(0).normal(0, 1e6, shape)
    lo, hi = extent(a)
    assert np.array_equal(lo, a.min(axis=0)) and np.array_equal(hi, a.max(axis=0))
    cells = np.random.default_rng(1).integers(-5, 9, shape)  # integers keep their type
    assert np.array_equal(extent(cells)[1], cells.max(axis=0)) and extent(cells)[1].dtype == cells.dtype


def test_extent_propagates_nan_and_rejects_empty_arrays_as_min_does():
    a = np.array([[0.0, 1.0, 2.0], [np.nan, 0.0, 5.0]])
    lo, hi = extent(a)
    assert np.isnan(lo[0]) and np.isnan(hi[0]) and lo[1] == 0.0 and hi[2] == 5.0
    with pytest.raises(ValueError):
        extent(np.empty((0, 3)))


def test_rows_equals_numpy_indexing_for_masks_and_indices():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(500, 3))
    mask = rng.random(500) < 0.3
    index = rng.integers(-500, 500, 800)  # negative indices and repeats too
    for sel in (mask, index, np.zeros(500, bool), np.array([], dtype=int), index.astype(np.int32)):
        out = rows(a, sel)
        assert np.array_equal(out, a[sel]) and out.shape == a[sel].shape
        assert not np.shares_memory(out, a)
    view = a[:, :2]  # not contiguous
    assert np.array_equal(rows(view, mask), view[mask])
    assert np.array_equal(rows(a[:, 0], index), a[:, 0][index])  # one-dimensional


def test_rows_raises_as_numpy_does_on_a_wrong_selection():
    a = np.zeros((4, 3))
    with pytest.raises(IndexError):
        rows(a, np.array([True, False]))  # a mask of the wrong length
    with pytest.raises(IndexError):
        rows(a, np.array([4]))
