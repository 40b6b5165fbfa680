"""4x4 homogeneous transformations: build, compose, invert, apply.

A transform ``T`` maps a point ``p`` (column vector) to ``R p + t``; the
convention throughout labkit is that a registration result maps the *source*
cloud onto the *target* cloud.
"""

from __future__ import annotations

import numpy as np

from .core.checks import as_points, require_real
from .core.errors import LabkitError


def make_transform(rotation=None, translation=None) -> np.ndarray:
    """Build a 4x4 matrix from a 3x3 rotation (default identity) and a translation (3,).

    References
    ----------
    .. [1] Notebook 05, section 3 (a 4x4 matrix from the adjusted shift); notebook 07, eq. 5.
    .. [2] R. Hartley, A. Zisserman (2004): Multiple View Geometry in Computer Vision, 2nd edition,
       Cambridge University Press (rigid motions as 4x4 matrices in homogeneous coordinates).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.transforms import make_transform
    >>> T = make_transform(np.eye(3), [1.0, 2.0, 3.0])
    >>> T[:3, 3].tolist(), T[3].tolist()
    ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0])
    """
    T = np.eye(4)
    if rotation is not None:
        R = _real_array(rotation, "rotation")
        if R.shape != (3, 3):
            raise LabkitError(f"rotation must have shape (3, 3), got {R.shape}")
        if not np.isfinite(R).all():
            raise LabkitError("rotation contains NaN or infinite values")
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise LabkitError("rotation is not orthonormal (R^T R != I): a scaled or sheared matrix is no rotation")
        if np.linalg.det(R) < 0:
            raise LabkitError("rotation has determinant -1: a reflection is no rotation")
        T[:3, :3] = R
    if translation is not None:
        t = _real_array(translation, "translation")
        if t.shape != (3,):
            raise LabkitError(f"translation must have shape (3,), got {t.shape}")
        if not np.isfinite(t).all():
            raise LabkitError(f"translation must be finite, got {t.tolist()}")
        T[:3, 3] = t
    return T


def _real_array(values, name: str) -> np.ndarray:
    """``values`` as a float64 array; complex numbers and non-numbers refused."""
    require_real(values, name)
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LabkitError(f"{name} must be numeric: {exc}") from None


