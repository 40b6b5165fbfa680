"""Private steps of :func:`labkit.m3c2` (module labkit.change): core points, normals at core points, cylinder statistics.

All functions work on coordinates already reduced to a local origin and never
loop over core points in Python. With numba (a core dependency) the searches run
in the compiled voxel-grid kernels of ``labkit.change.grid``. The kd-tree route
below is the fallback and the independent check in the tests: a chunk of core points is searched at once
with ``cKDTree.query_ball_point`` (``return_sorted=False``), the ragged answer
is flattened with ``np.repeat`` and every per-core sum is a ``np.bincount``.

A long cylinder (half length h much larger than the radius r) is not searched
with one ball of radius sqrt(r^2 + h^2), which would return up to h / r times
more points than the cylinder holds. The axis is cut into m slabs of length
s = 2 h / m <= 2 r; slab j is searched with a ball of radius sqrt(r^2 + (s/2)^2)
around its centre and keeps only the points whose axial coordinate falls in
that slab, so every point is counted once without a de-duplication step.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from . import grid as grid_kernels
from .grid import VoxelGrid, ball_covariances
from ..neighbours.eigh3 import HAVE_NUMBA, eigh3

CORE_CHUNK = 20_000  # core points per search batch (bounds the flattened neighbour arrays)
CALL_CORES = 50_000  # core points per compiled call: Python runs between calls, so Ctrl-C stops a long search
COLUMNS = 32  # a cylinder's bounding box spans at most about 2 * COLUMNS + 2 voxels per axis (cylinder_cell)


def cylinder_cell(radius: float, depth: float) -> float:
    """Voxel edge for the cylinder search: the smaller of radius and depth, but at least (radius + depth) / COLUMNS.

    A thin long cylinder (radius far below its depth) in voxels of its radius would visit
    (depth / radius)^2 voxel columns per core point: 10^18 for 1e-9 m in 1 m. The floor bounds
    that to about (2 COLUMNS + 2)^2 columns, each found by one binary search.
    """
    return max(min(radius, depth), (radius + depth) / COLUMNS)


# --------------------------------------------------------------------------- core points
# --------------------------------------------------------------------------- public steps
def pca_normals(local: np.ndarray, cores: np.ndarray, radius: float, *, use_numba: bool = HAVE_NUMBA):
    """Normal and surface variation l3 / (l1 + l2 + l3) at each core from the points within ``radius``.

    ``use_numba``: the numba voxel-grid kernel (``labkit.change.grid``); otherwise cKDTree ball queries.
    Fewer than 3 neighbours, or a line-like neighbourhood, give NaN.
    """
    if not use_numba:
        return _tree_pca_normals(cKDTree(local), local, cores, radius)
    grid = VoxelGrid(local, radius)
    counts, C = np.zeros(len(cores), dtype=np.int64), np.zeros((len(cores), 3, 3))
    for start in range(0, len(cores), CALL_CORES):  # one compiled call per slice: Ctrl-C stops in between
        rows = slice(start, start + CALL_CORES)
        counts[rows], C[rows] = ball_covariances(grid, cores[rows], radius)
    return _normals_from_covariances(counts, C)


def cylinder_stats(local: np.ndarray, cores: np.ndarray, normals: np.ndarray, radius: float, depth: float,
                   progress=None, *, use_numba: bool = HAVE_NUMBA):
    """Count, mean and standard deviation (ddof = 1) of the axial coordinates in each cylinder.

    A point p belongs to the cylinder of core c with unit axis n when its axial
    coordinate d = (p - c) . n satisfies |d| <= depth and its squared distance from
    the axis |p - c|^2 - d^2 is at most radius^2. Cores with a NaN normal get count 0.
    """
    if not use_numba:
        return _tree_cylinder_stats(cKDTree(local), local, cores, normals, radius, depth, progress)
    grid = grid_kernels.VoxelGrid(local, cylinder_cell(radius, depth))
    out = [np.zeros(len(cores), dtype=np.int64), np.full(len(cores), np.nan), np.full(len(cores), np.nan)]
    for start in range(0, len(cores), CALL_CORES):  # one compiled call per slice: Ctrl-C stops in between
        rows = slice(start, start + CALL_CORES)
        for arr, part in zip(out, grid_kernels.cylinder_stats(grid, cores[rows], normals[rows], radius, depth)):
            arr[rows] = part
        if progress is not None:
            progress(len(cores[rows]))
    return tuple(out)


def _normals_from_covariances(counts, C):
    C = np.where((counts >= 3)[:, None, None], C, np.nan)
    lam, V = eigh3(C)  # ascending
    ok = (counts >= 3) & (lam[:, 1] > 1e-12 * np.maximum(lam[:, 2], 1e-300))
    with np.errstate(invalid="ignore", divide="ignore"):
        variation = np.where(ok, np.clip(lam[:, 0], 0, None) / lam.sum(axis=1), np.nan)
    return np.where(ok[:, None], V[:, :, 0], np.nan), variation


# --------------------------------------------------------------------------- kd-tree route (without numba)
def _tree_pca_normals(tree: cKDTree, local: np.ndarray, cores: np.ndarray, radius: float):
    """:func:`pca_normals` with kd-tree ball queries (no numba)."""
    normals = np.full((len(cores), 3), np.nan)
    variation = np.full(len(cores), np.nan)
    for start in range(0, len(cores), CORE_CHUNK):
        rows = slice(start, start + CORE_CHUNK)
        seg, flat = _flat_ball(tree, cores[rows], radius)
        n = len(cores[rows])
        counts = np.bincount(seg, minlength=n)
        m = np.maximum(counts, 1)
        X = local[flat]
        cen = np.stack([np.bincount(seg, X[:, a], n) for a in range(3)], axis=1) / m[:, None]  # centroid
        D = X - cen[seg]
        C = np.empty((n, 3, 3))
        for a in range(3):
            for b in range(a, 3):
                C[:, a, b] = C[:, b, a] = np.bincount(seg, D[:, a] * D[:, b], n) / m  # covariance
        normals[rows], variation[rows] = _normals_from_covariances(counts, C)
    return normals, variation


def orient(normals: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Flip each normal so that n . direction >= 0 (a new array)."""
    flip = normals @ direction < 0
    return np.where(flip[:, None], -normals, normals)


