"""Local origin for UTM-sized coordinates.

Coordinates of 6-7 digits leave only about 9 significant digits below the metre
for any product or square. All algebra in labkit runs on coordinates reduced to
a local origin; results are moved back to the caller's frame at the end.
"""

from __future__ import annotations

import sys

import numpy as np

from .jit import compiled

_ORIGIN_POINTS = 4096  # an origin is the mean of about this many evenly strided points
_SUMS = []  # [the compiled column sums] once built


def local_origin(*clouds: np.ndarray) -> np.ndarray:
    """A shared origin for one or more (n, 3) arrays: the first cloud's mean, rounded to 1 m.

    The mean is taken over at most about 4096 evenly strided points (an origin only
    has to lie near the data; a full pass over 10^6 points costs 10 ms for nothing).
    Rounding keeps the reduction ``xyz - origin`` exact to the last bit for
    coordinates stored with millimetre resolution.
    """
    first = np.asarray(clouds[0], dtype=np.float64)
    step = max(1, len(first) // _ORIGIN_POINTS)
    # (rows in memory order: numpy then sums row after row; over another layout it may sum pairwise)
    rows = first.ndim == 2 and first.shape[1] == 3 and len(first) and first.flags.c_contiguous
    kernel = _sums_kernel() if rows else None
    if kernel is None:
        return np.round(first[::step].mean(axis=0))
    sums, m = kernel(first, step)
    return np.round(sums / m)


def _strided_sums(a, step):  # pragma: no cover - compiled
    """Column sums of the rows a[::step] (n, 3), row after row: numpy's order for a mean over axis 0."""
    s0 = s1 = s2 = 0.0
    m = 0
    for i in range(0, a.shape[0], step):
        s0, s1, s2, m = s0 + a[i, 0], s1 + a[i, 1], s2 + a[i, 2], m + 1
    return np.array([s0, s1, s2]), m


def _sums_kernel():
    """:func:`_strided_sums` compiled, once numba is loaded by another step (a mean of 4096 points is not
    worth loading it: numpy's mean over axis 0 takes about 0.1 ms, this pass a few microseconds)."""
    if not _SUMS:
        if "numba" not in sys.modules:
            return None
        _SUMS.append(compiled(_strided_sums))
    return _SUMS[0]


#: The types :func:`local_origin` calls the kernel with for a writeable C-contiguous (n, 3) array and a stride.
_SUMS_SIGNATURE = "Tuple((float64[::1], int64))(float64[:, ::1], int64)"


def load_origin_kernel():
    """Load the compiled pass of :func:`local_origin` now, where numba is loaded (else do nothing).

    A module whose first call in a fresh process should not wait for numba's disk cache (M3C2's voxel
    grid) calls this when it is imported; the kernel is the same either way.

    Examples
    --------
    >>> load_origin_kernel()
    >>> local_origin(np.array([[0.4, 1.6, 2.0], [1.6, 2.4, 2.0]])).tolist()
    [1.0, 2.0, 2.0]
    """
    kernel = _sums_kernel()
    if kernel is not None and hasattr(kernel, "compile"):  # (other types, e.g. read-only arrays, compile on demand)
        kernel.compile(_SUMS_SIGNATURE)


def reduce(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Return ``points - origin`` as a new array (the input is never modified)."""
    return np.asarray(points, dtype=np.float64) - origin
