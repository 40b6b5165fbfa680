"""Algebra shared by the transformation adjustments (notebook 11): pose Jacobians, closed form, null space, tests.

A pose maps ``p`` to ``s R(rx, ry, rz) p + t`` with R = Rz Ry Rx (``labkit.transforms.rotation_from_angles``).
Every helper here works on stacks of points or 3x3 blocks with batched numpy: nothing grows like n^2.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from ..core.checks import numeric_array
from ..core.distributions import beta_sf, chi2_sf, norm_isf
from ..core.errors import LabkitError
from ..transforms import angles_from_rotation, rotation_from_angles, skew  # noqa: F401 (skew: used by targets)

_NULL_RCOND = 1e-10  # eigenvalue of the scaled N below this times the largest: a direction the data do not fix
_E = np.eye(3)


def as_covariances(cov, n: int, name: str) -> np.ndarray | None:
    """(n, 3, 3) covariances from None, a standard deviation, (n,), (n, 3) or (n, 3, 3) (m, m^2)."""
    if cov is None:
        return None
    c = numeric_array(cov, name)
    if c.ndim == 0 or c.shape in ((n,), (n, 3)):
        if (c < 0).any():
            raise LabkitError(f"{name} (standard deviations) must be >= 0")
        s2 = np.broadcast_to((c**2).reshape(-1, 1) if c.ndim == 1 else c**2, (n, 3))
        out = np.zeros((n, 3, 3))
        out[:, [0, 1, 2], [0, 1, 2]] = s2
        return out
    if c.shape == (n, 3, 3):
        if (np.abs(c - c.transpose(0, 2, 1)) > 1e-9 * (np.abs(c).max() + 1e-300)).any():
            raise LabkitError(f"{name} covariance matrices (n, 3, 3) must be symmetric")
        if (np.linalg.eigvalsh(c)[:, 0] < -1e-12 * np.abs(c).max(axis=(1, 2))).any():
            raise LabkitError(f"{name} covariance matrices (n, 3, 3) must be positive semi-definite")
        return c.copy()
    raise LabkitError(f"{name} must be None, a scalar, or of shape ({n},), ({n}, 3) or ({n}, 3, 3); got {c.shape}")


def pose_jacobian(angles, s, p, scale: bool) -> np.ndarray:
    """d(s R p + t)/d[rx, ry, rz, tx, ty, tz, (s)] for every point p (n, 3): shape (n, 3, 6 or 7).

    With R = Rz Ry Rx: dR/drx p = R (e_x x p), dR/dry p = Rz Ry (e_y x Rx p), dR/drz p = e_z x (R p).
    """
    rx, ry, rz = angles
    Rx, Ry, Rz = rotation_from_angles(rx, 0, 0), rotation_from_angles(0, ry, 0), rotation_from_angles(0, 0, rz)
    R = Rz @ Ry @ Rx
    J = np.zeros((len(p), 3, 7 if scale else 6))
    J[:, :, 0] = s * np.cross(_E[0], p) @ R.T
    J[:, :, 1] = s * np.cross(_E[1], p @ Rx.T) @ (Rz @ Ry).T
    Rp = p @ R.T
    J[:, :, 2] = s * np.cross(_E[2], Rp)
    J[:, :, 3:6] = _E
    if scale:
        J[:, :, 6] = Rp
    return J


def closed_form(p, q, w=None, scale: bool = False):
    """Weighted closed-form (Kabsch/Umeyama) fit q ~ s R p + t: returns (R, t, s).

    References: K. S. Arun, T. S. Huang, S. D. Blostein (1987), S. Umeyama (1991).
    """
    w = np.ones(len(p)) if w is None else np.asarray(w, dtype=np.float64)
    w = w / w.sum()
    mp, mq = w @ p, w @ q
    P, Q = p - mp, q - mq
    H = (P * w[:, None]).T @ Q  # sum w p q^T
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    var_p = float(w @ np.einsum("ij,ij->i", P, P))
    s = float(np.trace(np.diag(S) @ D) / var_p) if scale and var_p > 0 else 1.0
    return R, mq - s * R @ mp, s


def solve_normal(N, rhs):
    """dx = -N^+ rhs and Q = N^+ through the eigenvectors of the scaled N; also the null vectors (u, k).

    Directions with an eigenvalue below 1e-10 of the largest (after scaling N to a unit diagonal) are not
    determined by the data: the solution leaves them at their initial value (minimum norm), and they are
    returned so the caller can name them and report the affected parameters as undetermined.
    """
    d = np.sqrt(np.clip(np.diag(N), 0.0, None))
    if not np.isfinite(N).all():
        raise LabkitError("the normal matrix contains NaN or infinite values")
    d[d == 0] = 1.0
    # scipy's eigh: numpy's stalls on busy BLAS threads for these small matrices
    lam, V = linalg.eigh(N / np.outer(d, d), driver="ev", check_finite=False)
    keep = lam > _NULL_RCOND * max(lam[-1], 1e-300)
    Qs = (V[:, keep] / lam[keep]) @ V[:, keep].T
    Q = Qs / np.outer(d, d)
    null = V[:, ~keep] / d[:, None]
    return -Q @ rhs, Q, null / np.maximum(np.linalg.norm(null, axis=0), 1e-300)


def to_caller_frame(angles, t_red, s, origin_p, origin_q, scale: bool):
    """Parameters and their Jacobian after undoing the reductions: q = s R (p - o_p) + t' + o_q.

    t = t' + o_q - s R o_p, so dt/dangles = -s dR o_p, dt/ds = -R o_p; the angles and the scale are unchanged.
    """
    u = 7 if scale else 6
    R = rotation_from_angles(*angles)
    t = t_red + origin_q - s * R @ origin_p
    J = np.eye(u)
    Jo = pose_jacobian(angles, s, origin_p[None, :], scale)[0]  # d(s R o_p)/d(...)
    J[3:6, :3] = -Jo[:, :3]
    if scale:
        J[3:6, 6] = -Jo[:, 6]
    x = np.concatenate([angles, t, [s]] if scale else [angles, t])
    return x, J


def propagate(Q, J, null, names):
    """Q' = J Q J^T with every parameter touched by a null vector set to variance inf (its row/column NaN).

    Returns (Q', mask of undetermined parameters).
    """
    Qc = J @ Q @ J.T
    bad = np.zeros(len(J), bool)
    if null.shape[1]:
        Jn = J @ null
        size = np.linalg.norm(J, axis=1)[:, None] * np.linalg.norm(null, axis=0)[None, :]
        bad = (np.abs(Jn) > 1e-6 * np.maximum(size, 1e-300)).any(axis=1)
    Qc[bad, :] = np.nan
    Qc[:, bad] = np.nan
    Qc[bad, bad] = np.inf
    return Qc, bad


def point_tests(e, Qee, scale, sigma_known: bool, dof: int, omega_unit: float):
    """Test of each 3-vector residual e_i with cofactor Qee_i (stack): statistic T_i, its dof r_i, p-value, z.

    T_i = e_i^T Qee_i^+ e_i / sigma0^2. With a known sigma0 (a priori) T_i ~ chi2(r_i) (Baarda's test of a
    3D residual); with an estimated sigma0 T_i / (f) ~ Beta(r_i/2, (f - r_i)/2) with f the redundancy and
    T_i computed with sigma0 = 1 divided by Omega (the multivariate tau test, Pope 1976). ``z`` is the
    standard normal value with the same two-sided p (comparable with Baarda's w and the critical value 3.29).
    """
    lam, V = np.linalg.eigh(Qee)
    top = np.maximum(lam[:, -1:], 1e-300)
    keep = lam > 1e-9 * top
    r = keep.sum(axis=1)
    y = np.einsum("nij,ni->nj", V, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        T0 = np.where(keep, y * y / np.where(keep, lam, 1.0), 0.0).sum(axis=1)
        if sigma_known:
            T = T0 / scale**2
            p = np.where(r > 0, chi2_sf(T, np.maximum(r, 1)), np.nan)
        else:
            T = T0 / max(omega_unit, 1e-300) * dof  # T0 / sigma0_hat^2
            ok = (r > 0) & (dof > r)
            beta = np.clip(T0 / max(omega_unit, 1e-300), 0.0, 1.0)
            p = np.where(ok, beta_sf(beta, np.maximum(r, 1) / 2, np.maximum(dof - r, 1) / 2), np.nan)
        z = np.where(np.isfinite(p), norm_isf(np.clip(p, 1e-300, 1.0) / 2), np.nan)
    return T, r, p, z


def angles_of(R) -> np.ndarray:
    """(rx, ry, rz) with R = Rz Ry Rx."""
    return angles_from_rotation(R)
