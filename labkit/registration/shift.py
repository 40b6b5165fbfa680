"""The shift of a point under a transformation and its covariance (notebook 07, eq. 5).

Methods that estimate different parameters (a translation, or a rotation about their own origin as
well) are compared by the shift they give at one point, the centre of the region.
"""

from __future__ import annotations

import numpy as np

from ..transforms import skew

__all__ = ["shift_at", "shift_covariance"]


def shift_at(T, c) -> np.ndarray:
    """Shift of the point c under T: R c + t - c (eq. 5).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.compare import shift_at
    >>> from labkit.transforms import make_transform, rotation_from_angles
    >>> T = make_transform(rotation_from_angles(0, 0, 0.001), [0.1, 0.0, 0.0])
    >>> shift_at(T, np.zeros(3)).round(6).tolist(), shift_at(T, np.array([100.0, 0, 0])).round(6).tolist()
    ([0.1, 0.0, 0.0], [0.09995, 0.1, 0.0])
    """
    return T[:3, :3] @ c + T[:3, 3] - c


def shift_covariance(result, c) -> np.ndarray:
    """Covariance of the shift at c by propagating the parameter covariance: J Sigma J^T.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from labkit.registration.compare import shift_covariance
    >>> result = SimpleNamespace(parameter_names=("tx", "ty", "tz", "rz"), origin=np.zeros(3),
    ...                      covariance=np.diag([1e-6, 1e-6, 1e-6, 1e-8]))
    >>> np.sqrt(np.diag(shift_covariance(result, np.array([100.0, 0, 0])))).round(5).tolist()
    [0.001, 0.01005, 0.001]
    """
    names = tuple(getattr(result, "parameter_names", ("tx", "ty", "tz")))
    Sigma = np.asarray(getattr(result, "covariance", np.full((3, 3), np.nan)), dtype=float)
    if Sigma.shape != (len(names), len(names)):
        return np.full((3, 3), np.nan)
    arm = c - np.asarray(getattr(result, "origin", np.zeros(3)), dtype=float)
    # d(shift)/d(angle): a small rotation dtheta moves c by dtheta x arm = -[arm]x dtheta
    dtheta = -skew(arm)
    cols = {"tx": np.eye(3)[:, 0], "ty": np.eye(3)[:, 1], "tz": np.eye(3)[:, 2],
            "rx": dtheta[:, 0], "ry": dtheta[:, 1], "rz": dtheta[:, 2]}
    J = np.column_stack([cols.get(n, np.zeros(3)) for n in names])
    # J Sigma J^T term by term, so that inf/NaN of undetermined parameters stay where J touches them
    terms = np.einsum("ik,kl,jl->ijkl", J, np.nan_to_num(Sigma, nan=0.0, posinf=0.0, neginf=0.0), J)
    bad = ~np.isfinite(Sigma)[None, None] & (J[:, None, :, None] != 0) & (J[None, :, None, :] != 0)
    return np.where(bad.any(axis=(2, 3)), np.inf, terms.sum(axis=(2, 3)))
