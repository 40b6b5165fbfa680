"""The target's kd-tree, kept for the next step on the same cloud (private).

``labkit register`` builds the compiled kd-tree of a 10-million-point target for ICP and needs
the same tree again for the distances of every point: building it twice cost 10-15 s and a
second copy of the cloud. :func:`local_tree` keeps the last tree it built, keyed by the identity
of the caller's coordinate array (a weak reference: the tree goes when the array goes), its
shape, the local origin, the duplicate rule and a checksum of an even subset of the coordinates
(an array changed in place gets a new tree). One entry only: a survey of many tiles keeps at
most one extra tree alive. :func:`forget` drops it.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

_lock = threading.Lock()
_last = None  # (weak reference to the caller's array, key, tree)


def _key(points, origin, merge_duplicates):
    sub = np.ascontiguousarray(points[:: max(1, len(points) // 4096)])
    return points.shape, np.asarray(origin, dtype=np.float64).tobytes(), bool(merge_duplicates), hash(sub.tobytes())


def local_tree(points: np.ndarray, origin, merge_duplicates: bool):
    """KDTree of ``points - origin`` (reused when the same array, origin and rule came last)."""
    global _last
    key = _key(points, origin, merge_duplicates)
    with _lock:
        last = _last
    if last is not None and last[0]() is points and last[1] == key:
        return last[2]
    from .kdtree import KDTree  # here, not at the top: `labkit.cli` imports this module and stays free of numba

    tree = KDTree(np.asarray(points, dtype=np.float64) - origin, merge_duplicates=merge_duplicates)
    try:
        ref = weakref.ref(points)
    except TypeError:  # pragma: no cover - arrays support weak references
        return tree
    with _lock:
        _last = (ref, key, tree)
    return tree


def forget() -> None:
    """Drop the kept tree (frees its memory)."""
    global _last
    with _lock:
        _last = None
