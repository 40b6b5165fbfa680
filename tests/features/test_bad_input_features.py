"""Bad and unusual input to the local geometry: degenerate neighbourhoods and exact duplicates.

Each case states the exact outcome: NaN normals with ``valid=False`` where the
data do not determine a plane, the same normals as the de-duplicated cloud where
points are repeated, or a LabkitError naming the problem.
"""

import numpy as np
import pytest

from labkit import features as F
from labkit.core.errors import LabkitError
from labkit.registration.matching.match import match

UTM = np.array([600000.0, 5400000.0, 300.0])


def plane(rng, n=400, size=5.0, sigma=0.002):
    """Tilted plane z = 0.1 x + 0.05 y with noise; the unit upward normal."""
    xy = rng.uniform(0, size, (n, 2))
    z = 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + rng.normal(0, sigma, n)
    nrm = np.array([-0.1, -0.05, 1.0])
    return np.column_stack([xy, z]), nrm / np.linalg.norm(nrm)


def angle_deg(a, b):
    c = np.abs(a @ b) / np.linalg.norm(a, axis=-1)
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


# ----------------------------------------------------------------------------- degenerate -> NaN


def _identical(rng):
    return np.tile([3.0, -2.0, 1.0], (30, 1))


def _collinear(rng):
    return np.outer(rng.uniform(0, 10, 40), [1.0, 2.0, -0.5]) + [1.0, 1.0, 1.0]


def _collinear_utm(rng):
    return _collinear(rng) + UTM


def _two_locations(rng):
    return np.repeat([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]], 20, axis=0)


def _collinear_repeated(rng):
    return np.repeat(_collinear(rng)[:10], 4, axis=0)


@pytest.mark.parametrize(
    "make", [_identical, _collinear, _collinear_utm, _two_locations, _collinear_repeated],
    ids=["identical", "collinear", "collinear_utm", "two_locations", "collinear_repeated"],
)  # fmt: skip
@pytest.mark.parametrize("duplicates", ["merge", "keep"])
def test_degenerate_neighbourhoods_give_nan_normals_and_invalid(make, duplicates):
    xyz = make(np.random.default_rng(0))
    pca = F.local_pca(xyz, k=5, duplicates=duplicates)
    assert not pca.valid.any()
    assert np.isnan(pca.normals).all() and np.isnan(pca.eigenvectors[:, :, 2]).all()
    assert np.isnan(pca.noise).all()  # no plane, no spread along its normal
    assert np.isnan(F.normals(xyz, k=5, duplicates=duplicates)).all()
    # the other two eigenvectors and the eigenvalues are still reported
    assert np.isfinite(pca.eigenvalues).all() and np.isfinite(pca.eigenvectors[:, :, :2]).all()


def test_a_line_inside_a_plane_cloud_is_invalid_only_where_the_neighbourhood_is_a_line():
    rng = np.random.default_rng(1)
    xyz, nrm = plane(rng)
    line = np.outer(np.linspace(0, 1, 30), [1.0, 0.0, 0.0]) + [50.0, 50.0, 0.0]  # far away: own neighbourhoods
    pca = F.local_pca(np.vstack([xyz, line]), k=8)
    assert pca.valid[: len(xyz)].all() and not pca.valid[len(xyz) :].any()
    assert np.median(angle_deg(pca.normals[: len(xyz)], nrm)) < 2.0


def test_multiscale_and_robust_normals_also_mark_degenerate():
    xyz = _collinear(np.random.default_rng(2))
    ms = F.multiscale_features(xyz, scales=(5, 8))
    assert np.isnan(ms.pca.normals).all() and not ms.pca.valid.any()
    with pytest.raises(LabkitError, match="distinct points"):
        F.robust_normals(_identical(None), k=5)


# ----------------------------------------------------------------------------- exact duplicates


@pytest.mark.parametrize("copies", [2, 3])
def test_duplicated_cloud_gives_the_normals_of_the_distinct_points(copies):
    rng = np.random.default_rng(3)
    xyz, _ = plane(rng)
    doubled = np.tile(xyz, (copies, 1))[rng.permutation(copies * len(xyz))]
    pca = F.local_pca(doubled + UTM, k=10)
    assert pca.n_duplicates == (copies - 1) * len(xyz)
    ref = F.local_pca(xyz + UTM, k=10)  # independent: the cloud without copies
    # every copy gets the result of its distinct point (match the rows by coordinates)
    order_d = np.lexsort(doubled.T[::-1])
    order_r = np.repeat(np.lexsort(xyz.T[::-1]), copies)
    assert np.allclose(pca.normals[order_d], ref.normals[order_r], atol=1e-9)
    assert np.allclose(pca.eigenvalues[order_d], ref.eigenvalues[order_r], rtol=1e-9, atol=1e-15)
    assert (pca.counts == 10).all()


def test_duplicates_keep_is_the_old_behaviour_and_tilts_normals():
    """A duplicate cluster pulls a kept neighbourhood toward itself; merged, it does not."""
    rng = np.random.default_rng(4)
    xyz, nrm = plane(rng, n=300, sigma=0.01)
    dup = np.repeat(xyz[:60], 6, axis=0)  # 60 points repeated 6 times
    cloud = np.vstack([xyz, dup])
    keep = F.local_pca(cloud, k=12, duplicates="keep")
    merged = F.local_pca(cloud, k=12)
    assert keep.n_duplicates == 0 and merged.n_duplicates == len(dup)
    assert (keep.counts == 12).all()
    ref = F.local_pca(xyz, k=12)
    assert np.allclose(merged.normals[: len(xyz)], ref.normals, atol=1e-9)
    # with copies kept, the neighbourhoods of the repeated points hold only a few distinct points
    a_keep = angle_deg(keep.normals[:60], nrm)
    a_merge = angle_deg(merged.normals[:60], nrm)
    assert np.nanmedian(a_keep) > 2 * np.median(a_merge)


