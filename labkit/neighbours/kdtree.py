"""A compiled kd-tree for k-nearest-neighbour searches in 3D (private; used by features and matching).

Why not only ``scipy.spatial.cKDTree``: on the real TLS scan (523,000 points,
clustered density) its kNN query was 85-90 % of the time of
:func:`labkit.features.normals` and of the ICP's matching. This tree is built
for the two searches labkit makes all the time:

- the k nearest neighbours of every point of the cloud itself (local PCA), run
  directly on the points in leaf order, so that consecutive queries visit the
  same leaves while they are in cache, and
- the nearest target point of every source point within a distance (ICP).

Construction: the points are split recursively at the median of the widest
coordinate of each node's bounding box (balanced, depth ~ log2(n / leafsize)),
with one rule for ties: points with equal coordinates always go to the same
side (``< v`` left, ``>= v`` right). Exact duplicates therefore share a leaf,
where they are found in O(leafsize^2) and, on request, merged into one point
(a duplicate is not a second observation of the surface). Every node
keeps its bounding box; a query visits the nearer child first and skips every
node whose box is farther than the current k-th distance (Friedman, Bentley,
Finkel 1977, ACM TOMS 3(3): 209-226).

Distances are Euclidean in float64 on the caller's (reduced) coordinates (float32
was considered and left out: it would make neighbour sets differ from the exact ones
at near-ties); the neighbours come sorted by distance, ties in any order. numba is a
core dependency; without it the queries fall back to cKDTree (the build stays slow).

Design: the search runs leaf by leaf (:meth:`KDTree.knn_of_leaves`); the build reads
no node twice for its box (the children's boxes are taken while the points are moved)
and selects the median in place; local PCA sums each point's moments in the search
kernel (:meth:`KDTree.knn_moments_of_leaves`) instead of writing and gathering an
(n, k) index array. Timings against cKDTree and Open3D: benchmarks/bench_features.py.
"""

from __future__ import annotations

import numpy as np

from ..core.arrays import rows
from ..core.jit import compiled
from .eigh3 import HAVE_NUMBA
from .kdtree_build import _build_two, _duplicates, _threads, in_runs
from .kdtree_nn import _RUNS_PER_THREAD, nearest
from .moments import covariances, knn_moments


LEAFSIZE = 24  # measured on the real TLS scan: self-kNN (k = 20) 10-25 % faster than 8-16; k = 1 alike
_PER_THREAD = 4000  # queries per thread at least; below, one thread is faster than starting more


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def _insert(bd, bi, d2, i, k):  # pragma: no cover - compiled
    """Insert (d2, i) into the ascending list bd/bi of length k (the last entry drops out)."""
    j = k - 1
    while j > 0 and bd[j - 1] > d2:
        bd[j] = bd[j - 1]
        bi[j] = bi[j - 1]
        j -= 1
    bd[j] = d2
    bi[j] = i


