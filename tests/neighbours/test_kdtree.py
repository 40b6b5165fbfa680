"""Tests of labkit.neighbours.kdtree: the compiled kNN against scipy's cKDTree and brute force."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labkit.neighbours import kdtree
from labkit.neighbours.kdtree import KDTree


def clouds():
    rng = np.random.default_rng(0)
    uniform = rng.uniform(0, 10, (3000, 3))
    ties = np.round(rng.normal(size=(3000, 3)), 1)  # many equal coordinates and duplicates
    surface = np.column_stack([rng.uniform(0, 5, (3000, 2)), np.zeros(3000)])  # flat: zero extent in z
    clustered = rng.normal(size=(3000, 3)) * np.exp(rng.uniform(-6, 0, (3000, 1)))  # densities over 10^2.6
    return {"uniform": uniform, "ties": ties, "surface": surface, "clustered": clustered}


@pytest.mark.parametrize("name", list(clouds()))
@pytest.mark.parametrize("k", [1, 7, 20])
def test_knn_distances_equal_ckdtree(name, k):
    P = clouds()[name]
    Q = P[::7] + np.random.default_rng(1).normal(0, 0.05, (len(P[::7]), 3))
    d, i = KDTree(P, leafsize=8).query(Q, k=k, workers=2)
    dc, ic = cKDTree(P).query(Q, k=k)
    assert np.allclose(d, dc, rtol=0, atol=1e-12)
    # the indices may differ only among equal distances
    assert np.allclose(np.linalg.norm(P[i] - (Q[:, None] if k > 1 else Q), axis=-1), dc, atol=1e-12)


@pytest.mark.parametrize("bound", [0.01, 0.03])
def test_distance_upper_bound_like_ckdtree(bound):
    P = clouds()["clustered"]
    Q = P[::5] + 0.05
    d, i = KDTree(P).query(Q, k=1, distance_upper_bound=bound)
    dc, ic = cKDTree(P).query(Q, k=1, distance_upper_bound=bound)
    assert np.array_equal(np.isinf(d), np.isinf(dc)) and np.isinf(d).any() and np.isfinite(d).any()
    assert np.allclose(d[np.isfinite(d)], dc[np.isfinite(dc)], atol=1e-12)
    assert (i[np.isinf(d)] == len(P)).all()


def test_merged_duplicates_are_counted_and_mapped():
    P = clouds()["ties"]
    tree = KDTree(P, merge_duplicates=True)
    distinct = np.unique(P, axis=0)
    assert tree.n == len(distinct) and tree.n_duplicates == len(P) - len(distinct)
    assert np.array_equal(tree.data[tree.representative], P)  # every point maps to an equal kept point
    assert np.array_equal(np.unique(tree.data, axis=0), distinct)
    # self-kNN on the distinct points equals cKDTree on np.unique
    d2, _ = tree._run(tree.data, 5, np.inf, 1)
    dc, _ = cKDTree(distinct).query(tree.data, k=5)
    assert np.allclose(np.sqrt(d2), dc, atol=1e-12)


def test_identical_points_make_one_leaf():
    tree = KDTree(np.ones((100, 3)), merge_duplicates=True)
    assert tree.n == 1 and tree.n_duplicates == 99
    d, i = tree.query(np.zeros((1, 3)), k=1)
    assert np.isclose(d[0], np.sqrt(3.0)) and i[0] == 0


def test_two_thread_build_gives_the_same_neighbours():
    """Above 10^5 points the root is split here and the halves built in two threads."""
    rng = np.random.default_rng(3)
    P = np.round(rng.normal(size=(150_000, 3)) * np.exp(rng.uniform(-3, 0, (150_000, 1))), 3)
    tree = KDTree(P, merge_duplicates=True)
    assert np.array_equal(tree.data[tree.representative], P)
    assert tree.n_duplicates == len(P) - len(np.unique(P, axis=0))
    Q = P[::50] + 0.001
    d, _ = tree.query(Q, k=8, workers=2)
    dc, _ = cKDTree(np.unique(P, axis=0)).query(Q, k=8)  # merged: the k nearest distinct points
    assert np.allclose(d, dc, atol=1e-12)
    d, _ = KDTree(P).query(Q, k=8, workers=2)
    assert np.allclose(d, cKDTree(P).query(Q, k=8)[0], atol=1e-12)


@pytest.mark.parametrize("name", list(clouds()))
def test_leaf_moments_equal_neighbours_then_covariances(name, monkeypatch):
    # the fused search + moments kernel against the two-step route (neighbour array, then eq. 1-2)
    from labkit.neighbours.moments import covariances

    tree = KDTree(clouds()[name], merge_duplicates=True)
    bounds = tree.leaf_bounds
    a, b = int(bounds[3]), int(bounds[-4])  # a run of whole leaves, not the whole cloud
    cen, C = tree.knn_moments_of_leaves(a, b, 20)
    nb = tree.knn_of_leaves(a, b, 20)
    X = tree.data[nb]  # (m, 20, 3)
    c_ref = X.mean(axis=1)
    D = X - c_ref[:, None]
    np.testing.assert_allclose(cen, c_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(C, np.einsum("mki,mkj->mij", D, D) / 20, rtol=0, atol=1e-12)
    c2, C2 = covariances(tree.data, None, nb, np.ascontiguousarray(tree.data.T))
    assert np.array_equal(cen, c2) and np.array_equal(C, C2)  # the same arithmetic: the same numbers
    with pytest.raises(ValueError, match="leaf bounds"):
        tree.knn_moments_of_leaves(a + 1, b, 20)
    monkeypatch.setattr(kdtree, "_PER_THREAD", 50)  # threads even on these small clouds
    for workers in (2, 3, -1):  # consecutive runs of leaves on threads: the same answer
        assert np.array_equal(tree.knn_of_leaves(a, b, 20, workers=workers), nb)
    small = tree.knn_of_leaves(a, b, 20, workers=-1, dtype=np.int32)  # the same indices in half the memory
    assert small.dtype == np.int32 and np.array_equal(small, nb)
    d, i = cKDTree(tree.data).query(tree.data[a:b], k=20)
    np.testing.assert_allclose(np.sort(((tree.data[nb] - tree.data[a:b, None]) ** 2).sum(-1), axis=1), d**2,
                               rtol=1e-12, atol=1e-15)  # the k nearest, checked by scipy


def test_selection_finds_the_kth_smallest_with_ties():
    from labkit.neighbours.kdtree_build import _select

    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 10, 101, 1000):
        for x in (rng.normal(size=n), rng.integers(0, 3, n).astype(float), np.zeros(n)):
            for kth in {0, n // 2, n - 1}:
                work = x.copy()
                assert _select(work, n, kth) == np.sort(x)[kth]
                assert np.array_equal(np.sort(work), np.sort(x))  # reordered, nothing lost


@pytest.mark.parametrize("name", list(clouds()))
@pytest.mark.parametrize("bound", [np.inf, 0.05])
def test_grouped_nearest_equals_the_per_point_search_index_for_index(name, bound):
    """nearest_in_groups (a source leaf walks the tree at once) against query(k=1): bitwise the same
    distances and the same indices, also where two target points are equally near (the 'ties' cloud
    and queries on the grid of its coordinates) and for groups that are not compact."""
    P = clouds()[name]
    tree = KDTree(P, leafsize=8, merge_duplicates=True)
    rng = np.random.default_rng(2)
    Q = np.round(P[::3] + rng.normal(0, 0.05, (len(P[::3]), 3)), 1 if name == "ties" else 12)
    qt = KDTree(Q, leafsize=8)
    Q = Q[qt.indices]  # leaf order: the groups are the leaves
    leaf_groups = qt.leaf_bounds
    chunk_groups = np.append(np.arange(0, len(Q), 5), len(Q))  # any grouping gives the same answer
    d0, i0 = tree.query(Q, k=1, distance_upper_bound=bound)
    for starts in (leaf_groups, chunk_groups, np.array([0, len(Q)])):
        for workers in (1, 2):
            d, i = tree.nearest_in_groups(Q, starts, bound, workers=workers)
            assert np.array_equal(d, d0) and np.array_equal(i, i0)
    # a warm start (ICP: last iteration's nearest point) changes no answer: a random candidate per
    # query, the answer itself, and (ties cloud) the answer of slightly moved queries
    rep = tree.representative
    found = i0 < tree.n
    for warm0 in (rng.integers(-1, tree.n, len(Q)), np.where(found, rep[np.where(found, i0, 0)], -1),
                  tree.nearest_in_groups(Q + 0.05, leaf_groups, bound, warm=np.full(len(Q), -1))[1]):
        warm0 = np.where(warm0 < tree.n, warm0, -1)
        for workers in (1, 2):
            warm = warm0.copy()
            d, i = tree.nearest_in_groups(Q, leaf_groups, bound, workers=workers, warm=warm)
            assert np.array_equal(d, d0) and np.array_equal(i, i0)
            assert np.array_equal(np.where(warm >= 0, tree.indices[warm], tree.n), i0)  # the next warm start
    # with a memory (ICP's iterations: the queries move by less and less) rows that provably kept their
    # nearest point are not searched again; every answer is still the per-point search's
    warm, memory = np.full(len(Q), -1), (np.zeros((len(Q), 3)), np.zeros(len(Q)))
    skipped = 0
    for step in (0.3, 0.01, 0.001, 1e-4, 0.0):
        Qs = Q + step * np.array([0.6, -0.8, 0.0]) if name != "ties" else np.round(Q + step, 1)
        d0, i0 = tree.query(Qs, k=1, distance_upper_bound=bound)
        before = memory[0].copy()
        d, i = tree.nearest_in_groups(Qs, leaf_groups, bound, workers=2, warm=warm, memory=memory)
        assert np.array_equal(d, d0) and np.array_equal(i, i0)
        skipped += int((memory[0] == before).all(axis=1).sum()) if step < 0.3 else 0
    assert skipped > (i0 < tree.n).sum()  # over the four small steps, more than once per row with a nearest point
    if name == "ties":  # the case the fallback is for: equally near target points
        from labkit.neighbours.kdtree_nn import _nn_groups

        n = len(Q)
        dist, index, tie = np.empty(n), np.empty(n, np.intp), np.zeros(n, np.bool_)
        _nn_groups(tree.data, *tree._nodes, Q, leaf_groups, np.inf, tree.indices, dist, index, tie,
                   np.empty(0, np.intp), np.empty((0, 3)), np.empty(0))
        assert tie.sum() > 10


def test_restricted_tree_answers_as_scipy_on_the_kept_points_in_another_frame():
    # millimetre coordinates with exact duplicates; the kept points in a frame 1 m away (another origin)
    rng = np.random.default_rng(7)
    P = np.round(rng.random((150_000, 3)) * [80.0, 60.0, 10.0], 3)
    P[1000:1200] = P[:200]
    keep = rng.random(len(P)) < 0.6
    keep[1000:1200] = keep[:200]  # a mask equal for duplicates (as the point selection's)
    whole = KDTree(P, merge_duplicates=True)
    shift = np.array([1.0, -1.0, 0.0])
    Q = P[keep] - shift
    cut = whole.restricted(keep, Q)
    fresh = KDTree(Q, merge_duplicates=True)
    assert (cut.n, cut.n_duplicates) == (fresh.n, fresh.n_duplicates)
    np.testing.assert_array_equal(cut.data[cut.representative], Q)  # every kept row maps to its point
    q = rng.random((20_000, 3)) * [80.0, 60.0, 10.0]
    # a merged tree lists each distinct point once: k neighbours as the tree built anew, the nearest as scipy
    np.testing.assert_array_equal(cut.query(q, k=4, distance_upper_bound=0.4)[0],
                                  fresh.query(q, k=4, distance_upper_bound=0.4)[0])
    ref_d = cKDTree(Q).query(q, k=1, distance_upper_bound=0.4)[0]
    d, _ = cut.nearest_in_groups(q, np.array([0, 7_000, 20_000]), 0.4, workers=2)
    np.testing.assert_array_equal(d, ref_d)
    nb = cut.knn_of_leaves(0, cut.n, 6, workers=-1)
    ref = cKDTree(cut.data).query(cut.data, k=6)[0]
    np.testing.assert_array_equal(np.sqrt(((cut.data[nb] - cut.data[:, None]) ** 2).sum(-1)), ref)
    kept_copy = whole.indices[whole.representative[0]]  # row 0 or its duplicate, row 1000
    bad = keep.copy()
    bad[kept_copy], bad[1000 if kept_copy == 0 else 0] = False, True  # a kept row whose point is dropped
    with pytest.raises(ValueError, match="duplicates"):
        whole.restricted(bad)


@pytest.mark.parametrize("spacing", [1.0, 0.37])
def test_tie_flags_say_where_the_kth_distance_is_shared(spacing):
    # integer coordinates (as LAS stores them) make equal distances common: the flag must agree with the
    # (k+1)-th neighbour of a search one longer, and the k neighbours must not change for it
    rng = np.random.default_rng(5)
    pts = rng.integers(0, 40, (6000, 3)).astype(float) * spacing
    pts[:, 2] *= 0.1  # flat-ish: many neighbours at the same few distances
    tree = KDTree(pts, merge_duplicates=True)
    k = 12
    nb, cen, C, tie = tree.knn_of_leaves(0, tree.n, k, workers=-1, moments=k, ties=True)
    longer = tree.knn_of_leaves(0, tree.n, k + 1)
    X, p = tree.data, np.arange(tree.n)
    d2 = lambda c: (X[c, 0] - X[p, 0]) ** 2 + (X[c, 1] - X[p, 1]) ** 2 + (X[c, 2] - X[p, 2]) ** 2  # noqa: E731
    assert np.array_equal(nb, longer[:, :k])
    assert np.array_equal(tie, d2(longer[:, k]) == d2(longer[:, k - 1]))
    assert 0.05 < tie.mean() < 0.95  # both answers occur
    c2, C2 = tree.knn_moments_of_leaves(0, tree.n, k)
    assert np.array_equal(cen, c2) and np.array_equal(C, C2)
