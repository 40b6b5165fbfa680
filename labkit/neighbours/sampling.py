"""Thinning and spacing of points: the one home of voxel thinning, even subsampling and median point spacing.

- :func:`voxel_thin`: one point per occupied voxel, the one nearest the voxel's centre (``keep='centre'``, also
  the even subsample of M3C2's core points, the ICP pyramid and the consensus target) or the first in order
  (``keep='first'``); :func:`voxel_sample`: a random one (the matching's ``sample=<size>``);
- :func:`even_subset`: at most n points spread evenly in space (the voxel edge found by bisection);
- :func:`median_spacing`: median distance of the points to their nearest other point;
- the matching's normal-space and automatic samples (:func:`normal_space_sample`, :func:`auto_sample`;
  step 1 of :func:`labkit.registration.match`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import LabkitError
from ..core.arrays import extent, rows

__all__ = ["even_subset", "flat_keys", "median_spacing", "voxel_sample", "voxel_thin"]


def flat_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per row of non-negative cell indices (mixed-radix number; row-wise unique beyond int64).

    Examples
    --------
    >>> import numpy as np
    >>> flat_keys(np.array([[0, 0, 0], [1, 2, 0], [0, 0, 0]])).tolist()
    [0, 5, 0]
    """
    dims = extent(cells)[1] + 1
    if np.prod(dims.astype(float)) >= 2.0**62:
        # too many cells for one int64: fall back to row-wise unique
        return np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    return np.ravel_multi_index(cells.T, dims)


def voxel_thin(xyz, size: float, *, keep: str = "centre", origin=None) -> np.ndarray:
    """Indices (sorted) of one point per occupied cube of edge ``size``.

    ``keep='centre'``: the point nearest the cube's centre (a measured point, ties to the first in order);
    ``'first'``: the first point of each cube. The grid starts at ``origin`` (default: the smallest
    coordinates). ``xyz`` is an (n, 3) float array, already checked by the caller.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.neighbours.sampling import voxel_thin
    >>> xyz = np.array([[0.1, 0.1, 0.1], [0.5, 0.5, 0.5], [1.5, 0.2, 0.2], [0.45, 0.5, 0.5]])
    >>> voxel_thin(xyz, 1.0, origin=np.zeros(3)).tolist(), voxel_thin(xyz, 1.0, keep="first").tolist()
    ([1, 2], [0, 2])
    """
    lo = extent(xyz)[0] if origin is None else origin
    cells = np.floor((xyz - lo) / size).astype(np.int64)
    key = flat_keys(cells)
    if keep == "first":
        return np.sort(np.unique(key, return_index=True)[1])
    centre = lo + (cells + 0.5) * size
    d2 = np.einsum("ij,ij->i", xyz - centre, xyz - centre)
    order = np.lexsort((d2, key))  # by cube, nearest its centre first
    first = np.flatnonzero(np.r_[True, np.diff(key[order]) != 0])
    return np.sort(order[first])


