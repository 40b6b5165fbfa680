"""Nearest target point of every source point, the source searched leaf by leaf (private; ICP's matching).

ICP asks in every iteration for the nearest target point (within a gate) of every
moved source point. Queried one by one (:func:`labkit.neighbours.kdtree._knn` with k = 1), each
query walks the target tree from its root. Here the source points come in groups
(the leaves of the source's own kd-tree, about 24 points that lie close together):
the target tree is walked ONCE per group, pruning every node farther from the
group's bounding box than the largest current nearest distance of its points; at a
target leaf, a point scans it only when the leaf's box is nearer to it than its own
current nearest distance (the scheme of :func:`labkit.neighbours.kdtree._knn_leaves`).

Measured on the real TLS and ALS halves (262,000 / 175,000 source points in leaf order,
one thread, best of 5 CPU times): 0.09-0.11 s per query pass against 0.06-0.07 s, ALS
0.05 s against 0.03 s; runs of 16 consecutive queries instead of whole leaves gained
little (0.09-0.10 s), the groups must be the leaves.

One pass does everything per group, on the threads: the rows the search memory answers at once
(ICP's later iterations) are answered there, the group's box and leaf scans hold the other rows
only, and every row's answer is written where it becomes known (no numpy passes over all rows
between kernels: they ran on one thread while the other waited). The gaps of a group's rows to a
leaf's box are one loop without branches (SIMD). The 9 calls of icp on the TLS halves (248,000
queries each, replayed): 0.40 s -> 0.27 s of CPU on one thread, wall on two threads 0.26 s -> 0.17 s.

The nearest distance of every query is exact, as with the per-point search. Only the
index can differ where two target points are at exactly the same distance (a tie):
the per-point search keeps the first one its own walk meets. Such queries are marked
and answered again by the per-point kernel, so the result is the per-point search's
own, index for index.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import compiled
from .kdtree_build import in_runs

_RUNS_PER_THREAD = 12  # runs of groups per thread: an uneven split evens out (12: the two clouds of a registration,
# searched side by side on a shared pool, end closer together than with 4 or 8; 24 costs more than it evens)


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def _gap2(lo, hi, a, b):  # pragma: no cover - compiled
    """Squared gap between the intervals [lo, hi] and [a, b] (0 where they overlap), without branches."""
    t = max(0.0, lo - b) + max(0.0, a - hi)  # (one of them is 0)
    return t * t


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def _still_nearest(d2, mx, my, mz, second):  # pragma: no cover - compiled
    """True where a warm candidate at squared distance d2 is provably still the nearest point of its query.

    When the query was last searched, from a place (mx, my, mz) away from where it is now, every other
    point lay at least sqrt(second) from there, so now at least sqrt(second) - |m| from the query
    (triangle inequality); a candidate nearer than that is the unique nearest point. The margin 1e-9
    (relative) covers the rounding of the distances, each of which is correct to a few units in the last place.
    """
    return (np.sqrt(d2) + np.sqrt(mx * mx + my * my + mz * mz)) * (1.0 + 1e-9) < np.sqrt(second)


@compiled(inline="always")  # (inlined by numba into the search loops that call it)
def _answer(q, i, d2, indices, dist, index, warm):  # pragma: no cover - compiled
    """Row q's answer as the caller wants it: the distance (inf: none), the input index of its nearest point
    X[i] (len(indices): none) and the next warm start (i, -1: none; an empty ``warm``: not wanted)."""
    if i >= 0:
        dist[q], index[q] = np.sqrt(d2), indices[i]
    else:
        dist[q], index[q] = np.inf, indices.shape[0]
    if warm.shape[0] > 0:
        warm[q] = i


@compiled
def _nn_groups(X, nodes, box, depth, Q, group_start, bound2, indices, dist, index, tie, warm, at, second):  # pragma: no cover
    """Distance and input index (``indices`` of the leaf-order row) of the nearest row of X (leaf order) of every
    row of Q, squared distance < bound2.

    Q's rows come in groups: group g holds rows group_start[g]:group_start[g + 1]. Missing
    neighbours get distance inf and index len(X). ``tie[q]`` is set where another point
    lies at exactly the nearest distance (the index is then the per-point search's business).
    ``warm[q]`` (a row of X, or -1; an empty array: none) is a first candidate, e.g. the nearest
    point of the previous ICP iteration: its distance bounds the walk from the start; overwritten
    with the row of X of the nearest point (-1: none), the next call's warm start.

    ``at`` and ``second`` (with ``warm``; empty arrays: no memory) are the search memory of
    :func:`nearest`: a row whose warm candidate is provably still its nearest point (:func:`_still_nearest`)
    is answered without a walk; every other row of the group is searched with its second nearest
    point (squared distance into ``second``, bound2 when there is none within the bound; the nearest
    distance at a tie; ``at`` := the row): the walk then prunes by that larger distance, so that no
    point nearer than it is missed. The group's box and leaf scans hold the searched rows only.
    """
    want2 = second.shape[0] > 0
    has_warm = warm.shape[0] > 0
    stack = np.empty(2 * depth + 4, np.int64)
    lower = np.empty(2 * depth + 4)
    longest = 0
    for g in range(group_start.shape[0] - 1):
        longest = max(longest, group_start[g + 1] - group_start[g])
    # the searched rows of a group, their coordinates and their current nearest (w, best, tied) and
    # second nearest (w2) squared distances, side by side while the walk runs
    live, gq = np.empty(longest, np.int64), np.empty(longest)
    rx, ry, rz = np.empty(longest), np.empty(longest), np.empty(longest)
    lw, lw2 = np.empty(longest), np.empty(longest)
    lbest, ltie = np.empty(longest, np.int64), np.empty(longest, np.bool_)
    for g in range(group_start.shape[0] - 1):
        n = 0
        lo0 = lo1 = lo2 = np.inf
        hi0 = hi1 = hi2 = -np.inf
        wmax = 0.0
        for q in range(group_start[g], group_start[g + 1]):
            tie[q] = False
            qx, qy, qz = Q[q, 0], Q[q, 1], Q[q, 2]
            w, best = bound2, -1
            if has_warm and warm[q] >= 0:
                i = warm[q]
                dx, dy, dz = X[i, 0] - qx, X[i, 1] - qy, X[i, 2] - qz
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < bound2:
                    w, best = d2, i
                    if want2 and _still_nearest(d2, qx - at[q, 0], qy - at[q, 1], qz - at[q, 2], second[q]):
                        _answer(q, i, d2, indices, dist, index, warm)
                        continue
            w2 = bound2 if want2 else w
            if want2:
                at[q, 0], at[q, 1], at[q, 2] = qx, qy, qz
            live[n] = q
            rx[n], ry[n], rz[n] = qx, qy, qz
            lw[n], lw2[n], lbest[n], ltie[n] = w, w2, best, False
            wmax = max(wmax, w2)
            n += 1
            lo0, hi0 = min(lo0, qx), max(hi0, qx)
            lo1, hi1 = min(lo1, qy), max(hi1, qy)
            lo2, hi2 = min(lo2, qz), max(hi2, qz)
        if n == 0:
            continue
        sp = 1
        stack[0] = 0
        lower[0] = 0.0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if lower[sp] > wmax:  # (not >=: a point exactly as near as the best is a tie to see)
                continue
            gap = _gap2(box[node, 0], box[node, 3], lo0, hi0) + _gap2(box[node, 1], box[node, 4], lo1, hi1)
            gap += _gap2(box[node, 2], box[node, 5], lo2, hi2)
            if gap > wmax:
                continue
            child = nodes[node, 2]
            if child < 0:  # a leaf: scanned by the queries whose nearest distance reaches its box
                s, e = nodes[node, 0], nodes[node, 1]
                leaf = X[s:e]  # (indices from 0 up: no checks for negative ones in the loop, 4 % faster)
                wmax = 0.0
                b0, b1, b2 = box[node, 0], box[node, 1], box[node, 2]
                b3, b4, b5 = box[node, 3], box[node, 4], box[node, 5]
                for k in range(n):  # the gap of every row to the leaf's box (a loop without branches: SIMD)
                    tx = max(0.0, b0 - rx[k]) + max(0.0, rx[k] - b3)
                    ty = max(0.0, b1 - ry[k]) + max(0.0, ry[k] - b4)
                    tz = max(0.0, b2 - rz[k]) + max(0.0, rz[k] - b5)
                    gq[k] = tx * tx + ty * ty + tz * tz
                for k in range(n):
                    w = lw[k]
                    w2 = lw2[k]  # the walk's reach for this query (w2 >= w)
                    if gq[k] <= w2:
                        qx, qy, qz = rx[k], ry[k], rz[k]
                        best = lbest[k]
                        tied = ltie[k]
                        for j in range(leaf.shape[0]):
                            i = s + j
                            dx, dy, dz = leaf[j, 0] - qx, leaf[j, 1] - qy, leaf[j, 2] - qz
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 < w:
                                if want2:
                                    w2 = w  # the former nearest is now the second
                                w = d2
                                best = i
                                tied = False
                            elif d2 == w and best >= 0 and i != best:  # (the warm start met again)
                                tied = True
                                w2 = d2
                            else:  # (d2 < w2 and i != best: w2 = d2, as a minimum: a shorter chain from point to point)
                                w2 = min(w2, d2 if i != best else np.inf)
                        if not want2:
                            w2 = w
                        lw[k], lw2[k], lbest[k], ltie[k] = w, w2, best, tied
                    wmax = max(wmax, w2)
                continue
            d = int(box[node, 7])
            v = box[node, 6]
            lo_d, hi_d = (lo0, hi0) if d == 0 else ((lo1, hi1) if d == 1 else (lo2, hi2))
            if lo_d + hi_d < 2.0 * v:
                near, other, cut = child, nodes[node, 3], v - hi_d
            else:
                near, other, cut = nodes[node, 3], child, lo_d - v
            far = max(gap, cut * cut) if cut > 0.0 else gap
            if far <= wmax:
                stack[sp] = other
                lower[sp] = far
                sp += 1
            stack[sp] = near
            lower[sp] = gap
            sp += 1
        for k in range(n):  # the answers of the searched rows
            q = live[k]
            _answer(q, lbest[k], lw[k], indices, dist, index, warm)
            tie[q] = ltie[k]
            if want2:
                second[q] = lw2[k]


def nearest(tree, Q, starts, bound, threads, warm=None, memory=None):
    """Distance and input index of the nearest tree point of every row of ``Q`` (distance < bound;
    else inf and ``tree.n``), exactly as ``tree.query(Q, 1, bound, threads)``.

    Rows ``starts[g]:starts[g + 1]`` form group g (searched together, :func:`_nn_groups`); groups of
    points that lie close together (a source tree's leaves) make the search fast, any grouping gives
    the same answer. Rows with a tie are answered again by the per-point kernel, which then decides
    the index as it always did. ``warm`` (per row a leaf-order position or -1; overwritten with the
    position of the row's nearest point, -1: none) gives a first candidate of every row, e.g. its
    nearest point in the previous ICP iteration: an exact bound, the same answer sooner (a candidate
    as near as the nearest point counts as a tie).

    ``memory`` (optional, with ``warm``): a pair (at (m, 3), second (m,)) per row, read and overwritten:
    where the row was last searched and the squared distance of its second nearest point from there
    (0: unknown; start with zeros). A row whose warm candidate is nearer than any other point can be
    since then (:func:`_still_nearest`) is answered without a search; the others are searched (with
    their second nearest point, the memory of the next call). ICP's later iterations move the
    source by less than the spacing of the target: most rows are not searched again. The same answer.
    """
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    bound2 = bound * bound if np.isfinite(bound) else np.inf
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    given = warm
    warm = _NO_WARM if warm is None else np.ascontiguousarray(warm, dtype=np.intp)
    at, second = memory if memory is not None and len(warm) else (_NO_AT, _NO_SECOND)
    dist, index = _search(tree, Q, starts, bound, bound2, threads, warm, at, second)
    if given is not None and warm is not given:  # (a copy of another type)
        given[:] = warm
    return dist, index


_NO_WARM, _NO_AT, _NO_SECOND = np.empty(0, np.intp), np.empty((0, 3)), np.empty(0)


def _search(tree, Q, starts, bound, bound2, threads, warm, at, second):
    """:func:`_nn_groups` on the threads, ties answered again by the per-point kernel
    (their second nearest point is then as near as the nearest: no row is left out of the next search for it).

    The groups are cut into runs of about equal numbers of rows, a few per thread; this thread and
    the pool's take the next run until none is left (a search with memory leaves the work uneven)."""
    m = len(Q)
    dist, index, tie = np.empty(m), np.empty(m, np.intp), np.zeros(m, np.bool_)
    args = (tree.data, *tree._nodes, Q)

    def run(a, b):  # the groups a..b-1
        _nn_groups(*args, starts[a:b + 1], bound2, tree.indices, dist, index, tie, warm, at, second)

    threads = min(threads, max(1, m // 4000))
    if threads <= 1 or len(starts) <= 2:
        run(0, len(starts) - 1)
    else:
        cut = np.searchsorted(starts, np.linspace(0, m, _RUNS_PER_THREAD * threads + 1)[1:-1])
        in_runs(run, np.unique(np.r_[0, np.minimum(cut, len(starts) - 1), len(starts) - 1]), threads)
    redo = np.flatnonzero(tie)
    if len(redo):
        d2_r, idx_r = tree._run(Q[redo], 1, bound, 1)
        i = idx_r[:, 0]
        dist[redo] = np.where(i >= 0, np.sqrt(d2_r[:, 0]), np.inf)
        index[redo] = np.where(i >= 0, tree.indices[np.maximum(i, 0)], tree.n)
        if len(warm):
            warm[redo] = i
        if len(second):
            second[redo] = 0.0
    return dist, index
