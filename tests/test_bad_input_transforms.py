"""Transformations (labkit.transforms): make_transform builds rigid motions only; origins and complex values checked."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.transforms import apply_transform, make_transform, rotation_from_angles

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