@compiled
def _knn(X, nodes, box, depth, Q, k, bound2, idx, dist2):  # pragma: no cover - compiled
    """k nearest of every row of Q among X (leaf order), squared distance < bound2; sorted ascending.

    Missing neighbours (fewer than k within the bound) get index -1 (and distance bound2).
    Every stacked node carries a lower bound of its distance (its parent's box distance,
    or the distance to the split plane for the far child), so most pruned nodes are
    never loaded. (A warm start from the previous query's neighbours was measured and
    dropped: checking candidates against the list cost more than the tighter bound saved.)
    """
    stack = np.empty(2 * depth + 4, np.int64)
    lower = np.empty(2 * depth + 4)  # lower bound of the squared distance to each stacked node
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    biggest = 1
    for node in range(nodes.shape[0]):
        if nodes[node, 2] < 0:
            biggest = max(biggest, nodes[node, 1] - nodes[node, 0])
    dbuf = np.empty(biggest)  # squared distances of the query to the points of one leaf
    cand = np.empty(biggest + 1, np.int64)  # the points of one leaf nearer than the k-th
    for q in range(Q.shape[0]):
        qx, qy, qz = Q[q, 0], Q[q, 1], Q[q, 2]
        for j in range(k):
            bd[j] = bound2
            bi[j] = -1
        worst = bound2
        sp = 1
        stack[0] = 0
        lower[0] = 0.0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if lower[sp] >= worst:  # pruned by a split plane: the node's memory is not touched
                continue
            # squared distance from q to the node's box (without branches)
            g = _gap2(box[node, 0], box[node, 3], qx, qx) + _gap2(box[node, 1], box[node, 4], qy, qy)
            g += _gap2(box[node, 2], box[node, 5], qz, qz)
            if g >= worst:
                continue
            l = nodes[node, 2]
            if l < 0:
                s, e = nodes[node, 0], nodes[node, 1]
                for i in range(s, e):  # the distances first (no dependence between them: vector code)
                    dx, dy, dz = X[i, 0] - qx, X[i, 1] - qy, X[i, 2] - qz
                    dbuf[i - s] = dx * dx + dy * dy + dz * dz
                c = 0
                for i in range(s, e):  # the points nearer than the k-th, without branches
                    cand[c] = i
                    c += dbuf[i - s] < worst
                for j in range(c):  # then the list, in the order of the leaf (the same list as one by one)
                    i = cand[j]
                    d2 = dbuf[i - s]
                    if d2 < worst:
                        _insert(bd, bi, d2, i, k)
                        worst = bd[k - 1]
                continue
            # nearer child (the side of the split plane q lies on) last on the stack: visited first
            r = nodes[node, 3]
            d = int(box[node, 7])
            qd = qx if d == 0 else (qy if d == 1 else qz)
            cut = qd - box[node, 6]
            far = max(g, cut * cut)  # the far child lies beyond the split plane
            if cut < 0.0:
                near, other = l, r
            else:
                near, other = r, l
            if far < worst:
                stack[sp] = other
                lower[sp] = far
                sp += 1
            stack[sp] = near
            lower[sp] = g
            sp += 1
        for j in range(k):
            idx[q, j] = bi[j]
            dist2[q, j] = bd[j]


