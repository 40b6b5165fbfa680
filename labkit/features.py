"""Local geometry of point clouds by PCA of neighbourhoods (seed 003, step 4).

(Provisional core: unit normals from the k nearest neighbours. The features
issue extends this module.)
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ._checks import as_points
from .errors import LabkitError


def normals(points, k: int = 20, *, orient: str = "up") -> np.ndarray:
    """Unit normals (n, 3): eigenvector of the smallest eigenvalue of each k-neighbourhood.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
    k : int
        Neighbours including the point itself (k >= 3).
    orient : {'up', 'none'}
        'up' flips normals to a non-negative z component (ALS convention).
    """
    xyz = as_points(points, min_points=3)
    if not 3 <= k <= len(xyz):
        raise LabkitError(f"k must be between 3 and the number of points ({len(xyz)}), got {k}")
    local = xyz - xyz.mean(axis=0)
    _, idx = cKDTree(local).query(local, k=k, workers=-1)
    nb = local[idx]  # (n, k, 3)
    nb -= nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb) / k
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    n = vecs[:, :, 0]
    if orient == "up":
        n = np.where(n[:, 2:3] < 0, -n, n)
    return n
