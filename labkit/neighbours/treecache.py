"""The target's kd-tree, kept for the next step on the same cloud (private).

``labkit register`` builds the compiled kd-tree of a 10-million-point target for ICP and needs
the same tree again for the distances of every point: building it twice cost 10-15 s and a
second copy of the cloud. :func:`local_tree` keeps the last tree it built, keyed by the identity
of the caller's coordinate array (a weak reference: the tree goes when the array goes), its
shape, the local origin, the duplicate rule and a checksum of an even subset of the coordinates
(an array changed in place gets a new tree). One entry only: a survey of many tiles keeps at
most one extra tree alive. :func:`forget` drops it.

The same way, :func:`keep_neighbours` keeps the k nearest neighbours that a first pass over a cloud
found (:class:`NeighbourRows`; ICP's point selection searches every point's neighbourhood, and
ICP's normals would search them again) for the next step on the same array, two clouds at most;
and :func:`offer_tree` hands a tree made ahead (the selected points' tree cut from the whole cloud's,
:meth:`labkit.neighbours.kdtree.KDTree.restricted`) to the next :func:`local_tree` or :func:`take_tree`
on that array, two clouds at most, each taken once.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from ..core.jit import compiled, have_numba
from ..core.threads import cores
from .kdtree_build import in_runs

_lock = threading.Lock()
_last = None  # (weak reference to the caller's array, key, tree)
_rows = []  # up to two (weak reference to the caller's array, key, NeighbourRows)
_offered = []  # up to two (weak reference to the caller's array, key, tree): made ahead for the next step


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
    tree = take_tree(points, origin, merge_duplicates, key)
    if tree is not None:
        keep_tree(points, origin, merge_duplicates, tree, key)
        return tree
    from .kdtree import KDTree  # here, not at the top: `labkit.cli` imports this module and stays free of numba

    tree = KDTree(np.asarray(points, dtype=np.float64) - origin, merge_duplicates=merge_duplicates)
    keep_tree(points, origin, merge_duplicates, tree, key)
    return tree


def keep_tree(points: np.ndarray, origin, merge_duplicates: bool, tree, key=None) -> None:
    """Keep ``tree`` (of ``points - origin``) as :func:`local_tree` keeps the last tree it built: when two
    clouds' trees were built side by side, the caller says which one a later step will ask for."""
    global _last
    try:
        ref = weakref.ref(points)
    except TypeError:  # pragma: no cover - arrays support weak references
        return
    key = _key(points, origin, merge_duplicates) if key is None else key
    with _lock:
        _last = (ref, key, tree)


def offer_tree(points: np.ndarray, origin, merge_duplicates: bool, tree) -> None:
    """Hand ``tree`` (of ``points - origin``, made ahead) to the next :func:`local_tree` or :func:`take_tree`
    on this very array (a weak reference; the two latest offers are kept)."""
    try:
        ref = weakref.ref(points, _drop_dead)
    except TypeError:  # pragma: no cover - arrays support weak references
        return
    key = _key(points, origin, merge_duplicates)
    with _lock:
        _offered[:] = [e for e in _offered if e[0]() is not None and e[0]() is not points][-1:] + [(ref, key, tree)]


def take_tree(points: np.ndarray, origin, merge_duplicates: bool, key=None):
    """The tree offered (:func:`offer_tree`) for this very array, origin and rule, once; else None."""
    key = _key(points, origin, merge_duplicates) if key is None else key
    with _lock:
        for i, (ref, k, tree) in enumerate(_offered):
            if ref() is points and k == key:
                del _offered[i]
                return tree
    return None


def forget() -> None:
    """Drop the kept tree, the offered trees and the neighbours (frees their memory)."""
    global _last
    with _lock:
        _last = None
        _rows.clear()
        _offered.clear()


