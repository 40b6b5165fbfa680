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

The nearest distance of every query is exact, as with the per-point search. Only the
index can differ where two target points are at exactly the same distance (a tie):
the per-point search keeps the first one its own walk meets. Such queries are marked
and answered again by the per-point kernel, so the result is the per-point search's
own, index for index.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import compiled
from .kdtree_build import _pool



_NO_WARM = np.empty(0, np.intp)


@compiled
def _gap2(lo, hi, a, b):  # pragma: no cover - compiled
    """Squared gap between the intervals [lo, hi] and [a, b] (0 where they overlap)."""
    t = lo - b
    if t > 0.0:
        return t * t
    t = a - hi
    return t * t if t > 0.0 else 0.0


@compiled
def _nn_groups(X, nodes, box, depth, Q, group_start, bound2, idx, dist2, tie, warm, second):  # pragma: no cover
    """Nearest row of X (leaf order) of every row of Q, squared distance < bound2.

    Q's rows come in groups: group g holds rows group_start[g]:group_start[g + 1]. Missing
    neighbours get index -1 and distance bound2. ``tie[q]`` is set where another point
    lies at exactly the nearest distance (the index is then the per-point search's business).
    ``warm[q]`` (a row of X, or -1; an empty array: none) is a first candidate, e.g. the nearest
    point of the previous ICP iteration: its distance bounds the walk from the start.
    ``second`` (an empty array: not wanted) gets the squared distance of every query's second
    nearest point (bound2 when there is none within the bound; the nearest distance at a tie): the
    walk then prunes by that larger distance, so that no point nearer than it is missed.
    """
    want2 = second.shape[0] > 0
    stack = np.empty(2 * depth + 4, np.int64)
    lower = np.empty(2 * depth + 4)
    for g in range(group_start.shape[0] - 1):
        a, b = group_start[g], group_start[g + 1]
        if b <= a:
            continue
        lo0 = hi0 = Q[a, 0]
        lo1 = hi1 = Q[a, 1]
        lo2 = hi2 = Q[a, 2]
        wmax = 0.0
        for q in range(a, b):
            idx[q] = -1
            dist2[q] = bound2
            tie[q] = False
            if warm.shape[0] > 0 and warm[q] >= 0:
                i = warm[q]
                dx, dy, dz = X[i, 0] - Q[q, 0], X[i, 1] - Q[q, 1], X[i, 2] - Q[q, 2]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < bound2:
                    dist2[q] = d2
                    idx[q] = i
            if want2:
                second[q] = bound2
                wmax = max(wmax, bound2)
            else:
                wmax = max(wmax, dist2[q])
            lo0, hi0 = min(lo0, Q[q, 0]), max(hi0, Q[q, 0])
            lo1, hi1 = min(lo1, Q[q, 1]), max(hi1, Q[q, 1])
            lo2, hi2 = min(lo2, Q[q, 2]), max(hi2, Q[q, 2])
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
                wmax = 0.0
                for q in range(a, b):
                    w = dist2[q]
                    w2 = second[q] if want2 else w  # the walk's reach for this query
                    qx, qy, qz = Q[q, 0], Q[q, 1], Q[q, 2]
                    gq = _gap2(box[node, 0], box[node, 3], qx, qx) + _gap2(box[node, 1], box[node, 4], qy, qy)
                    gq += _gap2(box[node, 2], box[node, 5], qz, qz)
                    if gq <= w2:
                        best = idx[q]
                        tied = tie[q]
                        for i in range(s, e):
                            dx, dy, dz = X[i, 0] - qx, X[i, 1] - qy, X[i, 2] - qz
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
                            elif want2 and d2 < w2 and i != best:
                                w2 = d2
                        dist2[q] = w
                        idx[q] = best
                        tie[q] = tied
                        if want2:
                            second[q] = w2
                        else:
                            w2 = w
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


