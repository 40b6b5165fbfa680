"""Neighbourhood engine: kd-tree, k-nearest and radius neighbours, chunked covariances (notebook 04).

Every local-geometry step in labkit (PCA normals and features, the ICP's target
planes, the consensus' local planes) starts the same way: find the neighbours of
each point, reduce them to their centroid and sum their outer products,

- (eq. 1) centroid   p_bar = 1/m sum_j p_j
- (eq. 2) covariance C = 1/m sum_j (p_j - p_bar)(p_j - p_bar)^T

This module does that part once, for all of them: a :class:`SearchPlan` holds the
compiled kd-tree (``labkit.neighbours.kdtree``; exact duplicates merged on request)
and the output rows, :func:`run_chunks` walks the query points chunk by chunk in
the tree's leaf order on one thread per core, and :func:`covariances` evaluates
eq. 1-2 per chunk. What the rows mean (normals, features) is left to the caller,
see :mod:`labkit.features`.

Speed. The ORDER of the queries matters most: asking in the tree's own leaf
order keeps the visited leaves in cache (earlier measurement with cKDTree at
10^6 points: 5.4-6.2 s down to 1.7-2.6 s). When every point of the cloud is a
query (the usual local PCA), whole leaves are searched together
(:meth:`labkit.neighbours.kdtree.KDTree.knn_of_leaves`): the tree is walked once per leaf
instead of once per point, and for local PCA (:func:`run_moment_chunks`) the centroid and
covariance of each neighbourhood are summed in the search kernel itself, while the
neighbours are in cache, so no (n, k) neighbour array is written and gathered again.

References
----------
Friedman, Bentley, Finkel (1977): An algorithm for finding best matches in
logarithmic expected time. ACM TOMS 3(3), 209-226.
"""

from __future__ import annotations

import itertools
import numbers
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.checks import as_points, as_rng, positive
from .eigh3 import HAVE_NUMBA
from ..core.frame import local_origin, reduce
from .kdtree import KDTree
from .moments import covariances, masked_covariances
from ..core.report import ReportMixin, fmt
from ..core.errors import LabkitError
from ..core.threads import cores


__all__ = [
    "CHUNK_SIZE", "LEAFSIZE", "Neighbourhoods", "SearchPlan", "check_chunk_size", "check_scale",
    "neighbourhoods", "reduced", "run_chunks", "run_moment_chunks", "scale_text",
]  # fmt: skip

CHUNK_SIZE = 20_000  # points per chunk (measured: 25 % less CPU than 100k, whose 50 MB temporaries
#                      always come from fresh mmap pages; about 10 MB of temporaries per chunk at k = 20)
LEAFSIZE = 16  # cKDTree of the radius searches


# --------------------------------------------------------------------------- neighbourhoods


@dataclass(frozen=True, eq=False, repr=False)
class Neighbourhoods(ReportMixin):
    """Neighbour indices of every point in compressed rows: point i owns ``indices[offsets[i]:offsets[i+1]]``.

    kNN neighbourhoods include the point itself and are sorted by distance.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.neighbours.search import neighbourhoods
    >>> pts = np.random.default_rng(0).uniform(0, 1, (200, 3))
    >>> nb = neighbourhoods(pts, radius=0.2)  # ragged rows: point i owns indices[offsets[i]:offsets[i + 1]]
    >>> len(nb), bool((nb.counts == np.diff(nb.offsets)).all()), 0 in nb[0]
    (200, True, True)
    >>> neighbourhoods(pts, k=6).dense().shape  # kNN rows all have k entries
    (200, 6)
    """

    indices: np.ndarray
    offsets: np.ndarray
    k: int | None
    radius: float | None

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __repr__(self) -> str:
        return f"Neighbourhoods({len(self)} points, {scale_text(self.k, self.radius)})"

    def __getitem__(self, i: int) -> np.ndarray:
        return self.indices[self.offsets[i] : self.offsets[i + 1]]

    @property
    def counts(self) -> np.ndarray:
        """Number of neighbours m of every point, shape (n,)."""
        return np.diff(self.offsets)

    def dense(self) -> np.ndarray:
        """Indices as an (n, m) array; only when every point has the same m (always for kNN)."""
        counts = self.counts
        if len(counts) and (counts != counts[0]).any():
            raise LabkitError("radius neighbourhoods have different sizes; use indices/offsets")
        return self.indices.reshape(len(self), -1)

    def _report(self):
        c = self.counts
        rows = [("points", str(len(self))), ("search", scale_text(self.k, self.radius))]
        if len(c):
            rows.append(("neighbours min / median / max", f"{c.min()} / {np.median(c):.0f} / {c.max()}"))
        return "Neighbourhoods", [("", rows)]