class NeighbourRows:
    """The k nearest neighbours of a cloud's points as rows of the cloud, where they are known (private).

    ``rows`` (n, k): the neighbours of row i, sorted by distance (exact duplicates merged: each
    distinct point once, by the row of one of its copies); read only where ``known[i]``, i.e. where
    they are the cloud's unique k nearest (no other point at the k-th distance). ``pca`` (optional):
    the local PCA of those neighbourhoods, eigenvalues (N, 3) and eigenvectors (N, 3, 3)
    (:func:`labkit.registration.matching.local_surface._pca_rows`) of the first pass's points, and
    the position (n,) of every row among them; read where ``known``. ``rows`` may be a function that
    makes them: it is called on the first use (ICP's plane reads only the kept PCA and never asks).
    """

    def __init__(self, rows, known: np.ndarray, k: int, pca=None):
        self._rows, self.known, self.k, self.pca = rows, known, int(k), pca
        self._lock = threading.Lock()

    @property
    def rows(self) -> np.ndarray:
        """The neighbours (n, k) as rows of the cloud (made on the first use where given as a function)."""
        if callable(self._rows):
            with self._lock:
                if callable(self._rows):
                    self._rows = self._rows()
        return self._rows

    def at(self, tree, pos, pca=False, neighbours=True):
        """For the points ``pos`` (leaf positions) of ``tree`` (a kd-tree of the same cloud, duplicates
        merged): where their neighbours are known (m,) bool, and those neighbours as leaf positions
        (None without ``neighbours``); with ``pca`` also their kept PCA (eigenvalues, eigenvectors), or
        None where none is kept."""
        row = tree.indices[pos]
        known = self.known[row]
        rk = row[known]
        nb = tree.representative[self.rows[rk]] if neighbours else None
        if not pca:
            return known, nb
        if self.pca is None:
            return known, nb, None
        lam, vecs, at = self.pca
        first = at[rk]
        return known, nb, (np.take(lam, first, axis=0), np.take(vecs, first, axis=0))  # (faster than [] by index)

    def gather(self, tree, pos, nb=None, lam=None, vecs=None):
        """:meth:`at` written in place: where the neighbours of the points ``pos`` are known (m,) bool is
        returned, and there row i of ``nb`` (m, k) gets their neighbours (leaf positions) and rows i of
        ``lam`` (m, 3) and ``vecs`` (m, 3, 3) their kept PCA (each optional; the PCA needs ``pca``). The
        other rows are left as they are. One compiled pass in ranges on the cores instead of a gather
        into new arrays and a scatter of those into the caller's."""
        pos = np.asarray(pos, dtype=np.intp)
        want_pca = lam is not None and self.pca is not None
        if not have_numba():  # pragma: no cover - depends on the environment
            have, nb_known, *pca = self.at(tree, pos, pca=want_pca, neighbours=nb is not None)
            if nb is not None:
                nb[have] = nb_known
            if want_pca:
                lam[have], vecs[have] = pca[0]
            return have
        have = np.empty(len(pos), dtype=bool)
        rep = tree.representative if nb is not None else _NO_INDEX
        src_lam, src_vecs, at = self.pca if want_pca else (_NO_LAM, _NO_VECS, _NO_INDEX)
        args = (tree.indices, pos, self.known, _NO_ROWS if nb is None else self.rows, rep, at, src_lam, src_vecs,
                _NO_NB if nb is None else nb, _NO_LAM if not want_pca else lam, _NO_VECS if not want_pca else vecs, have)
        kernel = compiled(_gather_rows)
        threads = min(cores(), max(1, len(pos) // 20_000))
        in_runs(lambda a, b: kernel(*args, a, b), np.linspace(0, len(pos), 4 * threads + 1).astype(np.intp), threads)
        return have


_NO_INDEX, _NO_NB, _NO_ROWS = np.empty(0, np.intp), np.empty((0, 0), np.intp), np.empty((0, 0), np.int32)
_NO_LAM, _NO_VECS = np.empty((0, 3)), np.empty((0, 3, 3))


def _gather_rows(indices, pos, known, rows, rep, at, lam, vecs, nb, lam_out, vecs_out, have, a, b):  # pragma: no cover
    """:meth:`NeighbourRows.gather` at the points ``a..b-1`` (compiled on first use)."""
    want_nb, want_pca = nb.shape[0] > 0, lam_out.shape[0] > 0
    for i in range(a, b):
        row = indices[pos[i]]
        ok = known[row]
        have[i] = ok
        if not ok:
            continue
        if want_nb:
            for c in range(rows.shape[1]):
                nb[i, c] = rep[rows[row, c]]
        if want_pca:
            r = at[row]
            for c in range(3):
                lam_out[i, c] = lam[r, c]
                for d in range(3):
                    vecs_out[i, c, d] = vecs[r, c, d]


def _drop_dead(_ref) -> None:
    """Drop the entries whose array is gone (called when a kept array dies): their neighbours and
    PCA, some 200 bytes per point, or their offered tree, go with it instead of waiting for the next cloud. No lock: the
    garbage collector may call this while this thread holds it; one assignment of the list."""
    _rows[:] = [e for e in _rows if e[0]() is not None]
    _offered[:] = [e for e in _offered if e[0]() is not None]


def keep_neighbours(points: np.ndarray, rows: NeighbourRows) -> None:
    """Keep ``rows`` for the array ``points`` (a weak reference; the two latest arrays are kept, each until
    it is gone)."""
    try:
        ref = weakref.ref(points, _drop_dead)
    except TypeError:  # pragma: no cover - arrays support weak references
        return
    key = _key(points, np.zeros(3), True)
    with _lock:
        _rows[:] = [e for e in _rows if e[0]() is not None and e[0]() is not points][-1:] + [(ref, key, rows)]


def kept_neighbours(points: np.ndarray, k: int) -> NeighbourRows | None:
    """The :class:`NeighbourRows` kept for this very array (same shape and content) with this k, or None."""
    with _lock:
        entries = list(_rows)
    for ref, key, rows in entries:
        if ref() is points and rows.k == k and key == _key(points, np.zeros(3), True):
            return rows
    return None
