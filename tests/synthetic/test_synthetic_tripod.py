"""The synthetic tripod scene: geometry, labels, counts, reproducibility, UTM shift."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.synthetic import sphere_on_tripod
from labkit.synthetic.tripod import LABEL_NAMES


def test_sphere_points_lie_on_the_true_sphere_within_noise():
    scene = sphere_on_tripod(n_sphere=5000, noise=0.001, rng=3)
    d = np.linalg.norm(scene.sphere_points - scene.sphere[:3], axis=1) - scene.sphere[3]
    # isotropic noise of 1 mm: the radial component has a std of 1 mm
    assert abs(d.std() - 0.001) < 0.05e-3
    assert abs(d.mean()) < 0.1e-3
    assert np.abs(d).max() < 6 * 0.001


def test_only_the_cap_facing_the_station_is_scanned():
    scene = sphere_on_tripod(n_sphere=3000, noise=0.0, rng=4)
    normals = (scene.sphere_points - scene.sphere[:3]) / scene.sphere[3]
    to_station = scene.station - scene.sphere_points
    facing = np.einsum("ij,ij->i", normals, to_station)
    assert (facing > 0).all()
    # the cap is a real cap: the normals span a wide cone, not a single direction
    u = (scene.station - scene.sphere[:3]) / np.linalg.norm(scene.station - scene.sphere[:3])
    assert np.degrees(np.arccos((normals @ u).min())) > 60


def test_non_sphere_points_are_far_from_the_sphere_surface():
    scene = sphere_on_tripod(n_sphere=1000, noise=0.0, rng=5)
    d = np.abs(np.linalg.norm(scene.points - scene.sphere[:3], axis=1) - scene.sphere[3])
    structure = np.isin(scene.labels, [1, 2, 3])
    # legs, base, ground stay off the sphere shell; only the adapter stem touches the sphere
    assert (d[structure] < 0.003).mean() < 0.005
    assert (d[scene.labels == 1] > 0.05).all()


def test_labels_are_consistent():
    scene = sphere_on_tripod(n_sphere=800, n_clutter=123, rng=6)
    assert scene.label_names == LABEL_NAMES
    assert scene.points.shape == (scene.n, 3)
    assert scene.labels.shape == scene.is_sphere.shape == (scene.n,)
    np.testing.assert_array_equal(scene.is_sphere, scene.labels == 0)
    counts = np.bincount(scene.labels, minlength=5)
    assert counts[0] == 800 and counts[4] == 123
    assert (counts > 0).all()
    # the ground is near z = 0, the legs between ground and head
    assert np.abs(scene.points[scene.labels == 3, 2]).max() < 0.05
    legs_z = scene.points[scene.labels == 1, 2]
    assert legs_z.min() > -0.05 and legs_z.max() < scene.sphere[2]


@pytest.mark.parametrize("ratio", [0.0, 0.5, 0.8])
def test_outlier_ratio_is_exact(ratio):
    scene = sphere_on_tripod(n_sphere=2000, outlier_ratio=ratio, rng=7)
    assert scene.outlier_ratio == pytest.approx(ratio, abs=1e-12)
    assert scene.is_sphere.sum() == 2000


def test_same_seed_same_scene_other_seed_other_scene():
    a = sphere_on_tripod(n_sphere=500, rng=11)
    b = sphere_on_tripod(n_sphere=500, rng=np.random.default_rng(11))
    c = sphere_on_tripod(n_sphere=500, rng=12)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert not np.array_equal(a.points, c.points)


def test_utm_option_shifts_everything():
    local = sphere_on_tripod(n_sphere=500, rng=21)
    utm = sphere_on_tripod(n_sphere=500, utm=True, rng=21)
    shift = utm.offset
    assert shift[0] > 1e5 and shift[1] > 1e6
    np.testing.assert_allclose(utm.points - shift, local.points, atol=1e-9)
    np.testing.assert_allclose(utm.sphere[:3] - shift, local.sphere[:3], atol=1e-9)
    assert utm.sphere[3] == local.sphere[3]
    np.testing.assert_allclose(utm.station - shift, local.station, atol=1e-9)
    custom = sphere_on_tripod(n_sphere=500, utm=[1.0, 2.0, 3.0], rng=21)
    np.testing.assert_allclose(custom.points - [1.0, 2.0, 3.0], local.points, atol=1e-12)


def test_range_noise_is_along_the_beam():
    scene = sphere_on_tripod(n_sphere=20000, outlier_ratio=0.0, noise=0.0005, range_noise=0.003, rng=8)
    clean_dir = (scene.sphere_points - scene.station)
    u = clean_dir / np.linalg.norm(clean_dir, axis=1, keepdims=True)
    # the range error shows up as spread along the beam; compare with the covariance model
    cov = scene.covariances()
    assert cov.shape == (scene.n, 3, 3)
    along = np.einsum("ij,ijk,ik->i", u, cov, u)
    np.testing.assert_allclose(along, 0.003**2, rtol=1e-6)
    np.testing.assert_allclose(np.trace(cov, axis1=1, axis2=2), 2 * 0.0005**2 + 0.003**2, rtol=1e-9)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_sphere": -1},
        {"n_sphere": 2.5},
        {"outlier_ratio": 1.0},
        {"outlier_ratio": -0.1},
        {"radius": 0.0},
        {"noise": -1.0},
        {"utm": [1.0, 2.0]},
        {"outlier_ratio": 0.5, "n_sphere": 100, "n_clutter": 1000},
        {"rng": "seed"},
        {"n_sphere": "many"},
        {"noise": "1 mm"},
        {"outlier_ratio": "half"},
        {"noise": "0.001"},  # text is refused, not converted (the shared validator of labkit.core.checks)
        {"noise": True},
    ],
)
def test_bad_arguments_raise(kwargs):
    with pytest.raises(LabkitError):
        sphere_on_tripod(**kwargs)


def test_large_scene_is_generated_vectorized():
    scene = sphere_on_tripod(n_sphere=100_000, outlier_ratio=0.8, rng=9)
    assert scene.n == 500_000
    assert np.isfinite(scene.points).all()
    assert "outlier ratio" in scene.summary()