def neighbourhoods(points, k: int | None = None, radius: float | None = None, *, chunk_size: int = CHUNK_SIZE):
    """The k nearest neighbours (including the point) or all points within ``radius`` of every point.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
    k : int, optional
        Number of neighbours including the point itself, 3 <= k <= n.
    radius : float, optional
        Search radius in metres (3D ball). Give exactly one of ``k`` and ``radius``.

    Returns
    -------
    Neighbourhoods

    References
    ----------
    .. [1] Notebook 04, section 1; the registration study, step 4 (a kd-tree of the cloud and the nearest
       neighbours of each point).
    .. [2] J. H. Friedman, J. L. Bentley, R. A. Finkel (1977): An algorithm for finding best matches
       in logarithmic expected time. ACM Transactions on Mathematical Software 3(3), 209-226,
       doi:10.1145/355744.355745.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.spatial import cKDTree
    >>> pts = np.random.default_rng(0).uniform(0, 1, (200, 3))
    >>> nb = neighbourhoods(pts, k=5)
    >>> nb.dense().shape, int(nb[7][0])  # the point itself comes first
    ((200, 5), 7)
    >>> bool((nb.dense() == cKDTree(pts).query(pts, 5)[1]).all())  # the same as scipy's kd-tree
    True
    """
    local, _ = reduced(points)
    k, radius = check_scale(k, radius, len(local))
    found = []  # (rows, counts, flat) per chunk, in any order
    plan = SearchPlan(local, merge=False)  # indices of the input points, duplicates included
    to_input = plan.tree.indices  # leaf position -> input row

    def work(rows, per_scale, _):
        counts, flat = per_scale[0]
        found.append((rows, counts, to_input[flat.reshape(-1)]))

    run_chunks(plan, [(k, radius)], check_chunk_size(chunk_size), work)
    rows, counts_leaf, flat = (np.concatenate(parts) for parts in zip(*found))
    # move every point's block from leaf order to input order
    counts = np.empty_like(counts_leaf)
    counts[rows] = counts_leaf
    offsets = np.concatenate([[0], np.cumsum(counts)])
    src_start = np.concatenate([[0], np.cumsum(counts_leaf)[:-1]])
    inv = np.empty_like(rows)
    inv[rows] = np.arange(len(rows))
    shift = src_start[inv] - offsets[:-1]  # per input point: source block start - target start
    indices = flat[np.arange(offsets[-1]) + np.repeat(shift, counts)]
    return Neighbourhoods(indices, offsets, k, radius)


# --------------------------------------------------------------------------- checks


def scale_text(k, radius) -> str:
    """The neighbourhood size as text for reports: ``k = <k>`` or ``radius = <r> m``.

    Examples
    --------
    >>> scale_text(20, None), scale_text(None, 0.25)
    ('k = 20', 'radius = 0.250 m')
    """
    if k is not None:
        return f"k = {k}"
    return f"radius = {fmt(radius, 3, 'm')}" if radius is not None else "k or radius per point (multi-scale)"


