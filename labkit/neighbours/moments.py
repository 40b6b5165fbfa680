"""Moments of neighbourhoods: centroids (eq. 1) and covariances (eq. 2) of notebook 04, the one home of the kernel.

Used by the neighbour search (:mod:`.search`), the features and the k-d tree's search of whole leaves
(:mod:`.kdtree`), which sums the same moments while the neighbours are in cache.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import compiled
from .eigh3 import HAVE_NUMBA


__all__ = ["covariances", "knn_moments", "masked_covariances"]


def covariances(local, counts, flat, cols=None):
    """Centroids (c, 3) (eq. 1) and covariances (c, 3, 3) (eq. 2) of one chunk of neighbourhoods.

    ``cols`` = ``local.T`` as a contiguous (3, n) array. For kNN the coordinates are then
    gathered per axis into contiguous (c, k) blocks and the six distinct products summed
    along k: measured 4-5x faster than a batched (3 x k) @ (k x 3) matmul on (c, k, 3).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> pts = rng.normal(size=(50, 3))
    >>> idx = rng.integers(0, 50, (4, 10))  # four kNN neighbourhoods of 10 points
    >>> cen, C = covariances(pts, None, idx)
    >>> cen.shape, C.shape, bool(np.allclose(C[0], np.cov(pts[idx[0]].T, bias=True)))
    ((4, 3), (4, 3, 3), True)
    """
    if flat.ndim == 2:
        if cols is None:
            return masked_covariances(local[flat], None)  # (c, k, 3), only one chunk at a time
        if HAVE_NUMBA:
            cen, C = np.empty((len(flat), 3)), np.empty((len(flat), 3, 3))
            _knn_covariances(cols, flat, cen, C)
            return cen, C
        k = flat.shape[1]
        cen = np.empty((len(flat), 3))
        D = []
        for a in range(3):
            g = cols[a][flat]  # (c, k)
            g -= g[:, :1].copy()  # differences to the first neighbour, as the compiled kernel
            m = g.mean(axis=1)
            cen[:, a] = cols[a][flat[:, 0]] + m  # (eq. 1)
            g -= m[:, None]
            D.append(g)
        C = np.empty((len(flat), 3, 3))
        for a in range(3):
            for b in range(a, 3):
                C[:, a, b] = C[:, b, a] = np.einsum("ck,ck->c", D[a], D[b]) / k  # (eq. 2)
        return cen, C
    # ragged radius neighbourhoods: segment sums with bincount
    seg = np.repeat(np.arange(len(counts)), counts)
    m = np.maximum(counts, 1)
    X = local[flat]
    cen = np.stack([np.bincount(seg, X[:, a], len(counts)) for a in range(3)], axis=1) / m[:, None]  # (eq. 1)
    D = X - cen[seg]
    C = np.empty((len(counts), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            C[:, a, b] = C[:, b, a] = np.bincount(seg, D[:, a] * D[:, b], len(counts)) / m  # (eq. 2)
    C[counts < 3] = np.nan  # too few neighbours: no plane
    return cen, C


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def knn_moments(x, y, z, ids, k, cen, C, r):  # pragma: no cover - compiled
    """Row ``r`` of ``cen`` and ``C``: centroid (eq. 1) and mean outer product of the deviations (eq. 2) of the
    points ``ids[:k]`` of the coordinate columns x, y, z, in two passes (no temporaries).

    The sums run over the differences to the first neighbour (for a point's own neighbourhood: the
    point itself). A difference of two coordinates does not depend on the frame they were reduced to
    (an integer origin leaves the reduction exact): the covariance of one neighbourhood is then the same
    to the bit in every such frame, so ICP can reuse what the surface selection computed in the whole
    cloud's frame; and large coordinates lose no digits to the centroid.

    The one compiled covariance kernel: :func:`covariances` and the k-d tree's search of whole leaves
    (:meth:`labkit.neighbours.kdtree.KDTree.knn_moments_of_leaves`) both call it, so both give the same numbers.
    """
    q0 = ids[0]
    x0, y0, z0 = x[q0], y[q0], z[q0]
    sx = sy = sz = 0.0
    for j in range(k):
        q = ids[j]
        sx += x[q] - x0
        sy += y[q] - y0
        sz += z[q] - z0
    cx, cy, cz = sx / k, sy / k, sz / k
    xx = xy = xz = yy = yz = zz = 0.0
    for j in range(k):
        q = ids[j]
        dx, dy, dz = (x[q] - x0) - cx, (y[q] - y0) - cy, (z[q] - z0) - cz
        xx += dx * dx
        xy += dx * dy
        xz += dx * dz
        yy += dy * dy
        yz += dy * dz
        zz += dz * dz
    cen[r, 0], cen[r, 1], cen[r, 2] = x0 + cx, y0 + cy, z0 + cz
    C[r, 0, 0], C[r, 1, 1], C[r, 2, 2] = xx / k, yy / k, zz / k
    C[r, 0, 1] = C[r, 1, 0] = xy / k
    C[r, 0, 2] = C[r, 2, 0] = xz / k
    C[r, 1, 2] = C[r, 2, 1] = yz / k


@compiled
def _knn_covariances(cols, idx, cen, C):  # pragma: no cover - compiled
    """Compiled (eq. 1, 2) for kNN, one neighbourhood after the other (no (c, k, 3) temporaries). Same
    two-pass arithmetic as the numpy route, so both agree to rounding."""
    m, k = idx.shape
    x, y, z = cols[0], cols[1], cols[2]
    for i in range(m):
        knn_moments(x, y, z, idx[i], k, cen, C, i)


def masked_covariances(X, w):
    """Centroids and covariances of neighbourhoods X (c, k, 3), optionally with a 0/1 mask w (c, k).

    Examples
    --------
    >>> import numpy as np
    >>> X = np.random.default_rng(0).normal(size=(2, 6, 3))  # two neighbourhoods of 6 points
    >>> w = np.array([[1, 1, 1, 1, 0, 0], [1] * 6])  # the first uses only its first 4 points
    >>> cen, C = masked_covariances(X, w)
    >>> bool(np.allclose(cen[0], X[0, :4].mean(axis=0))), bool(np.allclose(C[0], np.cov(X[0, :4].T, bias=True)))
    (True, True)
    """
    if w is None:
        cen = X.mean(axis=1)  # (eq. 1)
        D = X - cen[:, None, :]
        return cen, np.matmul(D.transpose(0, 2, 1), D) / X.shape[1]  # (eq. 2)
    wf = w.astype(np.float64)
    m = wf.sum(axis=1)
    cen = np.einsum("ck,ckd->cd", wf, X) / m[:, None]
    D = (X - cen[:, None, :]) * wf[..., None]
    return cen, np.matmul(D.transpose(0, 2, 1), D) / m[:, None, None]


