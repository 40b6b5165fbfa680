"""One Gauss-Helmert adjustment of all scans' poses and all targets' positions (notebook 11, sections 8-9).

Observations: the sphere centres c_o of observation o = (scan s, target g) in scan s's frame, with their 3x3
covariances. Unknowns: the pose of every scan except the reference (angles, translation, optional scale) and
the position X_g of every target seen at least twice, in the reference frame. Condition (notebook 11, eq. 13):
``s_s R_s (c_o + v_o) + t_s - X_g = 0``; for the reference scan R = I, t = 0, s = 1. B is block diagonal
(3x3 blocks s R), so B Sigma_ll B^T is too; the network has tens of observations and unknowns, so the small
A and N are formed densely, the observations never.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import pose as _pose
from ..transforms import rotation_from_angles


@dataclass(frozen=True, eq=False)
class Network:
    """The adjusted network (reduced frames) with what the statistics need."""

    angles: np.ndarray  # (k, 3)
    t: np.ndarray  # (k, 3) reduced translations
    s: np.ndarray  # (k,)
    X: np.ndarray  # (G, 3) reduced target positions
    v: np.ndarray  # (n_obs, 3) residuals of the centres
    e: np.ndarray  # (n_obs, 3) condition residuals -M k
    Qee: np.ndarray  # (n_obs, 3, 3)
    Q: np.ndarray  # N^+
    null: np.ndarray  # (u, j)
    pose_index: dict  # scan -> first column of its pose in x
    target_index: dict  # target -> first column of its position
    omega: float
    dof: int
    iterations: int
    converged: bool


def adjust(obs_scan, obs_target, centres, covs, origins, poses0, X0, reference, scale, *, tol=1e-11,
           max_iterations=30):
    """Adjust the network; poses0 (k, 4, 4) map reduced scan coordinates into the reduced reference frame.

    ``centres`` are reduced by ``origins[obs_scan]``; targets and scans without observations are skipped.
    """
    k = len(poses0)
    up = 7 if scale else 6
    scans = [s for s in range(k) if s != reference and (obs_scan == s).any()]
    pose_index = {s: i * up for i, s in enumerate(scans)}
    targets = sorted(set(obs_target.tolist()))
    target_index = {g: len(scans) * up + 3 * i for i, g in enumerate(targets)}
    u = len(scans) * up + 3 * len(targets)
    s = np.ones(k)
    angles = np.zeros((k, 3))
    for i in np.flatnonzero(np.isfinite(poses0).all(axis=(1, 2))):  # refused scans have no pose
        s[i] = np.cbrt(np.linalg.det(poses0[i, :3, :3]))
        angles[i] = _pose.angles_of(poses0[i, :3, :3] / s[i])
    t = poses0[:, :3, 3].copy()
    X = X0.copy()
    n = len(obs_scan)
    v = np.zeros_like(centres)
    col_target = np.array([target_index[int(g)] for g in obs_target])
    converged = False
    for it in range(1, max_iterations + 1):
        R = np.array([rotation_from_angles(*a) for a in angles])
        Ro = R[obs_scan]
        A = np.zeros((n, 3, u))
        for sc, c in pose_index.items():  # d f / d pose, all observations of one scan at once
            mine = obs_scan == sc
            A[mine, :, c:c + up] = _pose.pose_jacobian(angles[sc], s[sc], centres[mine] + v[mine], scale)
        A[np.arange(n)[:, None], np.arange(3)[None, :], (col_target[:, None] + np.arange(3))] = -1.0  # d f / d X
        so = s[obs_scan]
        M = (so**2)[:, None, None] * np.einsum("nij,njk,nlk->nil", Ro, covs, Ro)  # (eq. 14) s^2 R C R^T
        P = np.linalg.inv(M)
        w = so[:, None] * np.einsum("nij,nj->ni", Ro, centres) + t[obs_scan] - X[obs_target]  # (eq. 13) at x0
        PA = P @ A
        N = np.einsum("nji,njk->ik", A, PA)
        rhs = np.einsum("nji,nj->i", PA, w)
        dx, Q, null = _pose.solve_normal(N, rhs)
        kk = -np.einsum("nij,nj->ni", P, np.einsum("nij,j->ni", A, dx) + w)
        v = so[:, None] * np.einsum("nij,nkj,nk->ni", covs, Ro, kk)  # v = Sigma (s R)^T k
        for sc, c in pose_index.items():
            angles[sc] += dx[c:c + 3]
            t[sc] += dx[c + 3:c + 6]
            if scale:
                s[sc] += dx[c + 6]
        for g, c in target_index.items():
            X[g] += dx[c:c + 3]
        if np.abs(dx).max() < tol:
            converged = True
            break
    M_final = M
    e = -np.einsum("nij,nj->ni", M_final, kk)
    Qee = M_final - np.einsum("nij,jk,nlk->nil", A, Q, A)
    omega = float(np.einsum("ni,nij,nj->", kk, M_final, kk))
    dof = 3 * n - (u - null.shape[1])
    return Network(angles, t, s, X, v, e, Qee, Q, null, pose_index, target_index, omega, int(dof), it, converged)


def caller_pose(net, scan, origins, reference, scale):
    """(matrix 4x4, parameters, covariance (unit sigma0), undetermined mask) of one scan in the caller's frames."""
    up = 7 if scale else 6
    x, J = _pose.to_caller_frame(net.angles[scan], net.t[scan], net.s[scan], origins[scan], origins[reference], scale)
    c = net.pose_index[scan]
    # the reduced translation t' depends on the pose only; the target positions do not enter t
    Q = net.Q[c:c + up, c:c + up]
    null = net.null[c:c + up]
    null = null[:, np.linalg.norm(null, axis=0) > 1e-6]  # null vectors (unit length) that move this pose
    cov, bad = _pose.propagate(Q, J, null, None)
    T = np.eye(4)
    T[:3, :3] = net.s[scan] * rotation_from_angles(*net.angles[scan])
    T[:3, 3] = x[3:6]
    return T, x, cov, bad
