"""Tests of labkit.neighbours: kNN / radius neighbourhoods and the chunked covariance engine."""

import numpy as np
import pytest

import labkit.neighbours.search as NB
from labkit.core.errors import LabkitError

UTM = np.array([600000.0, 5400000.0, 300.0])


def clustered(rng, n=3000):
    """Densities over three orders of magnitude (like a TLS scan), a few exact duplicates and a plane."""
    blob = rng.normal(size=(n, 3)) * np.exp(rng.uniform(-5, 0, (n, 1)))
    plane = np.column_stack([rng.uniform(-3, 3, (n // 3, 2)), np.full(n // 3, 0.5)])
    pts = np.vstack([blob, plane])
    return np.vstack([pts, pts[rng.choice(len(pts), 50, replace=False)]])  # 50 exact copies


def engine_covariances(local, k, chunk_size, merge=True):
    """Centroids and covariances of every input point through SearchPlan / run_chunks / covariances."""
    plan = NB.SearchPlan(local, merge=merge)
    cen, C = np.empty((plan.n_out, 3)), np.empty((plan.n_out, 3, 3))
    cols = plan.points.T.copy()

    def work(rows, per_scale, _):
        counts, flat = per_scale[0]
        cen[rows], C[rows] = NB.covariances(plan.points, counts, flat, cols)

    NB.run_chunks(plan, [(k, None)], chunk_size, work)
    return plan.out(cen), plan.out(C), plan


def test_knn_covariances_match_brute_force_numpy():
    """Independent route: all distances, a stable sort, np.cov (eq. 1-2) on the distinct points."""
    rng = np.random.default_rng(0)
    local = clustered(rng)
    cen, C, plan = engine_covariances(local, 12, 500)
    distinct = np.unique(local, axis=0)
    assert plan.n_duplicates == len(local) - len(distinct) == 50
    checked = 0
    for i in rng.choice(len(local), 200, replace=False):
        d = np.linalg.norm(distinct - local[i], axis=1)
        order = np.argsort(d, kind="stable")
        if np.isclose(d[order[11]], d[order[12]], rtol=0, atol=1e-12):
            continue  # a tie at the 12th neighbour: either one is right
        nb = distinct[order[:12]]
        assert np.allclose(cen[i], nb.mean(axis=0), rtol=0, atol=1e-13)
        assert np.allclose(C[i], np.cov(nb.T, bias=True), rtol=1e-10, atol=1e-15)
        checked += 1
    assert checked > 150


@pytest.mark.parametrize("merge", [True, False])
def test_chunking_does_not_change_the_result(merge):
    """Chunks of 1, 37 and 500 points and one chunk give the same covariances (whole leaves or not)."""
    local = clustered(np.random.default_rng(1))
    ref = engine_covariances(local, 10, 10**7, merge)[1]
    for size in (1, 37, 500):
        assert np.array_equal(engine_covariances(local, 10, size, merge)[1], ref)


def test_leaf_search_equals_per_point_search():
    """The leaf-batched self-kNN (all points are queries) and the per-point search (``at``-style
    queries) find neighbours at the same distances, sorted ascending."""
    local = clustered(np.random.default_rng(2))
    tree = NB.SearchPlan(local).tree
    b = tree.leaf_bounds
    assert b[0] == 0 and b[-1] == tree.n and (np.diff(b) > 0).all()
    together = tree.knn_of_leaves(0, tree.n, 15)
    alone = tree.query_leaf_positions(np.arange(tree.n), 15)
    dist = [np.linalg.norm(tree.data[i] - tree.data[:, None], axis=2) for i in (together, alone)]
    assert np.array_equal(dist[0], dist[1]) and (np.diff(dist[0], axis=1) >= 0).all()
    with pytest.raises(ValueError, match="leaf bounds"):
        tree.knn_of_leaves(1, tree.n, 15)


def test_float32_input_agrees_with_float64():
    """float32 coordinates are read as the float64 numbers they are: same neighbours, and covariances
    equal to those of the float64 cloud within float32 rounding of the coordinates."""
    rng = np.random.default_rng(3)
    xyz = clustered(rng)[:2000] + [10.0, -20.0, 5.0]
    x32 = xyz.astype(np.float32)
    n32 = NB.neighbourhoods(x32, k=8)
    assert np.array_equal(n32.indices, NB.neighbourhoods(x32.astype(np.float64), k=8).indices)
    C64 = engine_covariances(xyz, 20, 500)[1]
    C32 = engine_covariances(x32.astype(np.float64), 20, 500)[1]
    scale = np.trace(C64, axis1=1, axis2=2)[:, None, None]
    eps32 = 30.0 * np.finfo(np.float32).eps * np.abs(xyz).max()  # coordinate rounding, metres
    assert np.all(np.abs(C32 - C64) <= 4 * eps32 * np.sqrt(scale) + 1e-12)


def test_compiled_and_numpy_knn_covariances_agree(monkeypatch):
    """The compiled kNN covariance kernel and the numpy route compute eq. 1-2 alike."""
    import labkit.neighbours.moments as M

    if not M.HAVE_NUMBA:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(5)
    local = rng.normal(size=(2000, 3)) * [30.0, 20.0, 0.05]
    idx = rng.integers(0, 2000, size=(500, 12))
    cols = local.T.copy()
    cen_c, C_c = M.covariances(local, None, idx, cols)
    monkeypatch.setattr(M, "HAVE_NUMBA", False)
    cen_n, C_n = M.covariances(local, None, idx, cols)
    X = local[idx]  # direct definition
    D = X - X.mean(axis=1, keepdims=True)
    C_ref = np.einsum("cka,ckb->cab", D, D) / idx.shape[1]
    for C in (C_c, C_n):
        assert np.allclose(C, C_ref, rtol=1e-12, atol=1e-12 * np.abs(C_ref).max())
    assert np.allclose(cen_c, cen_n, rtol=0, atol=1e-12) and np.allclose(cen_c, X.mean(axis=1), atol=1e-12)


@pytest.mark.parametrize("numba", [True, False])
def test_knn_covariances_are_the_same_in_every_integer_frame(monkeypatch, numba):
    """The kNN kernel sums differences to the first neighbour: the same covariances to the bit for
    coordinates reduced to another whole-metre origin (LAS-like millimetre coordinates, UTM-sized), and
    centroids that move with the origin."""
    import labkit.neighbours.moments as M

    monkeypatch.setattr(M, "HAVE_NUMBA", M.HAVE_NUMBA and numba)
    rng = np.random.default_rng(8)
    xyz = np.round(UTM + rng.normal(size=(3000, 3)) * [40.0, 30.0, 2.0], 3)
    idx = rng.integers(0, 3000, size=(800, 20))
    out = []
    for origin in (np.round(xyz.mean(axis=0)), np.round(xyz.mean(axis=0)) + [7.0, -3.0, 1.0], np.zeros(3)):
        local = xyz - origin
        cen, C = M.covariances(local, None, idx, local.T.copy())
        out.append((cen + origin, C))
    for cen, C in out[1:]:
        assert np.array_equal(C, out[0][1])
        assert np.allclose(cen, out[0][0], rtol=0, atol=1e-8)
    X = xyz[idx] - xyz[idx].mean(axis=1, keepdims=True)  # the definition (eq. 2)
    C_ref = np.einsum("cka,ckb->cab", X, X) / idx.shape[1]
    assert np.allclose(out[0][1], C_ref, rtol=1e-9, atol=1e-12 * np.abs(C_ref).max())


def test_knn_and_radius_neighbourhoods_match_brute_force():
    rng = np.random.default_rng(9)
    xyz = rng.uniform(0, 5, (800, 3)) + UTM
    knn = NB.neighbourhoods(xyz, k=8)
    ball = NB.neighbourhoods(xyz, radius=0.6)
    assert knn.dense().shape == (800, 8) and (knn.counts == 8).all()
    for i in rng.choice(len(xyz), 30, replace=False):
        d = np.linalg.norm(xyz - xyz[i], axis=1)
        assert knn[i][0] == i and np.allclose(np.sort(d[knn[i]]), np.sort(d)[:8])
        assert set(ball[i]) == set(np.flatnonzero(d <= 0.6))


def test_masked_covariances_use_only_the_masked_points():
    rng = np.random.default_rng(6)
    X = rng.normal(size=(40, 9, 3))
    w = rng.random((40, 9)) < 0.7
    w[:, :3] = True
    cen, C = NB.masked_covariances(X, w)
    for i in range(40):
        assert np.allclose(C[i], np.cov(X[i][w[i]].T, bias=True), atol=1e-14)
        assert np.allclose(cen[i], X[i][w[i]].mean(axis=0))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: NB.check_scale(2, None, 100), "between 3"),
        (lambda: NB.check_scale(None, None, 100), "give k"),
        (lambda: NB.check_scale(5.0, None, 100), "integer"),
        (lambda: NB.check_scale(None, -1.0, 100), "radius"),
        (lambda: NB.check_chunk_size(0), "positive integer"),
        (lambda: NB.neighbourhoods(np.zeros((10, 3)), k=4, radius=1.0, chunk_size=True), "positive integer"),
    ],
)
def test_bad_arguments_raise(call, match):
    with pytest.raises(LabkitError, match=match):
        call()


def test_input_not_modified():
    xyz = clustered(np.random.default_rng(4)) + UTM
    before = xyz.copy()
    NB.neighbourhoods(xyz, k=6)
    NB.reduced(xyz)
    assert np.array_equal(xyz, before)
