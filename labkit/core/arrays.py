"""Whole-row operations on tall (n, d) arrays, by the routes numpy runs fast.

numpy's generic paths for a row-major (n, 3) array are slow where a loop runs over the three values
of a row: ``a.min(axis=0)`` loops over three values at a time, ``a[index]`` and ``a[mask]`` walk a
general index iterator. Measured on 262,000 points: 12.6 ms for the box against 0.5 ms column by
column, 7.8 ms for the rows at an index against 0.7 ms with ``np.take``, 4.4 ms for the rows at a
mask against 1.1 ms with ``np.compress``. The helpers return the same values.
"""

from __future__ import annotations

import numpy as np


def extent(points) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and the largest value of every column of ``points`` (m, d): the box of a cloud.

    Column by column (the same values: a minimum is exact); an empty array raises as ``min`` does.

    Examples
    --------
    >>> lo, hi = extent(np.array([[1.0, 5.0, -2.0], [3.0, 4.0, 0.5]]))
    >>> lo.tolist(), hi.tolist()
    ([1.0, 4.0, -2.0], [3.0, 5.0, 0.5])
    """
    points = np.asarray(points)
    cols = range(points.shape[1])
    return np.array([points[:, c].min() for c in cols]), np.array([points[:, c].max() for c in cols])


def rows(a, selection) -> np.ndarray:
    """``a[selection]`` for a boolean mask or an integer index along the first axis (a new array).

    Examples
    --------
    >>> a = np.arange(12.0).reshape(4, 3)
    >>> rows(a, np.array([True, False, False, True])).tolist(), rows(a, np.array([2, 0]))[:, 0].tolist()
    ([[0.0, 1.0, 2.0], [9.0, 10.0, 11.0]], [6.0, 0.0])
    """
    a, selection = np.asarray(a), np.asarray(selection)
    if selection.dtype == bool:
        if selection.shape != a.shape[:1]:
            return a[selection]  # (numpy's own checks and message)
        return np.compress(selection, a, axis=0)
    if selection.dtype.kind not in "iu" or selection.ndim != 1:
        return a[selection]
    return np.take(a, selection, axis=0)