@compiled
def _still_nearest(X, Q, warm, at, second, bound2, idx, dist2, done):  # pragma: no cover - compiled
    """done[q] where the warm candidate is provably still the nearest point of query q (then idx, dist2 set).

    When query q was last searched from ``at[q]``, every other point lay at least sqrt(second[q]) from
    there, so now at least sqrt(second[q]) - |Q[q] - at[q]| from Q[q] (triangle inequality); a candidate
    nearer than that is the unique nearest point. The margin 1e-9 (relative) covers the rounding of the
    distances, each of which is correct to a few units in the last place.
    """
    for q in range(Q.shape[0]):
        done[q] = False
        i = warm[q]
        if i < 0:
            continue
        dx, dy, dz = X[i, 0] - Q[q, 0], X[i, 1] - Q[q, 1], X[i, 2] - Q[q, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if not d2 < bound2:
            continue
        mx, my, mz = Q[q, 0] - at[q, 0], Q[q, 1] - at[q, 1], Q[q, 2] - at[q, 2]
        if (np.sqrt(d2) + np.sqrt(mx * mx + my * my + mz * mz)) * (1.0 + 1e-9) < np.sqrt(second[q]):
            idx[q] = i
            dist2[q] = d2
            done[q] = True


def nearest(tree, Q, starts, bound, threads, warm=None, memory=None):
    """Leaf-order index and squared distance of the nearest tree point of every row of ``Q`` (squared
    distance < bound**2; else -1 and bound**2), exactly as ``tree._run(Q, 1, bound, threads)``.

    Rows ``starts[g]:starts[g + 1]`` form group g (searched together, :func:`_nn_groups`); groups of
    points that lie close together (a source tree's leaves) make the search fast, any grouping gives
    the same answer. Rows with a tie are answered again by the per-point kernel, which then decides
    the index as it always did. ``warm`` (per row a leaf-order position or -1) gives a first candidate
    of every row, e.g. its nearest point in the previous ICP iteration: an exact bound, the same
    answer sooner (a candidate as near as the nearest point counts as a tie).

    ``memory`` (optional, with ``warm``): a pair (at (m, 3), second (m,)) per row, read and overwritten:
    where the row was last searched and the squared distance of its second nearest point from there
    (0: unknown; start with zeros). A row whose warm candidate is nearer than any other point can be
    since then (:func:`_still_nearest`) is answered without a search; the others are searched (with
    their second nearest point, the memory of the next call). ICP's later iterations move the
    source by less than the spacing of the target: most rows are not searched again. The same answer.
    """
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    m = len(Q)
    bound2 = bound * bound if np.isfinite(bound) else np.inf
    idx, d2 = np.empty(m, np.intp), np.empty(m)
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    warm = _NO_WARM if warm is None else np.ascontiguousarray(warm, dtype=np.intp)
    if memory is None or not len(warm):
        _search(tree, Q, starts, bound, bound2, threads, warm, _NO_SECOND, idx, d2)
        return d2, idx
    at, second = memory
    done = np.empty(m, np.bool_)
    _still_nearest(tree.data, Q, warm, at, second, bound2, idx, d2, done)
    todo = np.flatnonzero(~done)
    if len(todo):
        group = np.searchsorted(starts, todo, side="right")  # rows of one group stay together
        sub = np.append(np.flatnonzero(np.r_[True, group[1:] != group[:-1]]), len(todo)).astype(np.int64)
        idx_t, d2_t, s2 = np.empty(len(todo), np.intp), np.empty(len(todo)), np.empty(len(todo))
        _search(tree, Q[todo], sub, bound, bound2, threads, warm[todo], s2, idx_t, d2_t)
        idx[todo], d2[todo] = idx_t, d2_t
        at[todo], second[todo] = Q[todo], s2
    return d2, idx


_NO_SECOND = np.empty(0)


def _search(tree, Q, starts, bound, bound2, threads, warm, second, idx, d2):
    """:func:`_nn_groups` on the threads, ties answered again by the per-point kernel (their second
    nearest point is then as near as the nearest: no row is left out of the next search for it)."""
    m = len(Q)
    tie = np.zeros(m, np.bool_)
    args = (tree.data, *tree._nodes)
    threads = min(threads, max(1, m // 4000))
    if threads <= 1 or len(starts) <= 2:
        _nn_groups(*args, Q, starts, bound2, idx, d2, tie, warm, second)
    else:
        cut = np.unique(np.linspace(0, len(starts) - 1, threads + 1).astype(int))
        jobs = [_pool(threads).submit(_nn_groups, *args, Q, starts[a:b + 1], bound2, idx, d2, tie, warm, second)
                for a, b in zip(cut[:-1], cut[1:])]
        for job in jobs:
            job.result()
    redo = np.flatnonzero(tie)
    if len(redo):
        d2_r, idx_r = tree._run(Q[redo], 1, bound, 1)
        d2[redo], idx[redo] = d2_r[:, 0], idx_r[:, 0]
        if len(second):
            second[redo] = 0.0
