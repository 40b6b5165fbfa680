"""labkit.transforms: 4x4 matrices built, composed, inverted and applied, against scipy's rotations."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from labkit.core.errors import LabkitError
from labkit.transforms import (angles_from_rotation, apply_transform, check_transform, compose, invert,
                               make_transform, rotation_from_angles, skew)


def test_rotation_from_angles_is_scipys_extrinsic_xyz_and_angles_come_back():
    rng = np.random.default_rng(0)
    for rx, ry, rz in rng.uniform(-1.2, 1.2, (50, 3)):
        R = rotation_from_angles(rx, ry, rz)
        np.testing.assert_allclose(R, Rotation.from_euler("xyz", [rx, ry, rz]).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(angles_from_rotation(R), [rx, ry, rz], atol=1e-12)


def test_compose_invert_and_apply_agree_with_applying_step_by_step():
    rng = np.random.default_rng(1)
    A = make_transform(rotation_from_angles(0.1, -0.2, 0.3), [612_000.0, 5_701_000.0, 80.0])
    B = make_transform(rotation_from_angles(-0.05, 0.02, 1.0), [1.0, -2.0, 0.5])
    p = rng.uniform(-50, 50, (100, 3))
    np.testing.assert_allclose(apply_transform(compose(A, B), p), apply_transform(A, apply_transform(B, p)),
                               rtol=0, atol=1e-8)
    np.testing.assert_allclose(apply_transform(invert(A), apply_transform(A, p)), p, rtol=0, atol=1e-8)
    before = p.copy()
    apply_transform(A, p)
    np.testing.assert_array_equal(p, before)  # the input is not modified


def test_apply_about_an_origin_is_the_conjugated_transform():
    T = make_transform(rotation_from_angles(0.0, 0.0, 0.4), [0.1, 0.2, 0.3])
    o = np.array([612_000.0, 5_701_000.0, 80.0])
    p = o + np.random.default_rng(2).uniform(-10, 10, (20, 3))
    shift = make_transform(np.eye(3), o)
    np.testing.assert_allclose(apply_transform(T, p, origin=o), apply_transform(compose(shift, T, invert(shift)), p),
                               rtol=0, atol=1e-8)


def test_skew_is_the_cross_product_for_one_vector_and_a_stack():
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(v), w), np.cross(v, w), atol=1e-14)
    np.testing.assert_allclose(skew(v[0]) @ w[0], np.cross(v[0], w[0]), atol=1e-14)


@pytest.mark.parametrize("bad", [np.eye(3), np.full((4, 4), np.nan), np.diag([2.0, 1, 1, 1])])
def test_check_transform_refuses_what_is_no_rigid_4x4(bad):
    with pytest.raises(LabkitError):
        check_transform(bad)
