"""labkit.change.distances.distances_before_after against a brute-force route (numpy nearest neighbours, eigh normals).

Agreement with labkit's own plain route (features.normals + point_to_plane_distance) on a larger village, the
reuse of ICP's tree and the progress reports: tests/test_icp_sampling.py and tests/test_progress.py; bad input:
tests/change/test_bad_input_distances.py and tests/registration/test_compare.py.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labkit.change.distances import distances_before_after
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


@pytest.mark.parametrize("kind, k", [("point_to_plane", 10), ("point_to_plane", 5), ("cloud_to_cloud", 10)])
def test_coverage_mask_is_the_rule_computed_with_scipy(epochs, kind, k):
    """covered = offset along the tangent plane (horizontal without a normal) <= 1.5 spacings of the nearest
    target point, the spacing being its 6th distinct neighbour's distance, floored at half the median (scipy).
    With k = 10 the spacing comes from the normals' own neighbour search, with k = 5 (fewer than 7
    neighbours) and without normals from a search of its own."""
    from labkit.change.distances import COVERAGE_FACTOR, COVERAGE_K

    src, tgt, T = epochs
    src = np.r_[src, src[:40] + [20.0, 0.0, 0.0]]  # 40 points beyond the target's edge
    change = distances_before_after(src, tgt, T, kind=kind, k=k)
    p, q = _apply(T, src) - UTM, tgt - UTM
    j = _nearest(p, q)
    distinct = np.unique(q, axis=0)
    spacing = cKDTree(distinct).query(q[j], k=COVERAGE_K + 1)[0][:, -1]
    spacing = np.maximum(spacing, 0.5 * np.median(spacing[np.unique(j, return_index=True)[1]]))
    off = p - q[j]
    along = np.hypot(off[:, 0], off[:, 1])
    if kind == "point_to_plane":
        n = _brute_normals(q, k)[j]
        along = np.linalg.norm(off - np.einsum("ij,ij->i", n, off)[:, None] * n, axis=1)
    ratio = along / (COVERAGE_FACTOR * spacing)
    clear = np.abs(ratio - 1) > 1e-6  # not on the threshold itself (normals from two eigen-solvers)
    assert clear.sum() > 0.98 * len(src)
    np.testing.assert_array_equal(change.covered[clear], ratio[clear] <= 1)
    assert 40 <= change.n_outside < 60 and not change.covered[-40:].any()


# --------------------------------------------------------------------------- coverage (real data)
def _halves(xyz, shift, seed):
    half = np.random.default_rng(seed).uniform(size=len(xyz)) < 0.5
    return xyz[half] - shift, xyz[~half]


def _coverage_check(src, tgt, shift, cut, margin):
    """Target cut at x = cut: moved source points well inside are covered, well outside are not (an independent
    route: scipy's horizontal nearest-neighbour distance to the cut target), and the statistics use the covered."""
    tgt = tgt[tgt[:, 0] < cut]
    change = distances_before_after(src, tgt, make_transform(np.eye(3), shift))
    moved = src + shift
    gap = cKDTree(tgt[:, :2]).query(moved[:, :2], k=1)[0]
    inside, far = (moved[:, 0] < cut - margin) & (gap < margin / 4), gap > margin
    assert inside.sum() > 1000 and far.sum() > 1000
    return change, inside, far


def test_real_als_halves_coverage_keeps_the_rms_after_honest(realdata):
    """Real sparse ALS (IGN, 0.3 m spacing) split into two epochs with a known shift; the target cut in half. The
    points beyond the cut are counted apart, so the RMS after is the covered part's and below the RMS before."""
    from labkit.io import read_cloud

    xyz = read_cloud(realdata / "als" / "las_with_several_extra_byte_bloc.laz").xyz[::4]
    shift = np.array([0.3, -0.2, 0.1])
    src, tgt = _halves(xyz, shift, 0)
    change, inside, far = _coverage_check(src, tgt, shift, float(np.median(tgt[:, 0])), 3.0)
    assert change.covered[inside].mean() > 0.995 and change.covered[far].mean() < 0.005
    n_out = change.n_outside
    assert 0.3 * len(src) < n_out < 0.7 * len(src) and change.stats("after")["n"] + n_out >= len(src) - 10
    text = change.summary()
    assert f"{n_out} points" in text and "outside its coverage" in text and "covered by the target" in text
    after, before, everything = change.stats("after"), change.stats("before"), change.stats("after", "all")
    assert after["rms"] < before["rms"] and after["rms"] < 0.5 * everything["rms"]
    # without the mask: every point, as before
    plain = distances_before_after(src, tgt[tgt[:, 0] < np.median(tgt[:, 0])], make_transform(np.eye(3), shift),
                                   coverage=False)
    assert plain.covered is None and plain.n_outside == 0
    assert np.isclose(plain.stats("after")["rms"], everything["rms"])


def test_real_tls_coverage_adapts_to_dense_spacing(realdata):
    """A real TLS scan (mm spacing, walls and ground) split the same way: the rule follows the local spacing."""
    from labkit.io import read_cloud

    xyz = read_cloud(realdata / "tls" / "TLS_scan_vz400i.laz").xyz[::10]
    shift = np.array([0.02, -0.01, 0.015])
    src, tgt = _halves(xyz, shift, 1)
    change, inside, far = _coverage_check(src, tgt, shift, 0.0, 0.5)
    assert change.covered[inside].mean() > 0.99 and change.covered[far].mean() < 0.1