@compiled
def _knn_leaves(X, nodes, box, depth, leaves, k, idx, cen, C, moments, tie):  # pragma: no cover - compiled
    """k nearest tree points of every point of the given leaves (self-queries, leaf order).

    The points of one leaf are searched together: first among themselves, then the
    tree is walked ONCE for the whole leaf, pruning every node whose box is farther
    from the leaf's box than the largest current k-th distance of its points; at each
    visited leaf, a point scans it only if the leaf's box is nearer to it than its own
    k-th distance. Same neighbours as :func:`_knn` (sorted ascending, ties in any
    order); the walk from the root is no longer paid per point. Row ``pos - start`` of
    ``idx`` belongs to leaf-order position ``pos``, ``start`` the first leaf's start.

    With ``moments`` > 0, row ``pos - start`` of ``cen`` and ``C`` gets the centroid (eq. 1) and
    covariance (eq. 2, divided by ``moments``) of the point's ``moments`` nearest neighbours (at most k),
    summed while they are in cache, in the order and arithmetic of
    :func:`labkit.neighbours.moments.covariances` (the same numbers: both call
    :func:`~labkit.neighbours.moments.knn_moments`, which sums differences to the nearest neighbour, the point
    itself). The neighbours are written where ``idx`` has rows (an empty ``idx``: only the moments).

    Where ``tie`` has rows, row ``pos - start`` tells whether another point lies at exactly the k-th
    distance (the k nearest are then not unique): a candidate at the current k-th distance, or the one a
    nearer candidate pushes out when the k-th distance stays. Nodes and leaves at exactly the k-th
    distance are therefore visited (the same neighbours: what they hold is never nearer).
    """
    most = 1
    for t in range(len(leaves)):
        most = max(most, nodes[leaves[t], 1] - nodes[leaves[t], 0])
    bd = np.empty((most, k))
    bi = np.empty((most, k), np.int64)
    worst = np.empty(most)
    ties = np.zeros(most, np.bool_)
    stack = np.empty(2 * depth + 4, np.int64)
    lower = np.empty(2 * depth + 4)  # lower bound of the squared box-to-box distance of each stacked node
    biggest = 1
    for node in range(nodes.shape[0]):
        if nodes[node, 2] < 0:
            biggest = max(biggest, nodes[node, 1] - nodes[node, 0])
    dbuf = np.empty(biggest)  # squared distances of one query to the points of one leaf
    cand = np.empty(biggest + 1, np.int64)  # the points of one leaf within a query's k-th distance
    qx_, qy_, qz_, gaps = np.empty(most), np.empty(most), np.empty(most), np.empty(most)  # the leaf's points
    start = nodes[leaves[0], 0]
    for t in range(len(leaves)):
        leaf = leaves[t]
        a, b = nodes[leaf, 0], nodes[leaf, 1]
        m = b - a
        for qi in range(m):
            qx_[qi], qy_[qi], qz_[qi] = X[a + qi, 0], X[a + qi, 1], X[a + qi, 2]
        # 1. the leaf's own points: each one's place among them by (distance, position), counted
        # without branches; the k first of that order make the list (as inserting them one by one would)
        wmax = 0.0
        for qi in range(m):
            for j in range(k):
                bd[qi, j] = np.inf
                bi[qi, j] = -1
            qx, qy, qz = X[a + qi, 0], X[a + qi, 1], X[a + qi, 2]
            for i in range(a, b):  # the distances first (vector code)
                dx, dy, dz = X[i, 0] - qx, X[i, 1] - qy, X[i, 2] - qz
                dbuf[i - a] = dx * dx + dy * dy + dz * dz
            for i in range(m):
                di = dbuf[i]
                r = 0
                for j in range(i):
                    r += dbuf[j] <= di
                for j in range(i + 1, m):
                    r += dbuf[j] < di
                if r < k:
                    bd[qi, r] = di
                    bi[qi, r] = a + i
            w = bd[qi, k - 1]
            at_w = 0  # the leaf's points at the k-th distance that did not make the list: a tie
            for i in range(m):
                at_w += dbuf[i] == w
            for j in range(k):
                at_w -= bd[qi, j] == w
            ties[qi] = at_w > 0
            worst[qi] = w
            wmax = max(wmax, w)
        # 2. one walk for the leaf: nodes nearer to its box than the largest k-th distance
        lo0, lo1, lo2, hi0, hi1, hi2 = box[leaf, 0], box[leaf, 1], box[leaf, 2], box[leaf, 3], box[leaf, 4], box[leaf, 5]
        sp = 1
        stack[0] = 0
        lower[0] = 0.0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if lower[sp] > wmax or node == leaf:
                continue
            g = _gap2(box[node, 0], box[node, 3], lo0, hi0) + _gap2(box[node, 1], box[node, 4], lo1, hi1)
            g += _gap2(box[node, 2], box[node, 5], lo2, hi2)
            if g > wmax:
                continue
            child = nodes[node, 2]
            if child < 0:  # a leaf: scanned by the points whose k-th distance reaches its box
                s, e = nodes[node, 0], nodes[node, 1]
                wmax = 0.0
                lo0_, lo1_, lo2_ = box[node, 0], box[node, 1], box[node, 2]
                hi0_, hi1_, hi2_ = box[node, 3], box[node, 4], box[node, 5]
                for qi in range(m):  # the gaps of all the leaf's points to this leaf's box first (vector code)
                    gq = _gap2(lo0_, hi0_, qx_[qi], qx_[qi]) + _gap2(lo1_, hi1_, qy_[qi], qy_[qi])
                    gaps[qi] = gq + _gap2(lo2_, hi2_, qz_[qi], qz_[qi])
                for qi in range(m):
                    w = worst[qi]
                    qx, qy, qz = qx_[qi], qy_[qi], qz_[qi]
                    if gaps[qi] <= w:
                        for i in range(s, e):  # the distances first (no dependence between them: vector code)
                            dx, dy, dz = X[i, 0] - qx, X[i, 1] - qy, X[i, 2] - qz
                            dbuf[i - s] = dx * dx + dy * dy + dz * dz
                        c = 0
                        for i in range(s, e):  # the points within the k-th distance, without branches
                            cand[c] = i
                            c += dbuf[i - s] <= w
                        for j in range(c):  # then the list, in the same order as before
                            i = cand[j]
                            d2 = dbuf[i - s]
                            if d2 < w:
                                _insert(bd[qi], bi[qi], d2, i, k)
                                before, w = w, bd[qi, k - 1]
                                ties[qi] = w == before < np.inf  # the point pushed out lies at the new k-th distance
                            elif d2 == w:
                                ties[qi] = True
                        worst[qi] = w
                    wmax = max(wmax, w)
                continue
            # the child on the side of the leaf's centre first; the other beyond the split plane
            d = int(box[node, 7])
            v = box[node, 6]
            lo_d, hi_d = (lo0, hi0) if d == 0 else ((lo1, hi1) if d == 1 else (lo2, hi2))
            if lo_d + hi_d < 2.0 * v:
                near, other, cut = child, nodes[node, 3], v - hi_d
            else:
                near, other, cut = nodes[node, 3], child, lo_d - v
            far = max(g, cut * cut) if cut > 0.0 else g
            if far <= wmax:
                stack[sp] = other
                lower[sp] = far
                sp += 1
            stack[sp] = near
            lower[sp] = g
            sp += 1
        if idx.shape[0] > 0:
            for qi in range(m):
                for j in range(k):
                    idx[a + qi - start, j] = bi[qi, j]
        if tie.shape[0] > 0:
            for qi in range(m):
                tie[a + qi - start] = ties[qi]
        if moments > 0:
            x, y, z = X[:, 0], X[:, 1], X[:, 2]
            for qi in range(m):  # the shared kernel of labkit.neighbours.moments
                knn_moments(x, y, z, bi[qi], moments, cen, C, a + qi - start)


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def _gap2(lo, hi, a, b):  # pragma: no cover - compiled
    """Squared gap between the intervals [lo, hi] and [a, b] (0 where they overlap), without branches
    (at most one of lo - b and a - hi is positive; an empty box, lo = inf, is infinitely far)."""
    t = max(lo - b, a - hi, 0.0)
    return t * t


