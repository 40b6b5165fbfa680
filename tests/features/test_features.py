"""Tests of labkit.features: PCA normals, eigenvalues, features, orientation, robust normals."""

import numpy as np
import pytest

from labkit import features as F
from labkit.cloud import PointCloud
from labkit.core.errors import LabkitError
from labkit.features.robust import _random_triples as random_triples

UTM = np.array([600000.0, 5400000.0, 300.0])


def angle_deg(a, b, signed=False):
    c = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c if signed else np.abs(c), -1.0, 1.0)))


def tilted_plane(rng, n=4000, sigma=0.005, size=20.0):
    """Plane z = 0.2 x - 0.1 y with noise along z; returns points and the unit upward normal."""
    xy = rng.uniform(0, size, (n, 2))
    z = 0.2 * xy[:, 0] - 0.1 * xy[:, 1] + rng.normal(0, sigma, n)
    nrm = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])
    return np.column_stack([xy, z]), nrm


def sphere(rng, n=6000, r=3.0, sigma=0.002):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * (r + rng.normal(0, sigma, (n, 1))), u


def cylinder(rng, n=6000, r=1.5, length=12.0, sigma=0.002):
    """Cylinder with its axis along x; returns points and the outward unit normals."""
    phi = rng.uniform(0, 2 * np.pi, n)
    radial = np.column_stack([np.zeros(n), np.cos(phi), np.sin(phi)])
    x = rng.uniform(0, length, n)
    pts = radial * (r + rng.normal(0, sigma, (n, 1))) + np.column_stack([x, np.zeros(n), np.zeros(n)])
    return pts, radial


def brute_force_pca(xyz, i, k):
    """Independent route: sort all distances, np.cov, eigvalsh (ascending -> descending)."""
    d = np.linalg.norm(xyz - xyz[i], axis=1)
    nb = xyz[np.argsort(d, kind="stable")[:k]]
    C = np.cov(nb.T, bias=True)
    lam, V = np.linalg.eigh(C)
    return C, lam[::-1], V[:, 0]


# ----------------------------------------------------------------------------- normals vs truth


def test_plane_normals_match_analytic_normal_and_point_up():
    rng = np.random.default_rng(1)
    xyz, nrm = tilted_plane(rng)
    N = F.normals(xyz + UTM, k=20)
    assert N.shape == xyz.shape
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0)
    assert (N[:, 2] >= 0).all()
    ang = angle_deg(N, np.tile(nrm, (len(N), 1)), signed=True)
    assert np.median(ang) < 1.0 and np.percentile(ang, 99) < 5.0


def test_sphere_normals_are_radial_and_viewpoint_orients_them_inward():
    rng = np.random.default_rng(2)
    xyz, radial = sphere(rng)
    centre = np.array([10.0, -4.0, 2.0])
    pca = F.local_pca(xyz + centre, k=15, orient="viewpoint", viewpoint=centre)
    ang = angle_deg(pca.normals, -radial, signed=True)  # toward the centre = inward
    assert np.median(ang) < 1.5 and ang.max() < 10.0
    # curvature shows up as change of curvature well above a plane's
    assert np.median(pca.features.change_of_curvature) > 1e-4


def test_cylinder_normals_are_radial_without_axis_component():
    rng = np.random.default_rng(3)
    xyz, radial = cylinder(rng)
    N = F.normals(xyz, k=15, orient="none")
    ang = angle_deg(N, radial)
    assert np.median(ang) < 1.5
    assert np.median(np.abs(N[:, 0])) < 0.02  # no component along the axis


def test_per_point_viewpoint_and_outward_orientation():
    rng = np.random.default_rng(4)
    xyz, radial = cylinder(rng, n=3000)
    outside = xyz + 5.0 * radial  # a "scanner" outside every point, radially
    N = F.normals(xyz, k=15, orient="viewpoint", viewpoint=outside)
    assert (np.einsum("ij,ij->i", N, radial) > 0).all()


def test_orient_none_keeps_eighs_sign_and_up_flips_it():
    rng = np.random.default_rng(5)
    xyz, _ = tilted_plane(rng, n=1500)
    raw = F.normals(xyz, k=12, orient="none")
    up = F.normals(xyz, k=12, orient="up")
    flipped = raw[:, 2] < 0
    assert np.allclose(up[flipped], -raw[flipped]) and np.allclose(up[~flipped], raw[~flipped])


# ----------------------------------------------------------------------------- eigenvalues


