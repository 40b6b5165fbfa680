"""Update and stopping rules of the ICP iteration: the step (eq. 5.3), its damping, convergence and cycles."""

from __future__ import annotations

import numpy as np

from ...transforms import skew


def update_transform(R, t, dx, dof, L):
    """Apply the step: R <- E R, t <- E t + dt with E = exp([omega]x) (eq. 5.3)."""
    dt = dx[-3:]
    if dof == "translation":
        return R, t + dt, float(np.linalg.norm(dt))
    omega = dx[:3]
    E = rodrigues(omega)
    R_new = E @ R
    U, _, Vt = np.linalg.svd(R_new)  # keep R orthonormal over many iterations
    return U @ Vt, E @ t + dt, float(np.linalg.norm(dt) + L * np.linalg.norm(omega))


def rodrigues(omega):
    """Rotation matrix exp([omega]x), re-orthonormalized by SVD."""
    theta = np.linalg.norm(omega)
    if theta < 1e-15:
        return np.eye(3)
    k = omega / theta
    K = skew(k)
    E = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
    U, _, Vt = np.linalg.svd(E)
    return U @ Vt


def within_precision(adj, share=0.05):
    """True when every component of the update is below ``share`` of its formal standard deviation.

    In a weak direction the nearest neighbours keep changing and the iteration jitters about its
    fixed point by a small fraction of that direction's precision; an absolute ``tol`` would wait
    for it in vain.
    """
    with np.errstate(invalid="ignore"):
        std = adj.sigma0 * np.sqrt(np.diag(adj.Qxx))
    ok = np.isfinite(std)
    return bool(ok.any() and np.all(np.abs(adj.dx[ok]) <= share * std[ok]))


def step_damping(dx, previous, damping, L, tol, floor=0.125):
    """Halve the step length (down to ``floor``) when a step reverses the previous one.

    The update N_sig^-1 A^T P l (eq. 5.12b) moves a weak direction the whole way in one step; where the
    tilt noise removed from N is most of a direction's information, the step overshoots and ICP
    oscillates about the fixed point (synthetic forest ALS vs DIM, X known to about 0.1 m: a 4-cycle
    of 75 mm that never converged). A reversal is a step pointing back by more than 120 degrees
    (rotations in metres at the radius L); damping changes the path, not the fixed point.
    """
    s = np.array(dx, dtype=np.float64)
    s[:-3] *= L
    size = np.linalg.norm(s)
    if previous is not None and size > 10 * tol and s @ previous < -0.5 * size * np.linalg.norm(previous):
        damping = max(0.5 * damping, floor)
    return damping, s


def cycle_converged(cycle, adj, atol, share=0.25):
    """A cycle between a few sets of pairs is converged when its steps are below ``atol`` or when it
    moves every component by at most ``share`` of that component's standard deviation (real ALS halves:
    a 2-cycle of 1.08 mm steps, 0.2 std in X, ran to max_iterations). With ``share=0.05`` over the last
    four iterations the same test ends the damped chatter between two sets of pairs, which never
    repeats exactly (sparse hills: 0.15 mm steps at a stated 26 mm for 35 iterations)."""
    if max(h.step for h in cycle) < atol:
        return True
    with np.errstate(invalid="ignore"):
        std = adj.sigma0 * np.sqrt(np.diag(adj.Qxx))
    span = np.ptp([h.translation for h in cycle], axis=0)
    if len(std) == 6:  # rigid: rx, ry, rz (rad), tx, ty, tz
        span = np.r_[np.radians(np.ptp([h.rotation_deg for h in cycle], axis=0)), span]
    free = np.isfinite(std)
    return bool(free.any() and np.all(span[free] <= share * std[free]) and np.all(span[~free] <= atol))


def cycle_period(history, atol, longest=10):
    """Period p if the state repeats the one p iterations ago within ``atol`` (nearest neighbours
    can alternate between a few sets), else 0."""
    x = history[-1]
    t, r, atol_r = x.translation.tolist(), x.rotation_deg.tolist(), float(np.degrees(atol) / 100)
    for p in range(2, longest + 1):
        if len(history) > p:
            y = history[-1 - p]
            if _close(t, y.translation.tolist(), atol) and _close(r, y.rotation_deg.tolist(), atol_r):
                return p
    return 0


def _close(a, b, atol):
    """``np.allclose(a, b, rtol=0, atol=atol)`` of two short lists of floats, without its array overhead (equal
    infinities are close, NaN is not)."""
    return all(abs(p - q) <= atol or p == q for p, q in zip(a, b))