def unique_kept_neighbours(nb, keep, tie, clean):
    """clean[p]: point p and its k nearest ``nb[p]`` (leaf positions) are all ``keep`` and no other point
    lies at the k-th distance (``tie[p]`` False, :meth:`KDTree.knn_of_leaves`), so that the k nearest among
    the kept points are these and no others. Ranges of points on the cores."""
    n = nb.shape[0]
    threads = min(_threads(-1), max(1, n // _PER_THREAD))
    in_runs(lambda a, b: _unique_kept(nb, keep, tie, clean, a, b),
            np.linspace(0, n, _RUNS_PER_THREAD * threads + 1).astype(np.intp), threads)


def neighbour_rows(nb, pos, indices, new, clean, k, rows):
    """rows[r] = new[indices[nb[pos[r], :k]]] where clean[pos[r]] (a selection's rows of the neighbours),
    ranges of rows on the cores."""
    m = len(pos)
    threads = min(_threads(-1), max(1, m // _PER_THREAD))
    in_runs(lambda a, b: _neighbour_rows(nb, pos[a:b], indices, new, clean, k, rows[a:b]),
            np.linspace(0, m, _RUNS_PER_THREAD * threads + 1).astype(np.intp), threads)


@compiled
def _unique_kept(nb, keep, tie, clean, start, end):  # pragma: no cover - compiled
    """:func:`unique_kept_neighbours` at the points ``start..end-1``."""
    for p in range(start, end):
        ok = keep[p] and not tie[p]
        for c in range(nb.shape[1]):
            if not ok:
                break
            ok = keep[nb[p, c]]
        clean[p] = ok


@compiled
def _neighbour_rows(nb, pos, indices, new, clean, k, rows):  # pragma: no cover - compiled
    """:func:`neighbour_rows` in this thread."""
    for r in range(pos.shape[0]):
        p = pos[r]
        if clean[p]:
            for c in range(k):
                rows[r, c] = new[indices[nb[p, c]]]


@compiled
def _tighten(X, nodes, box):  # pragma: no cover - compiled
    """Boxes (lo, hi) tight about each node's points ``X[start:end]`` (empty: +inf, -inf) and every split
    value moved to the smallest coordinate of the right child's points (the largest of the left's where
    the right holds none): a node's children have larger ids than the node, so one backward pass."""
    for node in range(nodes.shape[0] - 1, -1, -1):
        left, right = nodes[node, 2], nodes[node, 3]
        if left < 0:
            for e in range(3):
                box[node, e], box[node, 3 + e] = np.inf, -np.inf
            for i in range(nodes[node, 0], nodes[node, 1]):
                for e in range(3):
                    box[node, e] = min(box[node, e], X[i, e])
                    box[node, 3 + e] = max(box[node, 3 + e], X[i, e])
            continue
        for e in range(3):
            box[node, e] = min(box[left, e], box[right, e])
            box[node, 3 + e] = max(box[left, 3 + e], box[right, 3 + e])
        d = int(box[node, 7])
        if nodes[right, 1] > nodes[right, 0]:
            box[node, 6] = box[right, d]
        elif nodes[left, 1] > nodes[left, 0]:
            box[node, 6] = box[left, 3 + d]


_NO_IDX, _NO_CEN, _NO_C = np.empty((0, 1), np.intp), np.empty((0, 3)), np.empty((0, 3, 3))  # unused outputs
_NO_TIE = np.empty(0, np.bool_)


class KDTree:
    """kd-tree over (n, 3) points; optionally with exact duplicates merged (private).

    Attributes
    ----------
    data : ndarray (m, 3)
        The (kept) points in leaf order, contiguous.
    indices : ndarray (m,)
        Input row of every leaf-order point (as ``cKDTree.indices``).
    n : int
        Number of points in the tree (after merging).
    representative : ndarray (n_input,)
        Leaf-order position of the kept copy of every input point (merge only; else None).
    n_duplicates : int
        Input points merged into an identical earlier point.
    """

    def __init__(self, points, leafsize: int = LEAFSIZE, merge_duplicates: bool = False):
        P = np.ascontiguousarray(points, dtype=np.float64)
        perm, nodes, box, depth, X = _build_two(P, int(leafsize))
        self._representative, self._identity, self.n_duplicates = None, False, 0
        if merge_duplicates:
            keep, first = _duplicates(X, nodes)
            self.n_duplicates = int(len(keep) - keep.sum())
            if self.n_duplicates:
                new = np.cumsum(keep) - 1  # new leaf-order position of every kept point
                rep_leaf = new[first]
                self._representative = np.empty(len(P), dtype=np.intp)
                self._representative[perm] = rep_leaf
                X, perm = X[keep], perm[keep]
                bounds = np.concatenate([[0], np.cumsum(keep)])
                nodes = nodes.copy()
                nodes[:, 0], nodes[:, 1] = bounds[nodes[:, 0]], bounds[nodes[:, 1]]
            else:  # every point is its own representative: the inverse permutation, made when first asked for
                self._identity = True
        self.data, self.indices = np.ascontiguousarray(X), perm.astype(np.intp, copy=False)
        self._nodes = (nodes, box, int(depth))
        self._leaves = None  # leaf node ids in leaf order (see leaf_bounds)
        self.n = len(X)

    def restricted(self, keep, points=None):
        """The tree of the input points where ``keep`` (bool per input point; equal for exact duplicates),
        numbered as the rows of ``points[keep]``, made from this tree's nodes without a new build.

        ``points`` (optional): the kept points (``keep.sum()``, 3) in the frame the new tree is to hold
        them in (e.g. another local origin); default: this tree's coordinates. The kept points stay in
        their leaves (leaf order), so a leaf may be empty; every node's box is made tight about its kept
        points and its split plane moved between its children's kept points (:func:`_tighten`). Every
        search answer is the same nearest point as a tree built anew, except between points at exactly
        the same distance, which that tree may order differently.
        """
        keep = np.asarray(keep, dtype=bool)
        rep = self.representative
        kept_rows = np.flatnonzero(keep)
        kl = keep[self.indices]  # per distinct point, in leaf order
        if rep is not None and not kl[rep[kept_rows]].all():
            raise ValueError("keep must be equal for exact duplicates")
        out = object.__new__(KDTree)
        row = np.cumsum(keep) - 1  # row among the kept points of every input row
        nodes, box, depth = self._nodes
        bounds = np.concatenate([[0], np.cumsum(kl)])
        nodes = nodes.copy()
        nodes[:, 0], nodes[:, 1] = bounds[nodes[:, 0]], bounds[nodes[:, 1]]
        out.indices = row[self.indices[kl]].astype(np.intp, copy=False)
        if points is None:
            out.data = np.ascontiguousarray(rows(self.data, kl))
        else:
            out.data = np.ascontiguousarray(rows(np.asarray(points, dtype=np.float64), out.indices))
        box = box.copy()
        _tighten(out.data, nodes, box)
        out.n = len(out.data)
        out.n_duplicates = int(len(kept_rows) - out.n)
        out._identity = out.n_duplicates == 0  # then made when first asked for (the inverse permutation)
        out._representative = None
        if not out._identity:
            pos = np.cumsum(kl) - 1  # new leaf-order position of every kept distinct point
            out._representative = pos[rep[kept_rows]].astype(np.intp, copy=False)
        out._nodes = (nodes, box, depth)
        out._leaves = None
        return out

    @property
    def representative(self):
        """Leaf-order position of the kept copy of every input point (merge only; else None)."""
        if self._representative is None and self._identity:
            rep = np.empty(len(self.indices), dtype=np.intp)
            rep[self.indices] = np.arange(len(self.indices))
            self._representative = rep
        return self._representative

    def query_leaf_positions(self, pos, k: int, workers: int = 1):
        """Leaf-order indices (m, k) of the k nearest tree points of the tree's own points ``pos``."""
        return self._run(self.data[pos], int(k), np.inf, _threads(workers))[1]

    @property
    def leaf_bounds(self) -> np.ndarray:
        """Leaf-order start of every non-empty leaf, then ``n``: leaf j holds positions bounds[j]:bounds[j+1]."""
        if self._leaves is None:
            nodes = self._nodes[0]
            leaves = np.flatnonzero((nodes[:, 2] < 0) & (nodes[:, 1] > nodes[:, 0]))
            self._leaves = leaves[np.argsort(nodes[leaves, 0], kind="stable")]
        return np.append(self._nodes[0][self._leaves, 0], self.n)

    def knn_of_leaves(self, a: int, b: int, k: int, workers: int = 1, moments: int = 0, ties: bool = False,
                      dtype=np.intp):
        """Leaf-order indices (b - a, k) of the k nearest tree points of the tree's points a..b-1.

        ``a`` and ``b`` must be leaf bounds (:attr:`leaf_bounds`); the points of a leaf are
        searched together (:func:`_knn_leaves`), sorted by distance like :meth:`query`.
        ``workers`` threads (-1: one per core) take consecutive runs of leaves (the same answer).
        ``moments`` (at most k) > 0: also the centroids (b - a, 3) and covariances (b - a, 3, 3) of each
        point's ``moments`` nearest, as :func:`labkit.neighbours.moments.covariances` gives them (the same
        numbers), summed while the neighbours are in cache: returns (indices, centroids, covariances).
        ``ties``: last also (b - a,) bool, True where another point lies at exactly the k-th distance (the
        k nearest are not unique; what the (k+1)-th neighbour would tell, without searching for it).
        ``dtype``: of the indices (np.int32 halves the memory of neighbourhoods kept for later, n < 2^31).
        """
        bounds = self.leaf_bounds
        j0, j1 = np.searchsorted(bounds, [a, b])
        if bounds[j0] != a or bounds[j1] != b:
            raise ValueError(f"{a}:{b} does not start and end at leaf bounds")
        idx = np.empty((b - a, k), dtype=dtype)
        moments = min(int(moments), k)
        cen, C = (np.empty((b - a, 3)), np.empty((b - a, 3, 3))) if moments > 0 else (_NO_CEN, _NO_C)
        tie = np.zeros(b - a, dtype=bool) if ties else _NO_TIE
        if b > a and not HAVE_NUMBA:  # pragma: no cover - depends on the environment
            more = min(k + int(ties), self.n)
            d2, nb = self._run(self.data[a:b], more, np.inf, 1)
            idx[:] = nb[:, :k]
            if more > k:
                tie[:] = d2[:, k] == d2[:, k - 1]
            if moments > 0:
                cen, C = covariances(self.data, None, idx[:, :moments], np.ascontiguousarray(self.data.T))
        elif b > a:
            threads = min(_threads(workers), max(1, (b - a) // _PER_THREAD))
            # runs of whole leaves, a few per thread, taken by whoever is free (see in_runs)
            cut = np.unique(np.linspace(j0, j1, _RUNS_PER_THREAD * threads + 1).astype(np.intp))

            def part(u, v):
                s, e = bounds[u] - a, bounds[v] - a
                _knn_leaves(self.data, *self._nodes, self._leaves[u:v], k, idx[s:e],
                            cen[s:e] if moments else cen, C[s:e] if moments else C, moments, tie[s:e] if ties else tie)

            in_runs(part, cut if threads > 1 else [j0, j1], threads)
        out = (idx,) + ((cen, C) if moments > 0 else ()) + ((tie,) if ties else ())
        return out if len(out) > 1 else idx

    def knn_moments_of_leaves(self, a: int, b: int, k: int):
        """Centroids (b - a, 3) and covariances (b - a, 3, 3) of the k nearest tree points of the
        tree's points a..b-1 (leaf bounds), as :meth:`knn_of_leaves` followed by
        :func:`labkit.neighbours.moments.covariances` (the same numbers), without the (b - a, k) index array:
        the moments are summed in the search kernel while the neighbours are in cache."""
        if not HAVE_NUMBA:  # pragma: no cover - depends on the environment
            return covariances(self.data, None, self.knn_of_leaves(a, b, k), np.ascontiguousarray(self.data.T))
        bounds = self.leaf_bounds
        j0, j1 = np.searchsorted(bounds, [a, b])
        if bounds[j0] != a or bounds[j1] != b:
            raise ValueError(f"{a}:{b} does not start and end at leaf bounds")
        cen, C = np.empty((b - a, 3)), np.empty((b - a, 3, 3))
        if b > a:
            _knn_leaves(self.data, *self._nodes, self._leaves[j0:j1], k, _NO_IDX, cen, C, k, _NO_TIE)
        return cen, C

    def nearest_in_groups(self, q, starts, distance_upper_bound: float = np.inf, workers: int = 1, warm=None,
                          memory=None):
        """As ``query(q, k=1, ...)`` (the same distances and indices, ties included), the rows
        ``starts[g]:starts[g + 1]`` of ``q`` searched together (:func:`labkit.neighbours.kdtree_nn.nearest`):
        fast when each group lies close together (e.g. the leaves of a tree over the queries).

        ``warm`` (optional, int array per row of ``q``): a leaf-order position to try first, or -1;
        overwritten with the leaf-order position of each row's nearest point (-1: none), the warm
        start of the next call (ICP's next iteration). ``memory`` (optional, with ``warm``): per row
        where it was last searched (m, 3) and the squared distance of its second nearest point from
        there (m,), zeros at first; rows that provably kept their nearest point are not searched
        (see :func:`~labkit.neighbours.kdtree_nn.nearest`). The answer is the same with or without them."""
        return nearest(self, q, starts, float(distance_upper_bound), _threads(workers), warm, memory)

    def query(self, q, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1):
        """Like ``cKDTree.query``: (distance, input index); k = 1 gives 1-D arrays.

        Missing neighbours (beyond ``distance_upper_bound``) have distance inf and index ``n``.
        """
        Q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, 3)
        d2, leaf = self._run(Q, int(k), float(distance_upper_bound), _threads(workers))
        found = leaf >= 0
        idx = np.where(found, self.indices[np.where(found, leaf, 0)], self.n)
        d = np.where(found, np.sqrt(d2), np.inf)
        return (d[:, 0], idx[:, 0]) if k == 1 else (d, idx)

    def _run(self, Q, k, bound, threads):
        bound2 = bound * bound if np.isfinite(bound) else np.inf
        idx = np.empty((len(Q), k), dtype=np.intp)
        d2 = np.empty((len(Q), k))
        if not HAVE_NUMBA:  # pragma: no cover - depends on the environment
            from scipy.spatial import cKDTree

            d, i = cKDTree(self.data).query(Q, k=k, distance_upper_bound=bound)
            d, i = d.reshape(len(Q), k), i.reshape(len(Q), k)
            return d * d, np.where(i < self.n, i, -1)
        # a query of k neighbours costs about k / 4 nearest-point queries (measured on the real TLS halves)
        threads = min(threads, max(1, len(Q) * max(1, k // 4) // _PER_THREAD))
        args = self._nodes
        if threads <= 1:
            _knn(self.data, *args, Q, k, bound2, idx, d2)
            return d2, idx
        bounds = np.linspace(0, len(Q), _RUNS_PER_THREAD * threads + 1).astype(int)
        in_runs(lambda a, b: _knn(self.data, *args, Q[a:b], k, bound2, idx[a:b], d2[a:b]), bounds, threads)
        return d2, idx