def even_subset(xyz, n: int) -> np.ndarray:
    """Indices of at most ``n`` points spread evenly in space (one per voxel, nearest its centre).

    The voxel edge is found by bisection on the number of occupied voxels, so dense
    parts (near a TLS scanner, overlapping strips) are thinned and sparse parts kept:
    every part of the surface gets a vote in proportion to its area, not to its density.

    Examples
    --------
    A dense patch next to a sparse one keeps about as many points per square metre in both:

    >>> import numpy as np
    >>> from labkit.neighbours.sampling import even_subset
    >>> rng = np.random.default_rng(0)
    >>> dense = np.column_stack([rng.uniform(0, 1, (2000, 2)), np.zeros(2000)])
    >>> sparse = np.column_stack([rng.uniform(1, 2, (200, 2)), np.zeros(200)])
    >>> idx = even_subset(np.vstack([dense, sparse]), 200)
    >>> bool(len(idx) <= 200), bool(0.3 < np.mean(idx < 2000) < 0.7)
    (True, True)
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) <= n:
        return np.arange(len(xyz))
    lo_xyz, hi_xyz = extent(xyz)
    span = float((hi_xyz - lo_xyz).max()) or 1.0
    lo, hi = span / n ** (1 / 3) / 8, span  # few voxels at hi; too many at lo (a surface fills n^(2/3) of n^3)
    best = None
    for _ in range(30):
        size = np.sqrt(lo * hi)
        idx = voxel_thin(xyz, size, origin=lo_xyz)
        if idx.size > n:
            lo = size
        else:
            hi, best = size, idx
            if idx.size > 0.97 * n:
                break
    return best if best is not None else voxel_thin(xyz, hi, origin=lo_xyz)


def median_spacing(xyz, sample: int = 5000, *, distinct: bool = False) -> float:
    """Median distance to the nearest other point over an even subset of about ``sample`` points (m).

    ``distinct``: repeated points count once (the spacing of the surface, not of the file; 0.0 where fewer
    than two distinct points remain); otherwise a repeated point has spacing 0 (NaN for fewer than 2 points).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.neighbours.sampling import median_spacing
    >>> g = np.arange(10) * 0.25
    >>> grid = np.column_stack([np.repeat(g, 10), np.tile(g, 10), np.zeros(100)])
    >>> median_spacing(grid), median_spacing(np.r_[grid, grid], distinct=True), median_spacing(np.r_[grid, grid])
    (0.25, 0.25, 0.0)
    """
    if distinct:
        from .kdtree import KDTree  # compiled: loaded only where a caller needs the distinct points

        tree = KDTree(xyz, merge_duplicates=True)
        if tree.n < 2:
            return 0.0
        sub = tree.data[:: max(1, tree.n // sample)]
        return float(np.median(tree.query(sub, k=2, workers=1)[0][:, 1]))
    if len(xyz) < 2:
        return float("nan")
    d, _ = cKDTree(xyz).query(xyz[:: max(1, len(xyz) // sample)], k=2, workers=-1)
    return float(np.median(d[:, 1]))

#: Normal-space sampling draws only from planar neighbourhoods: l3 / (l1 + l2 + l3) below this.
MAX_VARIATION = 0.02


def voxel_sample(points, size, rng):
    """One random point per cubic voxel of edge ``size`` (indices, sorted).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.neighbours.sampling import voxel_sample
    >>> pts = np.random.default_rng(0).uniform(0, 2, (1000, 3))
    >>> len(voxel_sample(pts, 1.0, np.random.default_rng(1)))
    8
    """
    order = rng.permutation(len(points))
    _, first = np.unique(voxel_keys(points, size)[order], return_index=True)
    return np.sort(order[first])


def voxel_keys(points, size):
    """One int64 key per cubic voxel of edge ``size`` (21 bits per axis; wider grids raise).

    Column by column: no (n, 3) temporaries on a 10-million-point cloud.
    """
    key = np.zeros(len(points), dtype=np.int64)
    for a in range(3):
        cell = np.floor(points[:, a] / size).astype(np.int64)  # the grid through 0 of the local frame
        if cell.size:
            cell -= cell.min()
            if cell.max() >= 2**21:
                raise LabkitError(
                    f"voxel size {size:g} m is too small for the cloud's extent (over 2 million voxels per axis)"
                )
        key |= cell << (21 * (2 - a))
    return key


def auto_sample(points, geometry, m, rng):
    """About ``m`` source points spread evenly in space and over the normal directions (sample='auto').

    1. The voxel edge h that leaves about 2 m occupied voxels: the count at a trial edge on a random
       subset, scaled with the surface law count ~ h^-2 (two rounds); one random point per voxel of
       the whole cloud (dense strip overlaps and the scanner's near range count no more than sparse
       parts). 2. Normal-space balance (Rusinkiewicz & Levoy 2001) from these 2 m candidates to m:
       every normal direction keeps its points up to an equal quota, so that walls and slopes, which
       determine the horizontal shift, are not thinned as much as the ground.
    The shift's covariance stays honest: the cluster-robust block covariance (eq. 5.13) takes its
    variance from the residuals of the pairs actually used, whatever their number.
    """
    n = len(points)
    sub = rows(points, rng.choice(n, min(n, 1_000_000), replace=False)) if n > 1_000_000 else points
    lo, hi = extent(points)
    ext = np.sort(hi - lo)[::-1]
    h = max(float(np.sqrt(ext[0] * max(ext[1], 1e-9) / (2 * m))), 1e-6)  # a horizontal surface's guess
    for _ in range(2):  # the subset has >= 2 points per voxel at this size: nearly all voxels occupied
        h *= float(np.sqrt(max(_n_distinct(voxel_keys(sub, h)), 1) / (2 * m)))
    pool = voxel_sample(points, h, rng)
    if len(pool) <= m:
        return pool
    coarse, _, variation = geometry.compute(pool, min(10, geometry.k))  # coarse normals suffice for the bins
    # rough points (vegetation) have random normals and would fill the rare bins: planar candidates only
    planar = np.isfinite(coarse[:, 0]) & (variation < MAX_VARIATION)
    if planar.sum() >= m:
        pool, coarse = pool[planar], coarse[planar]
    coarse = np.where(np.isfinite(coarse[:, :1]), coarse, [0.0, 0.0, 1.0])
    return pool[normal_space_sample(coarse, m, rng)]


def _n_distinct(keys):
    """Number of distinct values, by a sort (``len(np.unique(keys))`` hashes in numpy 2.x: 0.46 s
    against 9 ms on 523,000 distinct int64 keys)."""
    if len(keys) == 0:
        return 0
    s = np.sort(keys)
    return int(np.count_nonzero(s[1:] != s[:-1])) + 1


def normal_space_sample(normals, m, rng, bins=8):
    """Rusinkiewicz & Levoy (2001): as even a share as possible for each normal-direction bin."""
    nrm = np.where(normals[:, 2:3] < 0, -normals, normals)  # orientation-free
    theta = np.arccos(np.clip(nrm[:, 2], 0, 1))  # polar angle 0..90 deg
    phi = np.arctan2(nrm[:, 1], nrm[:, 0]) % np.pi  # axial azimuth 0..180 deg
    key = np.minimum((theta / (np.pi / 2) * bins).astype(int), bins - 1) * 2 * bins
    key += np.minimum((phi / np.pi * 2 * bins).astype(int), 2 * bins - 1)
    key = np.where(theta < np.pi / (4 * bins), -1, key)  # all near-horizontal surfaces share one bin
    order = rng.permutation(len(key))
    order = order[np.argsort(key[order], kind="stable")]
    ks = key[order]
    starts = np.r_[0, np.flatnonzero(np.diff(ks)) + 1]
    sizes = np.diff(np.r_[starts, len(ks)])
    rank = np.arange(len(ks)) - np.repeat(starts, sizes)
    quota = _quota(sizes, m)
    return np.sort(order[rank < quota])


def _quota(sizes, m):
    """Largest per-bin quota q with sum(min(size, q)) <= m."""
    lo, hi = 0, int(sizes.max())
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if np.minimum(sizes, mid).sum() <= m else (lo, mid - 1)
    return max(lo, 1)