def reduced(points):
    """Checked points (n, 3) moved to a local origin near their centre, and that origin.

    Returns
    -------
    local : ndarray (n, 3)
        ``points - origin``: small numbers, so that covariances of UTM coordinates keep their digits.
    origin : ndarray (3,)

    Examples
    --------
    >>> import numpy as np
    >>> utm = np.random.default_rng(0).uniform(0, 10, (100, 3)) + [500000.0, 5400000.0, 100.0]
    >>> local, origin = reduced(utm)
    >>> bool(np.abs(local).max() < 20), bool(np.allclose(local + origin, utm))
    (True, True)
    """
    xyz = as_points(points, min_points=3)
    origin = local_origin(xyz)
    return reduce(xyz, origin), origin


def check_scale(k, radius, n):
    """``(k, None)`` or ``(None, radius)`` after checking them against n points; a radius wins over k.

    Raises
    ------
    LabkitError
        Neither given, k not an integer or outside 3..n, radius <= 0.

    Examples
    --------
    >>> check_scale(20, None, 100), check_scale(None, 0.5, 100)
    ((20, None), (None, 0.5))
    >>> check_scale(200, None, 100)
    Traceback (most recent call last):
    ...
    labkit.core.errors.LabkitError: k must be between 3 and the number of points (100), got 200
    """
    if radius is not None:
        return None, positive(radius, "radius")
    if k is None:
        raise LabkitError("give k (number of neighbours) or radius")
    if isinstance(k, bool) or not isinstance(k, numbers.Integral):
        raise LabkitError(f"k must be an integer, got {k!r}")
    if not 3 <= k <= n:
        raise LabkitError(f"k must be between 3 and the number of points ({n}), got {k}")
    return int(k), None




