"""The surface test of the point selection (labkit.registration.selection)."""

import numpy as np
import pytest

from labkit.features import local_pca
from labkit.registration import selection
from labkit.registration.matching.local_surface import Geometry
from labkit.registration.selection import MAX_SCATTER, SMOOTH_NOISE, surface_mask


def _scene(rng):
    """Ground on gentle hills, a steep curved bank, a roof step, a crown of leaves; some exact copies."""
    xy = rng.uniform(0, 30, (2500, 2))
    z = 0.6 * np.sin(xy[:, 0] / 4) + 0.3 * np.cos(xy[:, 1] / 3) + 2.0 * (xy[:, 0] > 22)
    ground = np.column_stack([xy, z + rng.normal(0, 0.01, len(xy))])
    crown = rng.normal([10, 12, 7], 1.2, (600, 3))
    pts = np.vstack([ground, crown]) + [600000.0, 5400000.0, 300.0]  # UTM-sized
    return np.vstack([pts, pts[:40]])  # exact duplicates count once


def _two_searches(points, k=20):
    """The test by its two separate passes: eigenvalues of the local PCA, noise of the local quadric."""
    local = points - points.mean(axis=0)
    pca = local_pca(local, k=k, orient="none")
    lam = np.sort(np.clip(pca.eigenvalues, 0, None), axis=1)
    _, noise = Geometry(local, k, quadric=True).at(np.arange(len(local)), need_noise=True)
    noise = np.where(np.isfinite(noise), noise, np.sqrt(lam[:, 0]))
    with np.errstate(invalid="ignore", divide="ignore"):
        scatter = noise / np.sqrt(lam[:, 1])
    return pca.valid & ((noise <= SMOOTH_NOISE) | (scatter <= MAX_SCATTER))


@pytest.mark.parametrize("chunk", [selection.CHUNK, 257])
def test_one_search_in_chunks_gives_the_two_pass_mask(monkeypatch, chunk):
    pts = _scene(np.random.default_rng(3))
    monkeypatch.setattr(selection, "CHUNK", chunk)  # many chunks: the seams change nothing
    keep = surface_mask(pts)
    np.testing.assert_array_equal(keep, _two_searches(pts))
    assert keep[:2500].mean() > 0.95 and keep[2500:3100].mean() < 0.2  # ground kept, crown left out
    np.testing.assert_array_equal(keep[-40:], keep[:40])  # a copy gets its original's answer


def test_input_not_modified():
    pts = _scene(np.random.default_rng(4))
    before = pts.copy()
    surface_mask(pts)
    np.testing.assert_array_equal(pts, before)


@pytest.mark.parametrize("surface", ["plane", "quadric"])
def test_icp_reuses_the_selection_neighbourhoods_with_the_same_result(monkeypatch, surface):
    from labkit.neighbours import kdtree, treecache
    from labkit.registration import icp
    from labkit.registration.matching import local_surface

    target = _scene(np.random.default_rng(5))
    source = _scene(np.random.default_rng(6)) - [0.03, -0.02, 0.01]
    searched = []
    real = kdtree.KDTree.query_leaf_positions

    def counting(self, pos, k, workers=1):
        searched.append(len(pos))
        return real(self, pos, k, workers)

    monkeypatch.setattr(kdtree.KDTree, "query_leaf_positions", counting)
    decomposed = []  # rows of local PCA (covariance and eigen-decomposition) computed
    pca_rows = local_surface._pca_rows

    def counting_pca(tree, cols, nb, k):
        decomposed.append(len(nb))
        return pca_rows(tree, cols, nb, k)

    monkeypatch.setattr(local_surface, "_pca_rows", counting_pca)
    runs = []
    for limit in (selection.KEEP_NEIGHBOURS, 0):  # the neighbours of the surface test kept, and not
        monkeypatch.setattr(selection, "KEEP_NEIGHBOURS", limit)
        treecache.forget()
        searched.clear()
        decomposed.clear()
        runs.append((icp(source, target, surface=surface, rng=0), sum(searched), sum(decomposed)))
    (reused, n_reused, pca_reused), (own, n_own, pca_own) = runs
    assert reused.selection.rule == "surface points"
    assert n_reused < 0.5 * n_own  # ICP searched only next to the points left out
    # ICP decomposed only those too: the selection's PCA of the two whole clouds (about 6,300 points) served the rest
    assert pca_reused < pca_own - 0.5 * (len(source) + len(target))
    # the covariances sum differences of the coordinates: the same normals in the selection's frame and ICP's
    np.testing.assert_array_equal(reused.matrix, own.matrix)
    np.testing.assert_allclose(reused.covariance, own.covariance, rtol=1e-9, atol=1e-18)
    assert reused.message == own.message and reused.iterations == own.iterations
    np.testing.assert_array_equal(reused.correspondences.rule, own.correspondences.rule)
    treecache.forget()


def test_the_plane_from_the_kept_pca_holds_no_neighbours_of_every_point():
    """Where the selection left points out, the points next to them are searched again among the kept ones;
    the plane from the kept PCA needs the neighbours of those rows only, not an (m, k) array for all m (on
    the real TLS halves 40 MB per cloud for 23,000 rows searched again), and gives the normals of a new search."""
    import tracemalloc

    from labkit.core.frame import local_origin
    from labkit.neighbours import treecache
    from labkit.registration.matching.local_surface import _leaf_geometry

    treecache.forget()
    source, target = _scene(np.random.default_rng(6)), _scene(np.random.default_rng(5))
    _, tgt, sel = selection.select_points(source, target)
    assert sel.rule == "surface points" and sel.used_target < len(target)
    k = 20
    known = treecache.kept_neighbours(tgt, k)
    tree = treecache.local_tree(tgt, local_origin(tgt), True)  # the selected points' tree, cut by the selection
    cols, pos = np.ascontiguousarray(tree.data.T), np.arange(tree.n)
    assert known is not None and not known.gather(tree, pos).all()  # some rows are searched again

    def peak(**kw):
        tracemalloc.start()
        try:
            out = _leaf_geometry(tree, cols, pos, k, **kw)
            return out, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    (n, noise, variation, _), from_kept = peak(known=known)
    (n0, noise0, variation0, _), searched = peak()
    np.testing.assert_array_equal(n, n0)
    np.testing.assert_array_equal(noise, noise0)
    np.testing.assert_array_equal(variation, variation0)
    assert from_kept < searched - 0.5 * tree.n * k * 8  # the (m, k) neighbours of the new search are not held
    treecache.forget()
