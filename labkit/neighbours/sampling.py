"""Sampling of the source for the matching: voxel, normal-space and the automatic thinning (private).

Step 1 of :func:`labkit.registration.match`; the choice between the methods (``sample=``) is made
by ``labkit.registration.matching.match._sample``.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import LabkitError

#: Normal-space sampling draws only from planar neighbourhoods: l3 / (l1 + l2 + l3) below this.
MAX_VARIATION = 0.02


def voxel_sample(points, size, rng):
    """One random point per cubic voxel of edge ``size``."""
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
    sub = points[rng.choice(n, min(n, 1_000_000), replace=False)] if n > 1_000_000 else points
    lo, hi = points.min(axis=0), points.max(axis=0)
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
