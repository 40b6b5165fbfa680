"""Minimal samples of four points: uniform, or local around a first point (tiny spheres in large scenes)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import LabkitError
from .config import S
from .hypotheses import score_hypotheses
from .iterations import required_for_ratio, required_from_probability


def working_set(n, size, gen):
    """Indices of the random reduction used for sampling and scoring (the exercise sheet: 1000 points)."""
    return np.arange(n) if size >= n else np.sort(gen.choice(n, size=size, replace=False))


def pick_sampling(sampling, known, r_max, extent):
    if sampling == "local" and not known:
        raise LabkitError("sampling='local' needs radius_range or nominal_radius (the neighbourhood is r_max + t)")
    if sampling == "auto":
        return "local" if known and extent > 10.0 * r_max else "uniform"
    return sampling


def mean_neighbourhood_share(W, radius):
    """Mean share of the working set within ``radius`` of a point (counted in C, no lists)."""
    counts = cKDTree(W).query_ball_point(W, radius, return_length=True)
    return float(counts.mean()) / len(W)


class UniformSampler:
    """Four points drawn uniformly; N follows eq. (27) with eps = 1 - k/m."""

    def __init__(self, m):
        self.m = m

    def draw(self, gen, size):
        # rows with a repeated index are degenerate and do not count
        return gen.integers(0, self.m, size=(size, S))

    def required(self, inlier_mask, p):
        return required_for_ratio(1.0 - np.count_nonzero(inlier_mask) / self.m, p)


class LocalSampler:
    """A uniform first point and three distinct points within ``radius`` of it.

    The probability that a sample is outlier-free becomes
    ``w = (1/m') sum_{i in I} C(k_i, 3) / C(d_i, 3)``: the first point must be an
    inlier and the other three inliers of its neighbourhood, where d_i is the
    neighbourhood size (without i), k_i the inliers in it and m' the number of
    points with d_i >= 3 (the only admissible first points). N then follows
    eq. (27) with (1 - eps)^4 replaced by w.
    """

    def __init__(self, W, radius):
        # all pairs closer than radius as one integer array (no per-point Python lists), both directions,
        # grouped by their first point: the neighbours of i are flat[offsets[i]:offsets[i + 1]]
        pairs = cKDTree(W).query_pairs(radius, output_type="ndarray").astype(np.int64)
        owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
        other = np.concatenate([pairs[:, 1], pairs[:, 0]])
        key = owner.astype(np.int16) if len(W) < 2**15 else owner  # 16-bit keys: numpy's stable sort is a radix sort
        order = np.argsort(key, kind="stable")
        self.flat = other[order]
        self.deg = np.bincount(owner, minlength=len(W))
        self.offsets = np.concatenate([[0], np.cumsum(self.deg)])
        self.first = np.flatnonzero(self.deg >= 3)
        self._W, self.radius, self._blocks = W, radius, None

    @property
    def blocks(self):
        if self._blocks is None:
            self._blocks = _Blocks(self._W, self.radius)
        return self._blocks

    def draw(self, gen, size):
        if self.first.size == 0:
            return np.zeros((size, S), dtype=np.int64)  # all duplicates: degenerate
        i = self.first[gen.integers(0, self.first.size, size)]
        d = self.deg[i]
        u = gen.random((size, 3))
        a = (u[:, 0] * d).astype(np.int64)  # three distinct positions in 0..d-1
        b = (u[:, 1] * (d - 1)).astype(np.int64)
        c = (u[:, 2] * (d - 2)).astype(np.int64)
        b += b >= a
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        c += c >= lo
        c += c >= hi
        base = self.offsets[i]
        return np.column_stack([i, self.flat[base + a], self.flat[base + b], self.flat[base + c]])

    def required(self, inlier_mask, p):
        cum = np.concatenate([[0], np.cumsum(inlier_mask[self.flat])])
        k = (cum[self.offsets[1:]] - cum[self.offsets[:-1]]).astype(np.float64)
        d = self.deg.astype(np.float64)
        ok = inlier_mask & (self.deg >= 3)
        share = k[ok] * (k[ok] - 1) * (k[ok] - 2) / (d[ok] * (d[ok] - 1) * (d[ok] - 2))
        w = share.sum() / max(self.first.size, 1)
        return required_from_probability(w, p)


class _Blocks:
    """Grid of the working set for scoring local hypotheses on the points that can be their inliers.

    A local hypothesis passes through its first point f and three points within
    rho = LOCAL_REACH r_max + t of f; for r <= r_max every point with |d| < t
    lies within 2 (r_max + t) of f. With grid cells of that size, those points
    are in the 3 x 3 x 3 cells around f's cell: scoring there gives exactly the
    scores over the whole working set, at a fraction of the cost.
    """

    def __init__(self, W, radius):
        self.W = W
        self.size = 2.0 * radius + 1e-9  # >= 2 (r_max + t) as LOCAL_REACH <= 1
        cells = np.floor(W / self.size).astype(np.int64)
        self.cells = cells
        keys, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.ravel()
        order = np.argsort(inv, kind="stable")
        bounds = np.searchsorted(inv[order], np.arange(len(keys) + 1))
        self._members = {tuple(k): order[bounds[j]:bounds[j + 1]] for j, k in enumerate(keys)}
        self._block_cache = {}
        self._offsets = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])

    def _block(self, cell):
        key = tuple(cell)
        if key not in self._block_cache:
            parts = [self._members.get(tuple(c)) for c in cell + self._offsets]
            self._block_cache[key] = np.concatenate([q for q in parts if q is not None])
        return self._block_cache[key]

    def score(self, W, Wsq, X, first, cfg):
        """Scores of hypotheses X (B, 4) with first points ``first`` (B,), equal to score_hypotheses on all of W."""
        scores = np.empty(len(X))
        cell_ids, inv = np.unique(self.cells[first], axis=0, return_inverse=True)
        inv = inv.ravel()
        for j, cell in enumerate(cell_ids):  # a loop over grid cells, not over points
            sel = np.flatnonzero(inv == j)
            pts = self._block(cell)
            scores[sel] = score_hypotheses(W[pts], Wsq[pts], X[sel], cfg.threshold, cfg.scoring)[0]
        return scores