def check_transform(T) -> np.ndarray:
    """Return ``T`` as a float64 4x4 rigid-body matrix or raise a clear error.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.transforms import check_transform
    >>> check_transform(np.eye(4)).shape
    (4, 4)
    >>> check_transform(np.ones((4, 4)))
    Traceback (most recent call last):
        ...
    labkit.core.errors.LabkitError: the last row of a homogeneous transformation must be [0, 0, 0, 1]
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise LabkitError(f"a transformation must be a 4x4 matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise LabkitError("the transformation contains NaN or infinite values")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise LabkitError("the last row of a homogeneous transformation must be [0, 0, 0, 1]")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise LabkitError("the upper-left 3x3 block is not a proper rotation matrix")
    return T


def compose(*transforms) -> np.ndarray:
    """Compose transforms so that ``compose(A, B)`` applies ``B`` first, then ``A``.

    References
    ----------
    .. [1] Notebook 07, section 1 (rigid transforms as 4x4 matrices mapping source onto target).

    Examples
    --------
    >>> from labkit.transforms import compose, make_transform
    >>> a, b = make_transform(translation=[1.0, 0, 0]), make_transform(translation=[0, 2.0, 0])
    >>> compose(a, b)[:3, 3].tolist()
    [1.0, 2.0, 0.0]
    """
    out = np.eye(4)
    for T in transforms:
        out = out @ check_transform(T)
    return out


def invert(T) -> np.ndarray:
    """Inverse of a rigid-body transform (uses R^T, no general inversion).

    References
    ----------
    .. [1] Notebook 07, section 1 (rigid transforms as 4x4 matrices mapping source onto target).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.transforms import invert, make_transform, rotation_from_angles
    >>> T = make_transform(rotation_from_angles(0.1, -0.2, 0.3), [5.0, -1.0, 2.0])
    >>> bool(np.allclose(invert(T) @ T, np.eye(4)))
    True
    """
    T = check_transform(T)
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def apply_transform(T, points, *, origin=None) -> np.ndarray:
    """Apply ``T`` to (n, 3) points and return a new array.

    With ``origin`` given, ``T`` is understood in the frame reduced to that
    origin: ``p' = R (p - o) + t + o``. This keeps rotations about a local point
    numerically sound for UTM coordinates.

    References
    ----------
    .. [1] Notebook 05, section 3 (the source moved by the adjusted shift); notebook 07, section 1
       (the 4x4 truth of a case).
    .. [2] R. Hartley, A. Zisserman (2004): Multiple View Geometry in Computer Vision, 2nd ed.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.transforms import apply_transform, make_transform, rotation_from_angles
    >>> T = make_transform(rotation_from_angles(0, 0, np.pi / 2), [10.0, 0, 0])
    >>> apply_transform(T, [[1.0, 0, 0]]).round(12).tolist()
    [[10.0, 1.0, 0.0]]
    >>> apply_transform(T, [[1.0, 0, 0]], origin=[1.0, 0, 0]).round(12).tolist()
    [[11.0, 0.0, 0.0]]
    """
    T = check_transform(T)
    xyz = as_points(points)
    R, t = T[:3, :3], T[:3, 3]
    # einsum, not ``xyz @ R.T``: BLAS picks its kernel by the shape of the block (one row, the edge of a
    # thread's share), so a point's last bits depend on the points beside it and on the thread count
    if origin is None:
        return np.einsum("ij,kj->ik", xyz, R) + t
    o = _real_array(origin, "origin")
    if o.shape != (3,) or not np.isfinite(o).all():
        raise LabkitError(f"origin must be 3 finite numbers, got {np.asarray(origin).tolist()}")
    return np.einsum("ij,kj->ik", xyz - o, R) + t + o


def rotation_from_angles(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix R = Rz(rz) Ry(ry) Rx(rx) from angles in radians.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.transforms import rotation_from_angles
    >>> R = rotation_from_angles(0.0, 0.0, np.pi / 2)
    >>> (R @ [1.0, 0.0, 0.0]).round(12).tolist()
    [0.0, 1.0, 0.0]
    """
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def angles_from_rotation(R) -> np.ndarray:
    """Angles (rx, ry, rz) in radians with R = Rz Ry Rx (inverse of :func:`rotation_from_angles`).

    Examples
    --------
    >>> from labkit.transforms import angles_from_rotation, rotation_from_angles
    >>> angles_from_rotation(rotation_from_angles(0.01, -0.02, 0.3)).round(6).tolist()
    [0.01, -0.02, 0.3]
    """
    R = np.asarray(R, dtype=np.float64)
    ry = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    rx = np.arctan2(R[2, 1], R[2, 2])
    rz = np.arctan2(R[1, 0], R[0, 0])
    return np.array([rx, ry, rz])


def skew(v) -> np.ndarray:
    """The cross-product matrix [v]x with [v]x w = v x w, for one vector (3,) or a stack (n, 3).

    Parameters
    ----------
    v : array_like (3,) or (n, 3)

    Returns
    -------
    ndarray (3, 3) or (n, 3, 3)
        ``[[0, -v3, v2], [v3, 0, -v1], [-v2, v1, 0]]`` for each vector.

    Examples
    --------
    >>> import numpy as np
    >>> v, w = np.array([1.0, 2.0, 3.0]), np.array([0.5, -1.0, 2.0])
    >>> bool(np.allclose(skew(v) @ w, np.cross(v, w)))
    True
    >>> skew(np.zeros((4, 3))).shape
    (4, 3, 3)
    """
    v = np.asarray(v, dtype=np.float64)
    if v.shape[-1:] != (3,) or v.ndim not in (1, 2):
        raise LabkitError(f"skew needs a vector (3,) or a stack (n, 3), got shape {v.shape}")
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)
