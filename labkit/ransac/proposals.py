"""Where in a large scan can a sphere of a known size be? Candidate centres from normals (for find_spheres).

Three vectorized steps over the whole scan, no loop over points:

1. Flat cells out: the scan is cut into cubes of edge 2 r_max; a cube whose
   points lie within the threshold of their best plane (smallest eigenvalue
   of their covariance) holds no sphere and is dropped, unless it touches a
   cube that is not flat (so a cap cut by the grid stays whole).
2. Normals of the remaining points from their k nearest neighbours, turned
   towards the station when it is known.
3. Votes: each point votes for the centre c = p - r n (both signs without a
   station), the votes are counted in cubes of r/2, and a block of 3 x 3 x 3
   vote cubes is a candidate when it holds enough votes whose normals spread
   in every direction (the scatter matrix of the voters' normals has a third
   eigenvalue > 0): planes (one direction), edges and cylinders (normals in
   one plane) are left out; sphere caps (a two-dimensional spread) stay.

The candidates are only proposals: each is searched by RANSAC in its
neighbourhood and verified (:mod:`~labkit.ransac.verify`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

K_NORMALS = 12  # neighbours per normal
MIN_VOTES = 10  # votes a candidate block needs
MIN_SPREAD = 0.03  # smallest eigenvalue of the voters' normal scatter (plane, edge, cylinder: ~0; cap: ~0.1-0.2)
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])


@dataclass(frozen=True)
class Proposals:
    """Candidate centres (m, 3) ordered by votes, their votes, and the indices of the points kept (not flat)."""

    centers: np.ndarray
    votes: np.ndarray
    kept: np.ndarray


def sphere_proposals(X, r_min, r_max, t, station=None):
    """Candidate sphere centres in the (reduced) cloud X (n, 3), see the module docstring."""
    kept = np.flatnonzero(not_flat(X, 2.0 * r_max + 2.0 * t, t))
    if len(kept) < K_NORMALS:
        return Proposals(np.empty((0, 3)), np.empty(0, dtype=np.int64), kept)
    P = X[kept]
    n = _normals(P)
    if station is not None:  # towards the station: the centre lies behind the surface
        n *= np.where(np.einsum("ij,ij->i", station - P, n) < 0, -1.0, 1.0)[:, None]
        V, N = P - 0.5 * (r_min + r_max) * n, n
    else:
        r = 0.5 * (r_min + r_max)
        V, N = np.concatenate([P - r * n, P + r * n]), np.concatenate([n, -n])
    centers, votes = _vote(V, N, 0.25 * (r_min + r_max))
    return Proposals(centers, votes, kept)


def not_flat(X, h, t, min_points=8):
    """Points in cubes of edge h that are not flat, plus the points of the cubes next to one."""
    key, inv = _cells(X, h)
    m = len(key)
    cnt = np.bincount(inv, minlength=m).astype(np.float64)
    mean = np.column_stack([np.bincount(inv, X[:, a], m) for a in range(3)]) / cnt[:, None]
    Q = X - mean[inv]  # (centred per cube: no loss of digits)
    C = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            C[:, a, b] = C[:, b, a] = np.bincount(inv, Q[:, a] * Q[:, b], m) / cnt
    lam = np.linalg.eigvalsh(C)
    seed = (cnt >= min_points) & (np.sqrt(np.maximum(lam[:, 0], 0.0)) > 0.5 * t)
    grow = np.unique((key[seed][:, None, :] + _OFFSETS[None]).reshape(-1, 3), axis=0)
    return _member(key, grow)[inv]


def _cells(X, h):
    """Integer cube of each point: the distinct cubes (m, 3) and each point's index into them."""
    cube = np.floor(X / h).astype(np.int64)
    lo = cube.min(axis=0)
    span = cube.max(axis=0) - lo + 1
    cube -= lo
    packed = (cube[:, 0] * span[1] + cube[:, 1]) * span[2] + cube[:, 2]  # one int per cube (fast unique)
    _, first, inv = np.unique(packed, return_index=True, return_inverse=True)
    return cube[first] + lo, inv.ravel()


