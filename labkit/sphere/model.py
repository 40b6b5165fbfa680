"""The sphere as a geometric model: residuals, algebraic fit, minimal 4-point solution.

Parameters follow the exercise sheet's eq. (3): ``x = [xc, yc, zc, r]``.
"""

from __future__ import annotations

import numpy as np

from ..core.checks import as_points
from ..core.errors import DegenerateGeometryError


def sphere_residuals(points, x) -> np.ndarray:
    """Orthogonal distances d_i = |p_i - c| - r of eq. (25), shape (n,).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.sphere.model import sphere_residuals
    >>> sphere_residuals(np.array([[2.0, 0, 0], [0, 0.5, 0], [0, 0, -1.0]]), [0, 0, 0, 1.0]).tolist()
    [1.0, -0.5, 0.0]
    """
    xyz = np.asarray(points, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    return np.linalg.norm(xyz - x[:3], axis=1) - x[3]


def algebraic_sphere(points) -> np.ndarray:
    """Linear (algebraic) sphere fit, used for initial values x0.

    Solves ``|p|^2 = 2 c.p + (r^2 - |c|^2)`` in the least-squares sense on
    coordinates centred at their mean (for conditioning), then moves back.

    Returns
    -------
    ndarray (4,)
        [xc, yc, zc, r] in the frame of ``points``.

    Raises
    ------
    DegenerateGeometryError
        If the points lie on a plane or line (no unique sphere).

    References
    ----------
    .. [1] Seed 000, section 1 (initial values x0, found heuristically); notebook 01, section 3;
       notebook 02, section 2 (the fit on all points).
    .. [2] I. Kasa (1976): A circle fitting procedure and its error analysis.
       IEEE Transactions on Instrumentation and Measurement 25(1), 8-14 (the
       same linear fit, here in three dimensions).

    Examples
    --------
    >>> from labkit.sphere.model import algebraic_sphere
    >>> from labkit.synthetic import sphere_points
    >>> points = sphere_points(50, 0, center=[1.0, 2.0, 3.0], radius=0.5)
    >>> algebraic_sphere(points).round(9).tolist()
    [1.0, 2.0, 3.0, 0.5]
    """
    xyz = as_points(points, min_points=4)
    mean = xyz.mean(axis=0)
    q = xyz - mean
    scale = np.sqrt((q**2).sum(axis=1).mean())
    if scale == 0:
        raise DegenerateGeometryError("all points coincide: no sphere is determined")
    q = q / scale
    M = np.column_stack([2.0 * q, np.ones(len(q))])
    rhs = (q**2).sum(axis=1)
    sol, _, rank, sv = np.linalg.lstsq(M, rhs, rcond=None)
    if rank < 4 or sv[-1] < 1e-9 * sv[0]:
        raise DegenerateGeometryError(
            "the points lie on a plane, a line or a circle: the sphere is not determined"
        )
    c = sol[:3]
    r2 = sol[3] + c @ c
    if r2 <= 0:
        raise DegenerateGeometryError("the algebraic fit gave no real radius")
    return np.concatenate([c * scale + mean, [np.sqrt(r2) * scale]])


def circumspheres(samples, *, min_volume_ratio: float = 1e-6):
    """Closed-form spheres through 4 points, batched over many samples.

    Parameters
    ----------
    samples : ndarray (m, 4, 3)
        m samples of 4 points each.
    min_volume_ratio : float
        A sample is degenerate (nearly coplanar) when the volume of its
        tetrahedron is below ``min_volume_ratio`` times the volume of a regular
        tetrahedron with the sample's RMS edge length.

    Returns
    -------
    centers : ndarray (m, 3)
    radii : ndarray (m,)
    valid : ndarray of bool (m,)
        False for (nearly) coplanar or duplicate samples; their centre and
        radius are NaN.

    Notes
    -----
    With p0 as origin and e_j = p_j - p0, the centre c' = c - p0 solves
    ``2 e_j . c' = |e_j|^2`` (j = 1..3), a 3x3 system per sample.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.sphere.model import circumspheres
    >>> samples = np.array([[[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, 1]],
    ...                 [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]])
    >>> centers, radii, valid = circumspheres(samples)
    >>> radii[valid].tolist(), valid.tolist()
    ([1.0], [True, False])
    """
    s = np.asarray(samples, dtype=np.float64)
    p0 = s[:, 0, :]
    E = s[:, 1:, :] - p0[:, None, :]  # (m, 3, 3) edge vectors
    det = np.linalg.det(E)  # 6 x signed tetrahedron volume
    edges = np.concatenate([E, s[:, 2:, :] - s[:, 1:2, :], s[:, 3:, :] - s[:, 2:3, :]], axis=1)
    rms_edge = np.sqrt((edges**2).sum(axis=2).mean(axis=1))
    regular = rms_edge**3 / np.sqrt(2.0)  # 6 x volume of a regular tetrahedron
    valid = np.abs(det) > min_volume_ratio * regular
    valid &= rms_edge > 0
    centers = np.full(p0.shape, np.nan)
    radii = np.full(len(s), np.nan)
    if valid.any():
        Ev = E[valid]
        rhs = 0.5 * (Ev**2).sum(axis=2)
        cp = np.linalg.solve(Ev, rhs[..., None])[..., 0]
        centers[valid] = cp + p0[valid]
        radii[valid] = np.linalg.norm(cp, axis=1)
    return centers, radii, valid