def test_at_on_a_duplicate_equals_its_kept_copy():
    rng = np.random.default_rng(5)
    xyz, _ = plane(rng, n=200)
    cloud = np.vstack([xyz, xyz[:50]])
    pca = F.local_pca(cloud, k=8, at=np.arange(200, 250))
    full = F.local_pca(cloud, k=8)
    assert np.allclose(pca.normals, full.normals[:50], atol=1e-12)
    assert np.allclose(pca.normals, full.normals[200:250], atol=1e-12)


def test_fewer_distinct_points_than_k_uses_all_of_them():
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    cloud = np.repeat(base, 5, axis=0)  # 20 rows, 4 distinct points of the plane z = 0
    pca = F.local_pca(cloud, k=10)
    assert (pca.counts == 4).all() and pca.valid.all()
    assert np.allclose(np.abs(pca.normals[:, 2]), 1.0)


@pytest.mark.parametrize("value", ["drop", None, "MERGE", 1])
def test_bad_duplicates_argument(value):
    with pytest.raises(LabkitError, match="duplicates must be one of"):
        F.local_pca(np.random.default_rng(0).normal(size=(20, 3)), k=5, duplicates=value)


def test_report_counts_duplicates_and_undetermined():
    cloud = np.vstack([_identical(None), plane(np.random.default_rng(6))[0]])
    text = F.local_pca(cloud, k=6).summary()
    assert "exact duplicates merged" in text and "29" in text
    assert "normal undetermined" in text


# ----------------------------------------------------------------------------- real data


def test_real_multibeam_plane_with_duplicates(realdata):
    """plane.laz (laspy, BSD-2): a flat patch, Z quantised to 1 cm, 9,850 exact duplicates.

    Independent route: the normal of one plane fitted to the whole patch (its RMS is
    about 8 mm over 2 m, so it is flat to about 0.3 deg). With duplicates kept, many
    neighbourhoods hold a few distinct points and their normals tilt by tens of degrees.
    """
    from labkit.io import read_cloud

    xyz = read_cloud(realdata / "tls" / "plane.laz").xyz
    assert len(xyz) == 28185
    centred = xyz - xyz.mean(axis=0)
    n0 = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    merged = F.local_pca(xyz, k=20)
    kept = F.local_pca(xyz, k=20, duplicates="keep")
    assert merged.n_duplicates == len(xyz) - len(np.unique(xyz, axis=0)) == 9850
    a_m, a_k = angle_deg(merged.normals, n0), angle_deg(kept.normals, n0)
    assert merged.valid.all()
    assert (a_k > 25).sum() > 2000  # the finding (3,773 of 28,185 at their settings)
    assert np.median(a_m) < 5.0 and (a_m > 25).mean() < 0.005
    assert np.median(a_m) < 0.5 * np.median(a_k)


# ----------------------------------------------------------------------------- argument catalogue

_PTS = np.random.default_rng(9).normal(size=(60, 3))


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: F.local_pca(_PTS, k=20.5), "k must be an integer"),
        (lambda: F.local_pca(_PTS, k=True), "k must be an integer"),
        (lambda: F.local_pca(_PTS, k=2), "k must be between 3"),
        (lambda: F.local_pca(_PTS, k=61), "k must be between 3"),
        (lambda: F.local_pca(_PTS, k=None, radius=None), "give k"),
        (lambda: F.local_pca(_PTS, radius=-1.0), "radius"),
        (lambda: F.local_pca(_PTS, radius=float("nan")), "radius"),
        (lambda: F.local_pca(_PTS, radius=float("inf")), "radius"),
        (lambda: F.local_pca(_PTS, k=5, chunk_size=0), "chunk_size"),
        (lambda: F.local_pca(_PTS, k=5, at=[60]), "at contains indices"),
        (lambda: F.local_pca(_PTS, k=5, at=[]), "at is empty"),
        (lambda: F.local_pca(_PTS, k=5, at=[0.5]), "at must be a 1-D array"),
        (lambda: F.local_pca(_PTS, k=5, orient="down"), "orient must be one of"),
        (lambda: F.local_pca(_PTS, k=5, orient="viewpoint"), "needs viewpoint"),
        (lambda: F.local_pca(_PTS, k=5, orient="viewpoint", viewpoint=[0, np.nan, 0]), "viewpoint must be finite"),
        (lambda: F.local_pca(np.vstack([_PTS, [np.nan, 0, 0]]), k=5), "NaN|finite"),
        (lambda: F.local_pca(_PTS[:, :2], k=5), r"\(n, 3\)|shape"),
        (lambda: F.normals(_PTS, k=5, duplicates="drop"), "duplicates must be one of"),
        (lambda: F.multiscale_features(_PTS, scales=(), by="k"), "at least one"),
        (lambda: F.robust_normals(_PTS, k=5, iterations=0), "iterations"),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_bad_arguments_give_one_clear_error(call, message):
    with pytest.raises(LabkitError, match=message):
        call()


def test_input_not_modified_by_merging():
    xyz = np.repeat(plane(np.random.default_rng(10))[0][:100], 2, axis=0)
    before = xyz.copy()
    F.local_pca(xyz, k=8)
    match(xyz, xyz, max_angle_deg=None)
    assert np.array_equal(xyz, before)
