"""Spheres through minimal samples, their scores (eqs. 25-26) and the local optimization (LO-RANSAC)."""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dgesv, dsyev

from ..sphere.ghm import adjust_sphere
from ..core.errors import LabkitError
from ..sphere.model import algebraic_sphere, circumspheres
from ._ball import in_shell, normal_equations, shell_counts
from .config import LO_STEPS, S


def spheres_through_samples(samples, solver):
    """Spheres [xc, yc, zc, r] (B, 4) through samples (B, 4, 3) and a validity mask."""
    if solver == "closed_form":
        centers, radii, valid = circumspheres(samples)
        return np.column_stack([centers, radii]), valid
    return _ghm_hypotheses(samples)


def _ghm_hypotheses(samples):
    """The exercise sheet's way: a Gauss-Helmert adjustment of each 4-point sample (a Python loop)."""
    X = np.full((len(samples), 4), np.nan)
    valid = np.zeros(len(samples), dtype=bool)
    for j, sample in enumerate(samples):
        try:
            fit = adjust_sphere(sample)  # a sample of the checked cloud: nothing to check again
        except LabkitError:  # singular N (the exercise sheet's det test), coplanar or duplicate points
            continue
        if fit.converged and np.all(np.isfinite(fit.x)):
            X[j], valid[j] = fit.x, True
    return X, valid


def squared_center_distances(W, Wsq, C):
    """|w_i - c_b|^2 for all points and hypotheses, (m, B), via one matrix product."""
    return Wsq[:, None] - 2.0 * (W @ C.T) + np.einsum("ij,ij->i", C, C)[None, :]


def score_hypotheses(W, Wsq, X, t, scoring):
    """Score (higher is better) and inlier count of each hypothesis X (B, 4) on W (eqs. 25-26)."""
    r = X[:, 3]
    if scoring == "ransac":
        # d_i^2 < t^2  <=>  (r - t)^2 < |w_i - c|^2 < (r + t)^2   (eq. 26), counted in one compiled pass
        C = X[:, :3]
        count = shell_counts(W @ C.T, Wsq, np.einsum("ij,ij->i", C, C), np.maximum(r - t, 0.0) ** 2, (r + t) ** 2)
        return count.astype(np.float64), count
    D2 = squared_center_distances(W, Wsq, X[:, :3])
    d2 = (np.sqrt(np.maximum(D2, 0.0)) - r) ** 2  # (eq. 25)
    gain = np.maximum(t * t - d2, 0.0)  # MSAC: t^2 - min(d_i^2, t^2)
    return gain.sum(axis=0), (gain > 0).sum(axis=0)


def shell_mask(W, x, t):
    if np.ndim(t) == 0:
        return in_shell(W, x[:3], x[3], t)
    diff = W - x[:3]
    d = np.sqrt(np.einsum("ij,ij->i", diff, diff)) - x[3]  # (eq. 25)
    return d * d < t * t  # (eq. 26)


def local_optimization_step(W, Wsq, x, score, cfg):
    """LO-RANSAC: iterate (inliers -> orthogonal least-squares sphere) while the score improves."""
    improved = False
    for _ in range(LO_STEPS):
        mask = shell_mask(W, x, cfg.threshold)
        if mask.sum() <= S:
            break
        x_new = orthogonal_fit(W[mask], x)
        if x_new is None or not cfg.r_min <= x_new[3] <= cfg.r_max:
            break
        s_new, _ = score_hypotheses(W, Wsq, x_new[None, :], cfg.threshold, cfg.scoring)
        if s_new[0] <= score:
            break
        x, score, improved = x_new, s_new[0], True
    return x, score, improved


def orthogonal_fit(P, x, steps=3, mask=None, by_axis=False):
    """A few Gauss-Newton steps of the orthogonal-distance sphere fit, from x; None if it fails.

    P holds the points by point (n, 3) or ``by_axis`` (3, n); with ``mask`` only the points with
    mask_i take part, in one compiled pass each, as if ``P[mask]`` had been passed.
    """
    if x is None:
        Q = P.T if by_axis else P
        try:
            x = algebraic_sphere(Q if mask is None else Q[mask])
        except LabkitError:
            return None
    x = np.array(x, dtype=np.float64)
    shift, x = x[:3].copy(), np.array([0.0, 0.0, 0.0, x[3]])  # work relative to the current centre (UTM-safe)
    if mask is None:  # every point, in every step
        mask = np.ones(P.shape[1] if by_axis else P.shape[0], dtype=np.bool_)
    for _ in range(steps):
        # Jacobian rows J_i = -[u_i, 1] (u_i the unit radial vector); J^T J and J^T d
        # summed in one compiled pass, without forming the n x 4 matrix J
        eqs = normal_equations(P, shift, x[:3], x[3], mask, by_axis)
        if eqs is None:
            return None
        JtJ, Jtd = eqs
        eig = dsyev(JtJ, compute_v=0)[0]  # (LAPACK directly: numpy's wrappers cost more than a 4 x 4 solve)
        if not eig[0] > 1e-12 * eig[-1]:
            return None
        _, _, step, info = dgesv(JtJ, -Jtd)
        if info != 0:
            return None
        x = x + step
    x[:3] += shift
    return x if np.isfinite(x).all() and x[3] > 0 else None
