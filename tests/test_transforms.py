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


# --------------------------------------------------------------------------- bad input
R = rotation_from_angles(0.1, -0.2, 0.3)


@pytest.mark.parametrize("rotation, fragment", [
    (np.diag([1.0, 1.0, -1.0]), "reflection"),
    (-np.eye(3), "reflection"),
    (R @ np.diag([-1.0, 1.0, 1.0]), "reflection"),
    (2.0 * np.eye(3), "scaled"),
    (1.001 * R, "scaled"),
    (np.diag([1.0, 1.0, 0.5]), "scaled"),
    (np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]]), "sheared"),
    (np.zeros((3, 3)), "orthonormal"),
    (np.full((3, 3), np.nan), "NaN"),
    (np.eye(3) + 0j, "complex"),
    (np.eye(4), "shape"),
])
def test_make_transform_refuses_what_is_no_rotation(rotation, fragment):
    with pytest.raises(LabkitError, match=fragment):
        make_transform(rotation, [0.0, 0.0, 0.0])


@pytest.mark.parametrize("translation, fragment", [
    ([np.nan, 0, 0], "finite"), ([0, np.inf, 0], "finite"), ([1j, 0, 0], "complex"), ([1, 2], "shape"),
    (["a", "b", "c"], "numeric"),
])
def test_make_transform_refuses_bad_translations(translation, fragment):
    with pytest.raises(LabkitError, match=fragment):
        make_transform(np.eye(3), translation)


@pytest.mark.parametrize("rotation", [np.eye(3), R, rotation_from_angles(np.pi, 0, 0), R.T])
def test_make_transform_accepts_rotations(rotation):
    T = make_transform(rotation, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(T[:3, :3], rotation)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


@pytest.mark.parametrize("origin, fragment", [
    ([np.nan, 0, 0], "finite"), ([0, 0, np.inf], "finite"), ([1, 2], "3 finite"), ([1j, 0, 0], "complex"),
])
def test_apply_transform_refuses_bad_origins(origin, fragment):
    with pytest.raises(LabkitError, match=fragment):
        apply_transform(np.eye(4), np.zeros((2, 3)), origin=origin)


def test_apply_transform_about_an_origin_is_a_rotation_about_it():
    o = np.array([500_000.0, 5_400_000.0, 100.0])
    p = o + [[1.0, 0, 0], [0, 2.0, 0]]
    out = apply_transform(make_transform(rotation_from_angles(0, 0, np.pi / 2)), p, origin=o)
    np.testing.assert_allclose(out - o, [[0, 1.0, 0], [-2.0, 0, 0]], atol=1e-9)


def test_a_point_moves_to_the_same_bits_alone_or_among_others():
    """Each point's result depends on that point only: not on the batch, its length or where it is cut.

    A threaded product splits the rows among the threads; BLAS computes a lone row (gemv) or the
    edge of a block with other kernels than the body, which rounds differently in the last bits.
    """
    T = make_transform(rotation_from_angles(0.01, -0.02, 0.3), [0.1, -0.2, 0.05])
    p = np.random.default_rng(4).uniform(-50, 50, (10_007, 3)) + [612_000.0, 5_701_000.0, 80.0]
    for origin in (None, p[0]):
        full = apply_transform(T, p, origin=origin)
        alone = np.concatenate([apply_transform(T, p[i:i + 1], origin=origin) for i in range(500)])
        np.testing.assert_array_equal(full[:500], alone)
        chunks = np.concatenate([apply_transform(T, p[i:i + 7], origin=origin) for i in range(0, len(p), 7)])
        np.testing.assert_array_equal(full, chunks)
        np.testing.assert_array_equal(full[::-1], apply_transform(T, p[::-1], origin=origin))
        np.testing.assert_allclose(full, (p - (0 if origin is None else origin)) @ T[:3, :3].T + T[:3, 3]
                                   + (0 if origin is None else origin), rtol=0, atol=1e-9)


#: apply_transform on a million points in a fresh interpreter; prints a digest of the bytes
CHILD = """
import hashlib
import numpy as np
from labkit.transforms import apply_transform, make_transform, rotation_from_angles
T = make_transform(rotation_from_angles(0.01, -0.02, 0.3), [0.1, -0.2, 0.05])
p = np.random.default_rng(5).uniform(-50, 50, (1_000_003, 3)) + [612_000.0, 5_701_000.0, 80.0]
out = [apply_transform(T, p), apply_transform(T, p, origin=p[0])]
print(hashlib.sha256(b"".join(a.tobytes() for a in out)).hexdigest())
"""


def test_apply_transform_is_bit_identical_on_one_and_all_cores(all_cores_and_one):
    out = all_cores_and_one(CHILD, CHILD, timeout=300)
    assert out[0] and out[0] == out[1]