def check_chunk_size(chunk_size) -> int:
    """``chunk_size`` as an int; LabkitError unless it is a positive integer.

    Examples
    --------
    >>> check_chunk_size(5000)
    5000
    >>> check_chunk_size(0)
    Traceback (most recent call last):
    ...
    labkit.core.errors.LabkitError: chunk_size must be a positive integer, got 0
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, numbers.Integral) or chunk_size < 1:
        raise LabkitError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    return int(chunk_size)



# --------------------------------------------------------------------------- search plan and chunks


class SearchPlan:
    """Where the PCA runs: the kd-tree (exact duplicates merged or not) and the output rows (private).

    Without ``at`` the queries are the tree's (distinct) points in leaf order and every
    chunk writes the input rows of its points (``tree.indices``); :meth:`out` then copies
    the result of each kept point to the duplicates merged into it. With ``at`` the
    queries are the requested points in leaf order and the output rows their positions
    in ``at``.

    Examples
    --------
    >>> import numpy as np
    >>> pts = np.random.default_rng(0).uniform(0, 1, (100, 3))
    >>> pts[1] = pts[0]  # an exact duplicate
    >>> plan = SearchPlan(pts)  # merge=True: the copy is searched once
    >>> plan.n_duplicates, plan.n_out, len(plan.points)
    (1, 100, 99)
    """

    def __init__(self, local, at=None, merge=True):
        self.tree = KDTree(local, merge_duplicates=merge)
        self.points = self.tree.data  # neighbour indices refer to these (leaf order)
        self.copies = None
        if at is None:
            self.n_out, self.n_query = len(local), self.tree.n
            self.query_pos, self.order = None, None
            if self.tree.n_duplicates:
                rep = self.tree.representative  # leaf position of the kept copy of every input point
                kept = self.tree.indices[rep]
                dup = np.flatnonzero(kept != np.arange(len(local)))
                self.copies = (dup, kept[dup])
        else:
            rep = self.tree.representative
            if rep is None:
                rep = np.empty(len(local), dtype=np.intp)
                rep[self.tree.indices] = np.arange(len(local))
            self.n_out = self.n_query = len(at)
            self.query_pos = rep[at]  # leaf position of every requested point
            self.order = np.argsort(self.query_pos, kind="stable")  # positions in ``at``, in leaf order

    @property
    def n_duplicates(self) -> int:
        return self.tree.n_duplicates

    def out(self, values):
        """Per input point (or per ``at`` entry): merged copies get the result of their kept point."""
        if self.copies is not None:
            dup, kept = self.copies
            values[dup] = values[kept]
        return values


def run_chunks(plan, scales, chunk_size, work, rng=None, step=None) -> None:
    """Call ``work(rows, per_scale, chunk_rng)`` for chunks of query points in the tree's leaf order.

    Parameters
    ----------
    plan : SearchPlan
        The tree and the output rows.
    scales : list of (k, radius)
        One entry per neighbourhood size: ``(k, None)`` for kNN, ``(None, r)`` for a ball.
    chunk_size : int
        Query points per chunk at most (memory grows with chunk_size * k).
    work : callable
        ``work(rows, per_scale, chunk_rng)``: ``rows`` index the output (see
        :class:`SearchPlan`); ``per_scale`` holds ``(counts, neighbours)`` for every
        scale, neighbours as leaf positions (rows of ``plan.points``): an (c, k) array
        for kNN, sorted by distance (one search with the largest k serves all k, since
        kNN neighbourhoods are nested), a flat array for a radius.
    rng : int or numpy.random.Generator, optional
        Each chunk gets its own child generator (reproducible for a given chunk_size,
        independent of thread timing); None gives ``chunk_rng = None``.
    step : callable, optional
        ``step(n)`` (a progress reporter) hears of every finished chunk, from the calling thread.

    Notes
    -----
    Chunks run in one thread per core; the kNN kernel, gathers, matmul and eigh release
    the GIL, and every chunk writes only its own rows. When every point is a query,
    the chunks end at leaf bounds and the points of one leaf are searched together.

    Examples
    --------
    >>> import numpy as np
    >>> pts = np.random.default_rng(0).normal(size=(500, 3))
    >>> plan = SearchPlan(pts)
    >>> seen = np.zeros(len(pts), bool)
    >>> def work(rows, per_scale, _):
    ...     seen[rows] = per_scale[0][1][:, 0] >= 0
    >>> run_chunks(plan, [(8, None)], 100, work)
    >>> bool(seen.all())
    True
    """
    threads = _n_threads()
    bounds = _chunk_bounds(plan, chunk_size, threads)
    rngs = as_rng(rng).spawn(len(bounds) - 1) if rng is not None else [None] * (len(bounds) - 1)
    ball = None
    if any(r is not None for _, r in scales):
        ball = cKDTree(plan.points, leafsize=LEAFSIZE, balanced_tree=False, compact_nodes=False)

    def job(i, rows, pos):
        work(rows, _query(plan, ball, pos, scales), rngs[i])

    _run_jobs(plan, bounds, threads, job, step)


def run_moment_chunks(plan, k, chunk_size, work, step=None) -> None:
    """Call ``work(rows, counts, centroids, covariances)`` (eq. 1-2) for the kNN neighbourhoods of the
    query points, chunk by chunk in the tree's leaf order (as :func:`run_chunks`).

    For local PCA, which needs only these moments: when every point is a query, the search kernel
    sums them while the neighbours are in cache (:meth:`labkit.neighbours.kdtree.KDTree.knn_moments_of_leaves`)
    and no (n, k) neighbour array is written or gathered again; the numbers are those of
    :func:`run_chunks` followed by :func:`covariances`.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0
    >>> cen, var_z = np.empty((len(floor), 3)), np.empty(len(floor))
    >>> def work(rows, counts, centroids, C):
    ...     cen[rows], var_z[rows] = centroids, C[:, 2, 2]
    >>> run_moment_chunks(SearchPlan(floor), 20, 50, work)
    >>> from scipy.spatial import cKDTree
    >>> nearest = floor[cKDTree(floor).query(floor, 20)[1]]  # (n, 20, 3), the same neighbourhoods
    >>> bool(np.allclose(cen, nearest.mean(axis=1))), bool(np.allclose(var_z, nearest[:, :, 2].var(axis=1)))
    (True, True)
    """
    tree = plan.tree
    k = min(int(k), tree.n)  # merged duplicates may leave fewer points than k
    threads = _n_threads()
    bounds = _chunk_bounds(plan, chunk_size, threads)
    cols = None if plan.order is None else np.ascontiguousarray(plan.points.T)

    def job(i, rows, pos):
        if isinstance(pos, slice):
            cen, C = tree.knn_moments_of_leaves(pos.start, pos.stop, k)
        else:
            cen, C = covariances(plan.points, None, tree.query_leaf_positions(pos, k), cols)
        work(rows, np.full(len(cen), k, dtype=np.intp), cen, C)

    _run_jobs(plan, bounds, threads, job, step)


def _n_threads():
    return cores()


def _run_jobs(plan, bounds, threads, job, step):
    """``job(i, rows, pos)`` for every chunk i (output rows, leaf positions), one thread per core."""

    def one(i):
        a, b = bounds[i], bounds[i + 1]
        if plan.order is None:  # the tree's own points a..b-1, whole leaves
            rows, pos = plan.tree.indices[a:b], slice(a, b)
        else:
            rows = plan.order[a:b]
            pos = plan.query_pos[rows]
        job(i, rows, pos)
        return b - a

    report = step if step is not None else (lambda n: None)
    if len(bounds) == 2 or plan.n_query == 0:
        report(one(0))
        return
    with ThreadPoolExecutor(threads) as pool:
        for n in pool.map(one, range(len(bounds) - 1)):  # in order; re-raises a failure of any chunk
            report(n)


def _chunk_bounds(plan, chunk_size, threads) -> np.ndarray:
    """Chunk bounds 0 = b_0 < ... < b_c = n_query: chunks of at most about chunk_size points, their
    number a multiple of the threads (5 chunks on 2 threads would leave one thread idle for a fifth
    of the time); for self-queries moved to the nearest leaf bound."""
    n_q = plan.n_query
    n_chunks = -(-n_q // max(1, chunk_size))
    n_chunks = max(1, -(-n_chunks // threads) * threads) if n_q >= threads else 1
    size = max(1, -(-n_q // n_chunks))
    bounds = np.append(np.arange(0, n_q, size), n_q)
    if plan.order is None:
        leaf = plan.tree.leaf_bounds
        j = np.clip(np.searchsorted(leaf, bounds), 1, len(leaf) - 1)
        nearer = np.where(bounds - leaf[j - 1] < leaf[j] - bounds, leaf[j - 1], leaf[j])
        bounds = np.unique(np.concatenate([[0], nearer[1:-1], [n_q]]))
    return bounds


def _query(plan, ball, pos, scales):
    """(counts, neighbours) of the query points at leaf positions ``pos`` for every (k, radius)."""
    tree = plan.tree
    ks = [k for k, r in scales if r is None]
    k_max = min(max(ks), tree.n) if ks else 0  # merged duplicates may leave fewer points than k
    q = plan.points[pos]
    idx = None
    if ks:
        if isinstance(pos, slice):  # whole leaves of the tree's own points
            idx = tree.knn_of_leaves(pos.start, pos.stop, k_max)
        else:
            idx = tree.query_leaf_positions(pos, k_max)
    out = []
    for k, r in scales:
        if r is None:
            k = min(k, tree.n)
            out.append((np.full(len(q), k, dtype=np.intp), idx[:, :k]))
            continue
        lists = ball.query_ball_point(q, r, return_sorted=False)
        counts = np.fromiter(map(len, lists), dtype=np.intp, count=len(lists))
        out.append((counts, np.fromiter(itertools.chain.from_iterable(lists), dtype=np.intp, count=int(counts.sum()))))
    return out