def _member(key, table):
    """For each row of key (m, 3): is it a row of table (rows unique)? Via one packed int per row."""
    lo = np.minimum(key.min(axis=0), table.min(axis=0)) if len(table) else key.min(axis=0)
    span = np.maximum(key.max(axis=0), table.max(axis=0) if len(table) else key.max(axis=0)) - lo + 1

    def pack(k):
        k = k - lo
        return (k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]

    return np.isin(pack(key), pack(table)) if len(table) else np.zeros(len(key), dtype=bool)


def _normals(P):
    """Unit normals of P (n, 3): smallest eigenvector of the k-neighbourhood covariance."""
    _, idx = cKDTree(P).query(P, k=K_NORMALS, workers=-1)
    Q = P[idx] - P[idx].mean(axis=1, keepdims=True)
    _, V = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q) / K_NORMALS)
    return V[:, :, 0].copy()


def _vote(V, N, b):
    """Count the votes V (m, 3) in cubes of edge b; blocks of 3 x 3 x 3 cubes with enough votes whose
    normals N spread in every direction, one per local maximum, ordered by votes."""
    key, inv = _cells(V, b)
    m = len(key)
    cnt = np.bincount(inv, minlength=m).astype(np.float64)
    S = np.column_stack([np.bincount(inv, N[:, a] * N[:, c], m) for a, c in
                         ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))])
    M = np.column_stack([np.bincount(inv, V[:, a], m) for a in range(3)])
    # sums over the 27 cubes around each cube (those that hold votes)
    order = _packed_order(key)
    block_cnt, block_S, block_M = np.zeros(m), np.zeros((m, 6)), np.zeros((m, 3))
    for off in _OFFSETS:
        j = order(key + off)
        hit = j >= 0
        block_cnt[hit] += cnt[j[hit]]
        block_S[hit] += S[j[hit]]
        block_M[hit] += M[j[hit]]
    # a local maximum of the block count (ties: the lower index) with enough votes
    peak = block_cnt >= MIN_VOTES
    for off in _OFFSETS:
        j = order(key + off)
        hit = j >= 0
        rival = np.zeros(m, dtype=bool)
        rival[hit] = (block_cnt[j[hit]] > block_cnt[hit]) | ((block_cnt[j[hit]] == block_cnt[hit]) & (j[hit] < np.flatnonzero(hit)))
        peak &= ~rival
    idx = np.flatnonzero(peak)
    s = block_S[idx] / block_cnt[idx, None]
    T = np.empty((len(idx), 3, 3))
    T[:, 0, 0], T[:, 1, 1], T[:, 2, 2] = s[:, 0], s[:, 1], s[:, 2]
    T[:, 0, 1] = T[:, 1, 0] = s[:, 3]
    T[:, 0, 2] = T[:, 2, 0] = s[:, 4]
    T[:, 1, 2] = T[:, 2, 1] = s[:, 5]
    lam = np.linalg.eigvalsh(T) if len(idx) else np.empty((0, 3))
    idx = idx[lam[:, 0] > MIN_SPREAD]
    idx = idx[np.argsort(-block_cnt[idx], kind="stable")]
    return block_M[idx] / block_cnt[idx, None], block_cnt[idx].astype(np.int64)


def _packed_order(key):
    """A lookup cube (q, 3) -> its row in key, -1 where absent (sorted packed keys, binary search)."""
    lo = key.min(axis=0) - 1
    span = key.max(axis=0) - lo + 2
    packed = ((key[:, 0] - lo[0]) * span[1] + (key[:, 1] - lo[1])) * span[2] + (key[:, 2] - lo[2])
    srt = np.argsort(packed)
    sp = packed[srt]

    def order(q):
        qq = ((q[:, 0] - lo[0]) * span[1] + (q[:, 1] - lo[1])) * span[2] + (q[:, 2] - lo[2])
        pos = np.clip(np.searchsorted(sp, qq), 0, len(sp) - 1)
        return np.where(sp[pos] == qq, srt[pos], -1)

    return order
