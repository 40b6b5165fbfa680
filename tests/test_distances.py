"""labkit.distances.distances_before_after against a brute-force route (numpy nearest neighbours, eigh normals).

Agreement with labkit's own plain route (features.normals + point_to_plane_distance) on a larger village, the
reuse of ICP's tree and the progress reports: tests/test_icp_sampling.py and tests/test_progress.py; bad input:
tests/test_bad_input.py and tests/test_compare.py.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labkit.distances import distances_before_after
from labkit.transforms import make_transform

UTM = np.array([612_000.0, 5_401_000.0, 290.0])


def _rotation_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def epochs():
    """A wavy surface at UTM size with exact copies; the source 3 cm higher, turned by 0.2 deg and shifted."""
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 12, (900, 2))
    tgt = np.c_[xy, 0.3 * np.sin(xy[:, 0]) + 0.2 * np.cos(0.7 * xy[:, 1]) + rng.normal(0, 0.002, 900)] + UTM
    tgt[::30] = tgt[5::30][: len(tgt[::30])]  # exact copies: merged before the normals
    src = tgt[rng.choice(900, 300, replace=False)] + rng.normal(0, 0.01, (300, 3)) * [1, 1, 0] + [0.05, -0.04, 0.03]
    R, centre = _rotation_z(0.2), UTM + [6.0, 6.0, 0.0]  # turned about the middle of the area
    T = make_transform(R, centre - R @ centre + [0.01, 0.02, -0.03])
    return src, tgt, T


def _apply(T, pts):
    return pts @ T[:3, :3].T + T[:3, 3]


def _nearest(p, q):
    """Index of the nearest q of every p, from all pairwise distances (small clouds only)."""
    return np.argmin(((p[:, None, :] - q[None, :, :]) ** 2).sum(axis=2), axis=1)


def _brute_normals(q, k):
    """Up-oriented PCA normals of the k nearest distinct points of every q (np.linalg.eigh); NaN on a line."""
    distinct = np.unique(q, axis=0)
    nb = distinct[cKDTree(distinct).query(q, k)[1]]
    D = nb - nb.mean(axis=1, keepdims=True)
    lam, V = np.linalg.eigh(np.einsum("mki,mkj->mij", D, D) / k)
    n = V[:, :, 0] * np.where(V[:, 2:3, 0] < 0, -1.0, 1.0)
    n[lam[:, 1] <= 1e-12 * lam[:, 2]] = np.nan
    return n


def _brute_plane(src, tgt, k, T=None):
    p = src if T is None else _apply(T, src)
    p, q = p - UTM, tgt - UTM
    j = _nearest(p, q)
    return np.einsum("ij,ij->i", _brute_normals(q, k)[j], p - q[j])


def test_cloud_to_cloud_equals_the_smallest_pairwise_distance(epochs):
    src, tgt, T = epochs
    change = distances_before_after(src, tgt, T, kind="cloud_to_cloud")
    for got, p in ((change.before, src), (change.after, _apply(T, src))):
        d2 = (((p - UTM)[:, None, :] - (tgt - UTM)[None, :, :]) ** 2).sum(axis=2)
        np.testing.assert_allclose(got, np.sqrt(d2.min(axis=1)), rtol=0, atol=1e-9)
    assert change.n_undetermined == 0 and change.kind == "cloud_to_cloud"


@pytest.mark.parametrize("k", [3, 8, 20])
def test_point_to_plane_equals_brute_force_plane_distances(epochs, k):
    src, tgt, T = epochs
    change = distances_before_after(src, tgt, T, k=k)
    before, after = _brute_plane(src, tgt, k), _brute_plane(src, tgt, k, T)
    for got, ref in ((change.before, before), (change.after, after)):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6)  # offsets kept in float32: micrometres
    assert np.isfinite(change.after).all()  # k = 3 too: three distinct points span a plane
    assert abs(np.median(change.before)) > 0.02 > abs(np.median(change.after))  # the transform removes the 3 cm


def test_given_normals_any_length_and_stats_over_the_points_with_a_distance(epochs):
    src, tgt, T = epochs
    n = _brute_normals(tgt - UTM, 10)
    n[:50] = np.nan  # unknown normals: NaN distances, left out of the statistics and counted
    change = distances_before_after(src, tgt, T, target_normals=5.0 * n)
    p = _apply(T, src) - UTM
    j = _nearest(p, tgt - UTM)
    ref = np.einsum("ij,ij->i", n[j], p - (tgt - UTM)[j])
    np.testing.assert_allclose(change.after, ref, rtol=0, atol=2e-6, equal_nan=True)
    ok = np.isfinite(ref)
    assert 0 < change.n_undetermined == int((~ok).sum())
    s = change.stats()
    assert s["n"] == ok.sum()
    np.testing.assert_allclose([s["median_abs"], s["rms"], s["mean"], s["q95_abs"]],
                               [np.median(np.abs(ref[ok])), np.sqrt(np.mean(ref[ok] ** 2)), np.mean(ref[ok]),
                                np.quantile(np.abs(ref[ok]), 0.95)], atol=2e-6)


def test_a_target_line_gives_nan_distances_next_to_it():
    rng = np.random.default_rng(4)
    plane = np.c_[rng.uniform(0, 5, (300, 2)), np.zeros(300)]
    line = np.c_[np.linspace(20, 25, 40), np.full(40, 20.0), np.zeros(40)]  # a wire: no plane
    tgt = np.r_[plane, line] + UTM
    src = np.r_[plane[:20], line[5:10]] + [0.01, 0.01, 0.05] + UTM
    change = distances_before_after(src, tgt, np.eye(4), k=6)
    assert np.isnan(change.after[20:]).all() and change.n_undetermined == 5
    np.testing.assert_allclose(change.after[:20], 0.05, atol=1e-6)