def test_eigenvalues_sorted_and_match_a_plain_per_point_route():
    rng = np.random.default_rng(6)
    xyz = np.vstack([tilted_plane(rng, n=1500)[0], sphere(rng, n=1500)[0] + [30, 0, 0]]) + UTM
    k = 17
    pca = F.local_pca(xyz, k=k, orient="none")
    lam, V = pca.eigenvalues, pca.eigenvectors
    assert (np.diff(lam, axis=1) <= 0).all() and (lam >= 0).all()
    assert np.allclose(np.einsum("nij,nik->njk", V, V), np.eye(3), atol=1e-10)
    for i in rng.choice(len(xyz), 40, replace=False):
        C, lam_ref, n_ref = brute_force_pca(xyz - UTM, i, k)
        assert np.allclose(lam[i], lam_ref, rtol=1e-8, atol=1e-14)
        assert np.allclose(C @ V[i], V[i] * lam[i], atol=1e-10)  # C v = lambda v
        assert angle_deg(pca.normals[i : i + 1], n_ref[None])[0] < 1e-5
        nb = np.argsort(np.linalg.norm(xyz - xyz[i], axis=1), kind="stable")[:k]
        assert np.allclose(pca.centroids[i], xyz[nb].mean(axis=0), atol=1e-8)


def test_eig_does_not_sort_but_eigh_does():
    # the registration study's pitfall: np.linalg.eig returns eigenvalues in no guaranteed order
    C = np.array([[1.0, 0, 0], [0, 5.0, 0], [0, 0, 3.0]])
    assert list(np.linalg.eig(C)[0]) == [1.0, 5.0, 3.0]
    lam, _ = F.sorted_eigh(C[None])
    assert list(lam[0]) == [5.0, 3.0, 1.0]


def test_chunked_equals_unchunked_and_utm_equals_local():
    rng = np.random.default_rng(7)
    xyz, _ = sphere(rng, n=2500)
    a = F.local_pca(xyz + UTM, k=12)
    b = F.local_pca(xyz + UTM, k=12, chunk_size=97)
    c = F.local_pca(xyz, k=12)
    assert np.array_equal(a.eigenvalues, b.eigenvalues) and np.array_equal(a.normals, b.normals)
    assert np.allclose(a.eigenvalues, c.eigenvalues, rtol=1e-6, atol=1e-12)
    assert angle_deg(a.normals, c.normals).max() < 1e-4
    assert np.allclose(a.centroids - UTM, c.centroids, atol=1e-8)


def test_at_computes_only_selected_points_with_whole_cloud_neighbours():
    rng = np.random.default_rng(18)
    xyz = sphere(rng, n=2000)[0] + UTM
    at = rng.choice(len(xyz), 150, replace=False)
    full = F.local_pca(xyz, k=12, orient="viewpoint", viewpoint=UTM)
    part = F.local_pca(xyz, k=12, orient="viewpoint", viewpoint=UTM, at=at)
    assert np.array_equal(part.eigenvalues, full.eigenvalues[at]) and np.array_equal(part.normals, full.normals[at])
    assert F.normals(xyz, k=12, at=[-1]).shape == (1, 3)
    for bad in ([len(xyz)], [[1, 2]], [0.5], []):
        with pytest.raises(LabkitError, match="at "):
            F.local_pca(xyz, k=12, at=bad)


def test_input_not_modified_and_pointcloud_accepted():
    rng = np.random.default_rng(8)
    xyz = tilted_plane(rng, n=500)[0] + UTM
    before = xyz.copy()
    N1 = F.normals(xyz, k=10)
    N2 = F.normals(PointCloud(xyz), k=10)
    assert np.array_equal(xyz, before) and np.array_equal(N1, N2)


# ----------------------------------------------------------------------------- neighbourhoods


def test_radius_pca_marks_small_neighbourhoods():
    xyz = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0.001], [50, 50, 50.0]])
    pca = F.local_pca(xyz, radius=0.5)
    assert pca.counts.tolist() == [4, 4, 4, 4, 1]
    assert np.isnan(pca.normals[4]).all() and not pca.valid[4] and pca.valid[:4].all()
    assert np.isnan(pca.noise[4])


# ----------------------------------------------------------------------------- features and noise


