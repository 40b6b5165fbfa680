"""Shared foundation: validation, transforms, point cloud, reports, CLI."""

import numpy as np
import pytest

import labkit
from labkit import transforms as tf
from labkit.core.checks import as_points, as_rng, probability
from labkit.cloud import PointCloud
from labkit.core.errors import LabkitError


def test_as_points_rejects_bad_input():
    with pytest.raises(LabkitError, match="shape"):
        as_points(np.zeros((4, 2)))
    with pytest.raises(LabkitError, match="at least 4"):
        as_points(np.zeros((3, 3)), min_points=4)
    bad = np.zeros((5, 3))
    bad[2, 1] = np.nan
    with pytest.raises(LabkitError, match="NaN"):
        as_points(bad)
    assert issubclass(LabkitError, ValueError)


def test_as_rng_is_reproducible():
    assert as_rng(7).random() == as_rng(7).random()
    g = np.random.default_rng(1)
    assert as_rng(g) is g
    with pytest.raises(LabkitError):
        as_rng("seed")
    with pytest.raises(LabkitError):
        probability(1.0, "p")


def test_transforms_compose_invert_apply():
    rng = np.random.default_rng(3)
    R = tf.rotation_from_angles(0.01, -0.02, 0.3)
    T = tf.make_transform(R, [1.0, 2.0, 3.0])
    pts = rng.normal(size=(50, 3))
    back = tf.apply_transform(tf.invert(T), tf.apply_transform(T, pts))
    np.testing.assert_allclose(back, pts, atol=1e-12)
    np.testing.assert_allclose(tf.compose(T, tf.invert(T)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(tf.angles_from_rotation(R), [0.01, -0.02, 0.3], atol=1e-12)
    with pytest.raises(LabkitError, match="4x4"):
        tf.apply_transform(np.eye(3), pts)
    with pytest.raises(LabkitError, match="rotation"):
        tf.check_transform(np.diag([2.0, 1, 1, 1]))


def test_apply_transform_about_origin_matches_world_form():
    R = tf.rotation_from_angles(0.0, 0.0, 0.01)
    origin = np.array([600000.0, 5400000.0, 300.0])
    pts = origin + np.random.default_rng(0).normal(size=(10, 3))
    local = tf.apply_transform(tf.make_transform(R, [0.1, 0.2, 0.3]), pts, origin=origin)
    world = tf.make_transform(R, [0.1, 0.2, 0.3] + origin - R @ origin)
    np.testing.assert_allclose(tf.apply_transform(world, pts), local, atol=1e-6)


def test_point_cloud_is_immutable_and_keeps_attributes():
    xyz = np.arange(12.0).reshape(4, 3)
    cloud = PointCloud(xyz, {"classification": [2, 2, 6, 6]})
    xyz[0, 0] = 99.0
    assert cloud.xyz[0, 0] == 0.0  # copied, not a view of the caller's array
    with pytest.raises(ValueError):
        cloud.xyz[0, 0] = 1.0
    sub = cloud.subset(cloud["classification"] == 6)
    assert len(sub) == 2 and list(sub["classification"]) == [6, 6]
    with pytest.raises(LabkitError, match="one per point"):
        PointCloud(xyz, {"intensity": [1, 2]})
    with pytest.raises(KeyError, match="gps_time"):
        cloud["gps_time"]


def test_convergence_error_is_gone():
    """Non-convergence is reported in the result, never raised: no ConvergenceError class exists."""
    assert "ConvergenceError" not in labkit.__all__
    with pytest.raises(AttributeError):
        labkit.ConvergenceError
    with pytest.raises(ImportError):
        from labkit.core.errors import ConvergenceError  # noqa: F401


def test_skew_is_the_cross_product_matrix():
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", tf.skew(v), w), np.cross(v, w), atol=1e-15)
    np.testing.assert_allclose(tf.skew(v[0]), -tf.skew(v[0]).T)
    with pytest.raises(LabkitError, match="shape"):
        tf.skew(np.ones(4))


def test_lazy_exports_resolve():
    assert labkit.PointCloud is PointCloud
    with pytest.raises(AttributeError):
        labkit.does_not_exist


def test_cli_version_and_error_exit(capsys):
    from labkit.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "labkit" in capsys.readouterr().out