def _tree_cylinder_stats(tree: cKDTree, local: np.ndarray, cores: np.ndarray, normals: np.ndarray, radius: float,
                         depth: float, progress=None):
    """:func:`cylinder_stats` with kd-tree ball queries, flattened (no numba)."""
    n = len(cores)
    count, mean, std = np.zeros(n, dtype=np.int64), np.full(n, np.nan), np.full(n, np.nan)
    slabs = max(1, int(np.ceil(depth / radius - 1e-9)))  # slab length 2 depth / slabs <= 2 radius
    half = depth / slabs
    ball = np.sqrt(radius**2 + half**2) * (1 + 1e-9) + 1e-12
    good = np.flatnonzero(np.isfinite(normals).all(axis=1))
    for start in range(0, len(good), CORE_CHUNK):
        rows = good[start:start + CORE_CHUNK]
        c, nrm = cores[rows], normals[rows]
        segs, ds = [], []
        for j in range(slabs):
            lo = -depth + 2 * half * j  # slab [lo, lo + 2 half), the last one closed at +depth
            seg, flat = _flat_ball(tree, c + (lo + half) * nrm, ball)
            D = local[flat] - c[seg]
            d = np.einsum("kd,kd->k", D, nrm[seg])  # axial coordinate
            r2 = np.einsum("kd,kd->k", D, D) - d * d  # squared distance from the axis
            upper = d <= depth if j == slabs - 1 else d < lo + 2 * half
            keep = (r2 <= radius**2) & (d >= lo) & upper & (np.abs(d) <= depth)
            segs.append(seg[keep])
            ds.append(d[keep])
        seg, d = np.concatenate(segs), np.concatenate(ds)
        k = np.bincount(seg, minlength=len(rows))
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = np.bincount(seg, d, len(rows)) / k  # mean of the axial coordinates
            dev = d - mu[seg]
            var = np.bincount(seg, dev * dev, len(rows)) / (k - 1)  # two-pass, ddof = 1
        count[rows], mean[rows] = k, np.where(k > 0, mu, np.nan)
        std[rows] = np.where(k > 1, np.sqrt(np.clip(var, 0, None)), np.nan)
        if progress is not None:
            progress(len(rows))
    return count, mean, std


def _flat_ball(tree: cKDTree, centres: np.ndarray, radius: float):
    """(segment id, point index) of every point within ``radius`` of each centre, flattened."""
    lists = tree.query_ball_point(centres, radius, workers=-1, return_sorted=False)
    counts = np.fromiter(map(len, lists), dtype=np.intp, count=len(lists))
    flat = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.intp, count=int(counts.sum()))
    return np.repeat(np.arange(len(centres)), counts), flat