def test_features_of_line_plane_and_volume():
    rng = np.random.default_rng(10)
    t = rng.uniform(0, 10, 1500)
    line = np.column_stack([t, 0.5 * t, -0.2 * t]) + rng.normal(0, 0.002, (1500, 3))
    plane = tilted_plane(rng, n=1500, sigma=0.002, size=8.0)[0]
    volume = rng.uniform(0, 3, (1500, 3))
    for pts, dominant in ((line, 0), (plane, 1), (volume, 2)):
        f = F.local_pca(pts, k=30).features
        medians = np.median(np.column_stack([f.linearity, f.planarity, f.scattering]), axis=0)
        assert np.argmax(medians) == dominant and np.sort(medians)[-1] > np.sort(medians)[-2] + 0.1
        # random sampling makes small kNN neighbourhoods elongated: a plane point often looks
        # line-like, hence "most", not "all" (notebook 04 shows it)
        votes = np.bincount(f.dominant(), minlength=3) / len(pts)
        assert np.argmax(votes) == dominant and votes[dominant] > 0.5
        assert np.allclose(f.linearity + f.planarity + f.scattering, 1.0)
    flin = F.local_pca(line, k=20).features
    assert np.median(flin.linearity) > 0.95 and np.median(flin.anisotropy) > 0.99


