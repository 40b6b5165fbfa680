"""Points of a cloud within a ball: one compiled pass over the points, no tree to build.

The verification asks a few dozen ball queries per detection; a k-d tree over
10^6 points costs about a second to build, a pass over them a few milliseconds.
The comparison is |x - c|^2 <= R^2, as in ``cKDTree.query_ball_point``.
Without numba the same runs in numpy.
"""

from __future__ import annotations

import numpy as np

try:  # numba compiles the passes; without it numpy does the work
    import numba
except ImportError:  # pragma: no cover - depends on the environment
    numba = None


def _inside(X, c, R):  # pragma: no cover - compiled
    R2 = R * R
    out = np.empty(X.shape[0], dtype=np.int64)
    k = 0
    for i in range(X.shape[0]):
        dx, dy, dz = X[i, 0] - c[0], X[i, 1] - c[1], X[i, 2] - c[2]
        if dx * dx + dy * dy + dz * dz <= R2:
            out[k] = i
            k += 1
    return out[:k].copy()


def _counts(X, c, radii):  # pragma: no cover - compiled
    R2 = radii * radii
    out = np.zeros(radii.shape[0], dtype=np.int64)
    for i in range(X.shape[0]):
        dx, dy, dz = X[i, 0] - c[0], X[i, 1] - c[1], X[i, 2] - c[2]
        d2 = dx * dx + dy * dy + dz * dz
        for j in range(radii.shape[0]):
            if d2 <= R2[j]:
                out[j] += 1
    return out


if numba is not None:
    _inside = numba.njit(cache=True, nogil=True)(_inside)
    _counts = numba.njit(cache=True, nogil=True)(_counts)


def ball_indices(X, c, R):
    """Indices (ascending) of the points of X (n, 3), C-contiguous float64, within distance R of c."""
    c = np.asarray(c, dtype=np.float64)
    if numba is None:  # pragma: no cover
        d = X - c
        return np.flatnonzero(np.einsum("ij,ij->i", d, d) <= R * R)
    return _inside(X, c, float(R))


def ball_counts(X, c, radii):
    """Number of points of X within each of the distances ``radii`` of c."""
    c = np.asarray(c, dtype=np.float64)
    radii = np.atleast_1d(np.asarray(radii, dtype=np.float64))
    if numba is None:  # pragma: no cover
        d = X - c
        d2 = np.einsum("ij,ij->i", d, d)
        return np.array([np.count_nonzero(d2 <= r * r) for r in radii])
    return _counts(X, c, radii)
