"""labkit.neighbours.treecache: the last kd-tree is reused for the same array, origin and rule, and rebuilt otherwise.

That ICP and the distances share one tree through it: tests/test_icp_sampling.py.
"""

import gc

import numpy as np
import pytest

from labkit.neighbours import treecache as _treecache
from labkit.neighbours.treecache import forget, local_tree


@pytest.fixture(autouse=True)
def empty_cache():
    forget()
    yield
    forget()


def _cloud(n=2000, seed=0):
    return np.random.default_rng(seed).uniform(0, 10, (n, 3)) + [500_000.0, 5_400_000.0, 300.0]


def test_same_array_origin_and_rule_give_the_same_tree_which_is_right():
    pts = _cloud()
    origin = np.round(pts.mean(axis=0))
    tree = local_tree(pts, origin, merge_duplicates=True)
    assert local_tree(pts, origin.copy(), True) is tree  # an equal origin in another array
    np.testing.assert_array_equal(tree.data[np.argsort(tree.indices)], pts - origin)  # the tree of pts - origin
    q = pts[:5] - origin
    np.testing.assert_array_equal(tree.query(q, k=1)[1], np.arange(5))


@pytest.mark.parametrize("change", ["copy", "origin", "rule", "in place", "shape"])
def test_anything_else_gives_a_new_tree(change):
    pts = _cloud()
    origin = np.round(pts.mean(axis=0))
    tree = local_tree(pts, origin, False)
    if change == "copy":
        again = local_tree(pts.copy(), origin, False)  # equal values, another array: not trusted
    elif change == "origin":
        again = local_tree(pts, origin + 1.0, False)
    elif change == "rule":
        again = local_tree(pts, origin, True)
    elif change == "in place":
        pts[:: len(pts) // 4096 or 1] += 0.5  # the sampled rows move: the checksum changes
        again = local_tree(pts, origin, False)
        np.testing.assert_array_equal(again.data[np.argsort(again.indices)], pts - origin)
    else:
        again = local_tree(pts[:-1], origin, False)
    assert again is not tree


def test_one_entry_weakly_kept_and_forget_drops_it():
    a, b = _cloud(seed=1), _cloud(seed=2)
    origin = np.round(a.mean(axis=0))
    ta = local_tree(a, origin, False)
    tb = local_tree(b, origin, False)
    assert local_tree(b, origin, False) is tb
    assert local_tree(a, origin, False) is not ta  # only the last tree is kept
    forget()
    assert local_tree(a, origin, False) is not ta and _treecache._last is not None
    del a
    gc.collect()
    assert _treecache._last[0]() is None  # the array is not kept alive by the cache


def test_kept_neighbours_go_with_their_array():
    from labkit.neighbours.treecache import NeighbourRows, keep_neighbours, kept_neighbours

    pts = _cloud(500)
    rows = NeighbourRows(np.zeros((500, 4), dtype=np.int32), np.ones(500, dtype=bool), 4)
    keep_neighbours(pts, rows)
    assert kept_neighbours(pts, 4) is rows and kept_neighbours(pts.copy(), 4) is None
    del pts
    gc.collect()
    assert _treecache._rows == []  # no rows of a dead array held until the next cloud comes


def test_an_offered_tree_is_taken_once_by_its_array_and_goes_with_it():
    treecache = _treecache
    treecache.forget()
    pts = np.random.default_rng(0).random((50, 3))
    tree = object()  # any tree: the cache only hands it on
    treecache.offer_tree(pts, np.zeros(3), True, tree)
    assert treecache.take_tree(pts.copy(), np.zeros(3), True) is None  # another array with the same content
    assert treecache.take_tree(pts, np.ones(3), True) is None  # another origin
    assert treecache.local_tree(pts, np.zeros(3), True) is tree  # taken instead of a build
    assert treecache.take_tree(pts, np.zeros(3), True) is None  # once
    other = np.random.default_rng(1).random((50, 3))
    treecache.offer_tree(other, np.zeros(3), True, tree)
    del other
    gc.collect()
    assert treecache._offered == []  # dropped with its array
    treecache.forget()


@pytest.mark.parametrize("m", [1, 7, 50_000])
@pytest.mark.parametrize("with_pca", [True, False])
def test_gather_writes_what_at_returns_where_the_neighbours_are_known(m, with_pca):
    from labkit.neighbours.kdtree import KDTree
    from labkit.neighbours.treecache import NeighbourRows

    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (60_000, 3))
    pts[1] = pts[0]  # an exact duplicate: merged in the tree
    tree = KDTree(pts, merge_duplicates=True)
    k = 5
    rows = rng.integers(0, len(pts), (len(pts), k)).astype(np.int32)
    known = rng.random(len(pts)) < 0.8
    pca = (rng.random((tree.n, 3)), rng.random((tree.n, 3, 3)), tree.representative.copy()) if with_pca else None
    nr = NeighbourRows(rows, known, k, pca)
    pos = np.sort(rng.choice(tree.n, m, replace=False))
    nb, lam, vecs = np.full((m, k), -7), np.full((m, 3), -7.0), np.full((m, 3, 3), -7.0)
    have = nr.gather(tree, pos, nb, lam, vecs)
    ref_have, ref_nb, *ref_pca = nr.at(tree, pos, pca=with_pca)
    assert (have == ref_have).all()
    assert (nb[have] == ref_nb).all() and (nb[~have] == -7).all()
    if with_pca:
        assert (lam[have] == ref_pca[0][0]).all() and (vecs[have] == ref_pca[0][1]).all()
        assert (lam[~have] == -7).all()
    else:  # nothing kept to gather: the PCA rows stay as they were
        assert (lam == -7).all() and (vecs == -7).all()