def test_eigen_features_closed_form_values():
    f = F.eigen_features(np.array([[3.0, 2.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]))
    e = np.array([3, 2, 1]) / 6
    assert np.isclose(f.linearity[0], (e[0] - e[1]) / e[0])
    assert np.isclose(f.omnivariance[0], np.cbrt(e.prod()))
    assert np.isclose(f.eigenentropy[0], -(e * np.log(e)).sum())
    assert np.isclose(f.eigenentropy[1], np.log(3)) and np.isclose(f["scattering"][1], 1.0)
    assert np.isnan(f.planarity[2]) and np.isnan(f.eigenentropy[2])
    assert set(f.keys()) >= {"linearity", "planarity", "scattering", "change_of_curvature"}


def test_local_noise_recovers_sigma_monte_carlo():
    rng = np.random.default_rng(11)
    sigma = 0.01
    xyz, nrm = tilted_plane(rng, n=6000, sigma=sigma / nrm_z(), size=25.0)
    noise = F.local_noise(xyz + UTM, k=30)
    assert abs(np.median(noise) / sigma - 1) < 0.1
    assert np.isclose(np.mean(noise**2) / sigma**2, 1.0, atol=0.1)  # m / (m - 3) makes it unbiased


def nrm_z():
    """z component of the tilted plane's normal: vertical noise sigma_z gives sigma_n = sigma_z n_z."""
    return 1.0 / np.linalg.norm([-0.2, 0.1, 1.0])


def test_multiscale_picks_least_entropy_and_single_scale_equals_local_pca():
    rng = np.random.default_rng(12)
    xyz = np.vstack([tilted_plane(rng, n=1500)[0], rng.uniform(0, 3, (500, 3)) + [30, 0, 0]])
    ms = F.multiscale_features(xyz, scales=(8, 16, 32))
    H = ms.entropy
    assert H.shape == (len(xyz), 3)
    assert np.array_equal(ms.best, np.argmin(H, axis=1))
    assert np.allclose(ms.pca.eigenvalues, ms.eigenvalues[np.arange(len(xyz)), ms.best])
    one = F.multiscale_features(xyz, scales=(16,))
    ref = F.local_pca(xyz, k=16)
    assert np.allclose(one.pca.eigenvalues, ref.eigenvalues) and np.allclose(one.pca.normals, ref.normals)
    rad = F.multiscale_features(xyz, scales=(0.5, 1.0), by="radius")
    assert np.allclose(rad.eigenvalues[:, 1], F.local_pca(xyz, radius=1.0).eigenvalues, equal_nan=True)
    assert "chosen" in ms.summary()


# ----------------------------------------------------------------------------- robust normals


def plane_with_outliers(rng, n=3000, share=0.35):
    xyz, nrm = tilted_plane(rng, n=n, sigma=0.003, size=12.0)
    bad = rng.random(n) < share
    xyz[bad] += np.outer(rng.uniform(0.05, 0.6, bad.sum()), nrm)  # low vegetation / clutter above
    return xyz, nrm, bad


@pytest.mark.parametrize("threshold", [None, 0.01])
def test_robust_normals_beat_pca_with_gross_outliers(threshold):
    rng = np.random.default_rng(13)
    xyz, nrm, bad = plane_with_outliers(rng)
    rob = F.robust_normals(xyz + UTM, k=30, threshold=threshold, rng=1)
    pca = F.local_pca(xyz + UTM, k=30)
    truth = np.tile(nrm, (len(xyz), 1))
    a_rob = angle_deg(rob.normals[~bad], truth[~bad], signed=True)
    a_pca = angle_deg(pca.normals[~bad], truth[~bad], signed=True)
    assert np.median(a_rob) < 1.0 and np.median(a_pca) > 3 * np.median(a_rob)
    assert np.percentile(a_rob, 90) < 0.5 * np.percentile(a_pca, 90)
    assert np.median(rob.noise[~bad]) < 0.006 < np.median(pca.noise[~bad])
    assert abs(np.median(rob.inliers) / 30 - 0.65) < 0.15
    again = F.robust_normals(xyz + UTM, k=30, threshold=threshold, rng=1)
    assert np.array_equal(rob.normals, again.normals)  # reproducible from rng


def test_random_triples_are_distinct_and_uniform():
    rng = np.random.default_rng(14)
    tri = random_triples(rng, (20000,), 5)
    assert (tri[:, 0] != tri[:, 1]).all() and (tri[:, 0] != tri[:, 2]).all() and (tri[:, 1] != tri[:, 2]).all()
    counts = np.bincount(np.sort(tri, axis=1) @ [25, 5, 1], minlength=125)
    counts = counts[counts > 0]
    assert len(counts) == 10 and counts.min() > 0.8 * counts.mean()  # all C(5,3) sets, evenly


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"k": 2}, "between 3"),
        ({"k": 51}, "between 3"),
        ({"k": 4.5}, "integer"),
        ({"k": None}, "give k"),
        ({"radius": -1.0}, "radius"),
        ({"orient": "down"}, "orient"),
        ({"orient": "viewpoint"}, "needs viewpoint"),
        ({"orient": "viewpoint", "viewpoint": [0, 0]}, "shape"),
        ({"orient": "up", "viewpoint": [0, 0, 1]}, "only used"),
        ({"chunk_size": 0}, "chunk_size"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    xyz = np.random.default_rng(15).uniform(0, 1, (50, 3))
    with pytest.raises(LabkitError, match=match):
        F.local_pca(xyz, **kwargs)


def test_bad_points_raise():
    xyz = np.random.default_rng(16).uniform(0, 1, (50, 3))
    xyz[7, 1] = np.nan
    with pytest.raises(LabkitError, match="NaN"):
        F.normals(xyz)
    with pytest.raises(LabkitError, match="shape"):
        F.normals(np.zeros((10, 2)))
    with pytest.raises(LabkitError, match="between 3"):
        F.normals(np.zeros((5, 3)), k=20)
    with pytest.raises(LabkitError, match="sorted"):
        F.eigen_features([[1.0, 2.0, 3.0]])
    with pytest.raises(LabkitError, match="outlier_ratio"):
        F.robust_normals(np.random.default_rng(0).uniform(size=(40, 3)), k=10, outlier_ratio=1.5)


def test_reports_render():
    rng = np.random.default_rng(17)
    xyz, _ = tilted_plane(rng, n=300)
    for res in (F.local_pca(xyz, k=10), F.neighbourhoods(xyz, k=5), F.robust_normals(xyz, k=10, rng=0)):
        assert res.summary() and "<table>" in res._repr_html_()


@pytest.mark.slow
def test_real_tls_pca_matches_brute_force(realdata):
    """Real TLS scan (clustered density, 1 mm grid: many ties): the compiled kNN + PCA against
    an independent route (all distances, np.cov, eigh) at 300 random points of a 60,000-point crop."""
    from labkit.io import read_cloud

    xyz = read_cloud(realdata / "tls" / "TLS_scan_vz400i.laz").xyz[:60000]
    distinct = np.unique(xyz, axis=0)  # the PCA merges exact duplicates
    pca = F.local_pca(xyz, k=20, orient="none")
    assert pca.n_duplicates == len(xyz) - len(distinct)
    rng = np.random.default_rng(0)
    for i in rng.choice(len(xyz), 300, replace=False):
        d = np.linalg.norm(distinct - xyz[i], axis=1)
        kth = np.sort(d)[19]
        if np.sum(np.isclose(d, kth, rtol=0, atol=1e-12)) > 1:
            continue  # a tie at the 20th distance: either neighbour is right
        nb = distinct[np.argsort(d, kind="stable")[:20]]
        lam, V = np.linalg.eigh(np.cov(nb.T, bias=True))
        assert np.allclose(pca.eigenvalues[i], lam[::-1], rtol=1e-7, atol=1e-13)
        if lam[1] > 1e-6 * lam[2]:
            assert abs(abs(pca.normals[i] @ V[:, 0]) - 1.0) < 1e-8


# --------------------------------------------------------------------------- PCA at points of a kd-tree one has
def _distinct_brute_force_pca(points, at, k):
    """Normals (up) and noise at ``at`` from numpy alone: distinct points, cKDTree neighbours, np.linalg.eigh."""
    from scipy.spatial import cKDTree

    distinct = np.unique(points, axis=0)
    nb = distinct[cKDTree(distinct).query(points[at], k)[1]]  # (m, k, 3)
    D = nb - nb.mean(axis=1, keepdims=True)
    lam, V = np.linalg.eigh(np.einsum("mki,mkj->mij", D, D) / k)  # ascending
    n = V[:, :, 0] * np.sign(V[:, 2:3, 0])
    return n, np.sqrt(k * lam[:, 0] / (k - 3))


def test_pca_at_equals_local_pca_and_a_numpy_pca_on_a_tree_of_utm_points():
    from labkit.neighbours.kdtree import KDTree

    rng = np.random.default_rng(21)
    xy = rng.uniform(0, 30, (3000, 2))
    pts = np.c_[xy, 0.3 * np.sin(xy[:, 0] / 3) + rng.normal(0, 0.004, 3000)] + UTM
    pts[::40] = pts[7::40][: len(pts[::40])]  # exact copies: merged, as local_pca's default
    at = np.r_[rng.choice(3000, 400, replace=False), -1, 7]
    origin = pts[0].round()
    for k in (4, 10, 25):
        n, noise = F.pca_at(KDTree(pts - origin, merge_duplicates=True), at, k, chunk_size=97)
        ref = F.local_pca(pts, k=k, at=at)
        np.testing.assert_allclose(n, ref.normals, atol=1e-9)
        np.testing.assert_allclose(noise, ref.noise, rtol=1e-9)
        bn, bnoise = _distinct_brute_force_pca(pts, at, k)
        np.testing.assert_allclose(n, bn, atol=1e-8)  # the same sign: up
        assert (n[:, 2] >= 0).all()
        np.testing.assert_allclose(noise, bnoise, rtol=1e-6)
    # a tree that keeps the copies equals duplicates='keep'; k = 3 gives a normal but no noise (redundancy 0)
    n, noise = F.pca_at(KDTree(pts - origin), at, 3)
    np.testing.assert_allclose(n, F.local_pca(pts, k=3, at=at, duplicates="keep").normals, atol=1e-9)
    assert np.isfinite(n[:, 0]).mean() > 0.9 and np.isnan(noise).all()
    assert np.isnan(n[-1]).all()  # point 7: three neighbours, one of them its copy (a line)


def test_pca_at_shows_each_chunks_neighbours_as_scipy_finds_them():
    """``seen(rows, nb)``: every position of ``at`` once, with its k nearest distinct points (scipy's distances)."""
    from scipy.spatial import cKDTree

    from labkit.neighbours.kdtree import KDTree

    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(0, 10, (800, 2)), rng.normal(0, 0.01, 800)]
    pts[::50] = pts[1::50][: len(pts[::50])]  # exact copies: merged
    tree = KDTree(pts, merge_duplicates=True)
    at = rng.choice(800, 300, replace=False)
    got = {}
    n, _ = F.pca_at(tree, at, 8, chunk_size=70, seen=lambda rows, nb: got.update(zip(rows.tolist(), nb.copy())))
    assert sorted(got) == list(range(len(at)))
    nb = np.array([got[i] for i in range(len(at))])
    dist = np.linalg.norm(tree.data[nb] - pts[at][:, None, :], axis=2)
    distinct = np.unique(pts, axis=0)
    np.testing.assert_allclose(dist, cKDTree(distinct).query(pts[at], 8)[0], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(n, F.pca_at(tree, at, 8)[0])  # the same normals with or without it


def test_pca_at_marks_a_line_and_reports_chunks_and_refuses_bad_arguments():
    from labkit.neighbours.kdtree import KDTree

    line = np.c_[np.arange(50.0), 2 * np.arange(50.0), np.zeros(50)]
    plane = np.c_[np.random.default_rng(0).uniform(0, 1, (50, 2)) + 100, np.zeros(50)]
    tree = KDTree(np.r_[line, plane], merge_duplicates=True)
    done = []
    n, noise = F.pca_at(tree, np.arange(100), 5, chunk_size=30, step=done.append)
    assert done == [30, 30, 30, 10]
    assert np.isnan(n[:50]).all() and np.isnan(noise[:50]).all()  # a line has no plane
    np.testing.assert_allclose(n[50:], np.tile([0, 0, 1.0], (50, 1)), atol=1e-12)
    for at, k, match in (([0, 100], 5, "outside"), ([0.5], 5, "indices"), ([], 5, "empty"), ([0], 2, "k must"),
                         ([0], 101, "k must"), ([0], 5.0, "integer")):
        with pytest.raises(LabkitError, match=match):
            F.pca_at(tree, at, k)
