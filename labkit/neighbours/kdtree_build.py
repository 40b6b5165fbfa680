"""Construction of the compiled kd-tree of :mod:`labkit.neighbours.kdtree` (private): the median split with ties
kept together, the two-thread build of the root's halves, the duplicate search and the kept thread pool.

See :mod:`labkit.neighbours.kdtree` for the design and the measurements.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..core.arrays import extent
from ..core.jit import compiled
from ..core.threads import cores
from .eigh3 import HAVE_NUMBA



@compiled
def _build(P, leafsize):  # pragma: no cover - compiled
    """Median kd-tree: permutation (leaf order), node ranges, children, boxes, depth, leaf-order points.

    The coordinates are moved along with the permutation (W), so every pass over a
    node reads its points sequentially instead of gathering them through ``perm``.
    P must be a private, writeable float64 copy: it becomes W (one copy less of a large cloud).
    """
    n = P.shape[0]
    perm = np.arange(n)
    W = P
    wbuf = np.empty((n, 3))
    cap = max(16, 4 * (n // max(1, leafsize // 2)) + 16)
    start = np.empty(cap, np.int64)
    end = np.empty(cap, np.int64)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    lo = np.empty((cap, 3))
    hi = np.empty((cap, 3))
    sval = np.zeros(cap)
    sdim = np.zeros(cap, np.int64)
    stack = np.empty((64, 2), np.int64)  # node, depth
    buf = np.empty(n, np.int64)
    keys = np.empty(n)
    start[0], end[0] = 0, n
    count, sp, depth_max = 1, 1, 1
    stack[0, 0], stack[0, 1] = 0, 1
    for d in range(3):  # the root's box; every other node's box comes from its parent's partition pass
        lo[0, d] = np.inf
        hi[0, d] = -np.inf
    for i in range(n):
        for d in range(3):
            v = W[i, d]
            if v < lo[0, d]:
                lo[0, d] = v
            if v > hi[0, d]:
                hi[0, d] = v
    cbox = np.empty((2, 6))  # boxes of the two children (lo, hi), filled while the points are moved
    dims = np.empty(3, np.int64)
    while sp > 0:
        sp -= 1
        node, depth = stack[sp, 0], stack[sp, 1]
        depth_max = max(depth_max, depth)
        a, b = start[node], end[node]
        if b - a <= leafsize:
            continue
        # try the dimensions from the widest down (equal widths: the lower dimension first); split at the
        # median with ties kept together
        e0, e1, e2 = hi[node, 0] - lo[node, 0], hi[node, 1] - lo[node, 1], hi[node, 2] - lo[node, 2]
        dims[0], dims[1], dims[2] = 0, 1, 2
        if e1 > e0:
            dims[0], dims[1] = 1, 0
        if e2 > max(e0, e1):
            dims[2], dims[1], dims[0] = dims[1], dims[0], 2
        elif e2 > min(e0, e1):
            dims[2], dims[1] = dims[1], 2
        split = -1
        for t in range(3):
            d = dims[t]
            if hi[node, d] - lo[node, d] <= 0.0:
                break
            m = b - a
            for i in range(m):
                keys[i] = W[a + i, d]
            v = _select(keys, m, m // 2)  # the median (keys reordered)
            below = _partition(W, perm, wbuf, buf, a, b, d, v, cbox)
            if below == 0:  # v is the minimum (nothing moved): split after all points equal to v
                nxt = np.inf
                for i in range(m):
                    if keys[i] > v and keys[i] < nxt:
                        nxt = keys[i]
                v = nxt
                below = _partition(W, perm, wbuf, buf, a, b, d, v, cbox)
            split = a + below
            sval[node], sdim[node] = v, d
            break
        if split < 0:  # all points identical: one leaf, however many
            continue
        if count + 2 > cap:  # ties can make more, smaller leaves than median splits alone: grow
            cap *= 2
            start, end = _grow(start, cap), _grow(end, cap)
            left, right = _grow(left, cap, -1), _grow(right, cap, -1)
            lo, hi = _grow2(lo, cap), _grow2(hi, cap)
            sval, sdim = _grow(sval, cap), _grow(sdim, cap)
        if sp + 2 > stack.shape[0]:
            bigger = np.empty((2 * stack.shape[0], 2), np.int64)
            bigger[:sp] = stack[:sp]
            stack = bigger
        l, r = count, count + 1
        count += 2
        left[node], right[node] = l, r
        start[l], end[l], start[r], end[r] = a, split, split, b
        for e in range(3):
            lo[l, e], hi[l, e] = cbox[0, e], cbox[0, 3 + e]
            lo[r, e], hi[r, e] = cbox[1, e], cbox[1, 3 + e]
        stack[sp, 0], stack[sp, 1] = r, depth + 1
        stack[sp + 1, 0], stack[sp + 1, 1] = l, depth + 1
        sp += 2
    # pack what a query reads per node into two rows: box and split (float), range and children (int)
    box = np.empty((count, 8))
    box[:, :3] = lo[:count]
    box[:, 3:6] = hi[:count]
    box[:, 6] = sval[:count]
    box[:, 7] = sdim[:count]
    nodes = np.empty((count, 4), np.int64)
    nodes[:, 0], nodes[:, 1] = start[:count], end[:count]
    nodes[:, 2], nodes[:, 3] = left[:count], right[:count]
    return perm, nodes, box, depth_max, W


@compiled
def _partition(W, perm, wbuf, buf, a, b, d, v, cbox):  # pragma: no cover - compiled
    """Stable partition of the points W[a:b] (and perm[a:b]) into coordinate d < v and >= v; returns the
    number below. The points below move down in place (never past one not yet read), the others through
    ``wbuf``/``buf`` to behind them; ``cbox`` gets the two sides' boxes (lo, hi). Nothing moves when no
    point lies below v."""
    for c in range(2):
        for e in range(3):
            cbox[c, e] = np.inf
            cbox[c, 3 + e] = -np.inf
    j0, j1 = a, 0
    for i in range(a, b):
        x0, x1, x2 = W[i, 0], W[i, 1], W[i, 2]
        if (x0 if d == 0 else (x1 if d == 1 else x2)) < v:
            perm[j0] = perm[i]
            W[j0, 0], W[j0, 1], W[j0, 2] = x0, x1, x2
            j0 += 1
            c = 0
        else:
            buf[j1] = perm[i]
            wbuf[j1, 0], wbuf[j1, 1], wbuf[j1, 2] = x0, x1, x2
            j1 += 1
            c = 1
        cbox[c, 0] = min(cbox[c, 0], x0)
        cbox[c, 1] = min(cbox[c, 1], x1)
        cbox[c, 2] = min(cbox[c, 2], x2)
        cbox[c, 3] = max(cbox[c, 3], x0)
        cbox[c, 4] = max(cbox[c, 4], x1)
        cbox[c, 5] = max(cbox[c, 5], x2)
    if j0 > a:
        for i in range(j1):
            perm[j0 + i] = buf[i]
            W[j0 + i, 0], W[j0 + i, 1], W[j0 + i, 2] = wbuf[i, 0], wbuf[i, 1], wbuf[i, 2]
    return j0 - a


@compiled
def _select(x, n, kth):  # pragma: no cover - compiled
    """The kth smallest of x[:n], in place (Hoare's selection with a median-of-three pivot)."""
    lo, hi = 0, n - 1
    while hi > lo:
        mid = (lo + hi) // 2
        if x[mid] < x[lo]:
            x[mid], x[lo] = x[lo], x[mid]
        if x[hi] < x[lo]:
            x[hi], x[lo] = x[lo], x[hi]
        if x[hi] < x[mid]:
            x[hi], x[mid] = x[mid], x[hi]
        pivot = x[mid]
        i, j = lo, hi
        while i <= j:
            while x[i] < pivot:
                i += 1
            while x[j] > pivot:
                j -= 1
            if i <= j:
                x[i], x[j] = x[j], x[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            break
    return x[kth]


@compiled
def _grow(a, cap, fill=0):  # pragma: no cover - compiled
    out = np.full(cap, fill, a.dtype)
    out[: len(a)] = a
    return out


@compiled
def _grow2(a, cap):  # pragma: no cover - compiled
    out = np.empty((cap, 3))
    out[: len(a)] = a
    return out


@compiled
def _duplicates(X, nodes):  # pragma: no cover - compiled
    """keep[i] False for a leaf-order point equal to an earlier one of its leaf; first[i] its kept copy."""
    n = X.shape[0]
    keep = np.ones(n, np.bool_)
    first = np.arange(n)
    for node in range(nodes.shape[0]):
        if nodes[node, 2] >= 0:
            continue
        for i in range(nodes[node, 0] + 1, nodes[node, 1]):
            for j in range(nodes[node, 0], i):
                if keep[j] and X[i, 0] == X[j, 0] and X[i, 1] == X[j, 1] and X[i, 2] == X[j, 2]:
                    keep[i] = False
                    first[i] = j
                    break
    return keep, first


def _build_two(P, leafsize):
    """:func:`_build`, with the root split here and its two halves built in two threads (the kernel
    releases the GIL); the same tree as one call, up to the numbering of the nodes."""
    n = len(P)
    if n < 100_000 or _threads(-1) < 2 or not HAVE_NUMBA:
        return _build(np.array(P, np.float64, order="C"), leafsize)  # private, writeable copy
    lo, hi = extent(P)
    d = int(np.argmax(hi - lo))
    keys = P[:, d]
    v = np.partition(keys, n // 2)[n // 2]
    left = keys < v
    if not left.any():  # v is the minimum: split after all points equal to it (ties stay together)
        left = keys <= v
        if left.all():
            return _build(np.array(P, np.float64, order="C"), leafsize)  # private, writeable copy
        v = keys[~left].min()
    iL, iR = np.flatnonzero(left), np.flatnonzero(~left)
    cut = len(iL)
    W = np.empty((n, 3))  # both halves built in place in one array: no stacking of the results
    np.take(P, iL, axis=0, out=W[:cut])
    np.take(P, iR, axis=0, out=W[cut:])
    halves = [W[:cut], W[cut:]]  # private, contiguous halves, each replaced by its tree

    def build(a, b):
        halves[a] = _build(halves[a], leafsize)

    in_runs(build, [0, 1, 2], 2)  # this thread builds one, a pool worker the other (if it is free)
    (pL, nL, bL, dL, _), (pR, nR, bR, dR, _) = halves
    mL = len(nL)
    nodes = np.empty((1 + mL + len(nR), 4), np.int64)
    nodes[0] = (0, n, 1, 1 + mL)
    nodes[1 : 1 + mL] = nL
    nodes[1 : 1 + mL, 2:] += np.where(nL[:, 2:] >= 0, 1, 0)
    nodes[1 + mL :] = nR
    nodes[1 + mL :, :2] += len(iL)
    nodes[1 + mL :, 2:] += np.where(nR[:, 2:] >= 0, 1 + mL, 0)
    root = np.concatenate([lo, hi, [v, d]])
    box = np.vstack([root[None, :], bL, bR])
    perm = np.empty(n, np.int64)
    np.take(iL, pL, out=perm[:cut])
    np.take(iR, pR, out=perm[cut:])
    return perm, nodes, box, max(dL, dR) + 1, W


_pool_lock = threading.Lock()
_pool_state = {"pool": None, "size": 0}


def _pool(threads):
    """A thread pool kept for the compiled kernels of this module (ICP queries the tree ~10 times per
    call, and starting threads cost 5-10 ms each on a loaded machine). Only kernels run on it, which
    never submit work themselves, so callers on any thread can share it without deadlock."""
    with _pool_lock:
        if _pool_state["pool"] is None or _pool_state["size"] < threads:
            old = _pool_state["pool"]
            _pool_state["pool"], _pool_state["size"] = ThreadPoolExecutor(threads, "labkit-kdtree"), threads
            if old is not None:
                old.shutdown(wait=False)
        return _pool_state["pool"]


def in_runs(run, cuts, threads):
    """``run(a, b)`` for the consecutive ranges ``cuts[i]:cuts[i + 1]``, taken one after the other by this
    thread and by up to ``threads - 1`` workers of the kept pool, each taking the next range left.

    Unlike a fixed split (one part per thread, the caller waiting), the caller works too and nobody
    waits for a late thread: where another caller keeps the pool busy (the two clouds of a
    registration are treated side by side), this thread takes the remaining ranges itself, and a worker
    that starts after the last range has been taken returns at once (a pool job that has not started
    by then is cancelled, so a run may itself use the pool without a deadlock). Each range is computed
    alone: the result does not depend on who computed which range.
    """
    cuts = np.asarray(cuts).tolist()
    ranges = iter([(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a])  # (empty ranges skipped)
    lock = threading.Lock()

    def work():
        while True:
            with lock:
                a, b = next(ranges, (0, 0))
            if b <= a:
                return
            run(a, b)

    threads = min(int(threads), len(cuts) - 1)
    if threads <= 1:
        return work()
    pool = _pool(threads - 1)
    jobs = [pool.submit(work) for _ in range(threads - 1)]
    try:
        work()
    finally:
        for job in jobs:
            if not job.cancel():
                job.result()


def _forget_pool():  # a forked child has none of the parent's threads: start afresh
    global _pool_lock
    _pool_lock = threading.Lock()
    _pool_state["pool"], _pool_state["size"] = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _threads(workers):
    if workers == -1:
        return cores()
    return max(1, int(workers))
