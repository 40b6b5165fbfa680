"""Compiled passes over the points of a sphere adjustment (numba, loaded on the first call).

The Gauss-Helmert iteration of :mod:`labkit.sphere.ghm` needs, per iteration,
two sweeps over the points: (1) linearize at l + v0 and sum the normal
equations N = A^T P A, n = A^T P w (eqs. 8-11, 21), (2) the correlates k and
residuals v (eqs. 13, 19); after the last one, a third for the main check,
the redundancy numbers and the w-test. With independent points of equal or
per-point precision (``B Sigma_ll B^T`` diagonal with b_i^T Sigma_i b_i =
sigma_i^2, since |b_i| = 1) each sweep is one compiled loop over the (n, 3)
coordinates: no (3, n) copies, no temporaries of length n but the results.
The sums run in another order than numpy's, so results agree with the numpy
route of :mod:`~labkit.sphere.ghm` to rounding (about 1e-15 relative).

The kernels are compiled by :func:`labkit.core.jit.compiled` when they are
first asked for (numba is imported then, never on import of this module);
without numba the callers keep their numpy route.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import compiled, have_numba


def _linearize_sums(pts, o, v0, x, q, u, b, w, first):  # pragma: no cover - compiled
    """Sweep (1): rows b_i (eq. 10) and misclosures w_i (eq. 8) at l + v0, x; N and n (eq. 21).

    l_i = pts_i - o; q has one element (all points alike) or one per point;
    u = 4 unknowns, or 3 with the radius held; ``first``: v0 = 0 (not read: the same numbers, as
    l + 0 = l and r - 0 = r). Returns N, n, min r_i, max|l|, largest extent of l.
    """
    one = q.shape[0] == 1
    p_one = 1.0 / q[0]  # the weight of every point when all are alike (one division, not one per point)
    n00 = n01 = n02 = n11 = n12 = n22 = n03 = n13 = n23 = n33 = 0.0  # sums in scalars (registers)
    g0 = g1 = g2 = g3 = 0.0
    rmin, amax = np.inf, 0.0
    lo0 = lo1 = lo2 = np.inf
    hi0 = hi1 = hi2 = -np.inf
    for i in range(pts.shape[0]):
        l0, l1, l2 = pts[i, 0] - o[0], pts[i, 1] - o[1], pts[i, 2] - o[2]
        lo0, lo1, lo2 = min(lo0, l0), min(lo1, l1), min(lo2, l2)
        hi0, hi1, hi2 = max(hi0, l0), max(hi1, l1), max(hi2, l2)
        amax = max(amax, abs(l0), abs(l1), abs(l2))
        if first:
            a0, a1, a2 = l0 - x[0], l1 - x[1], l2 - x[2]
        else:
            a0, a1, a2 = (l0 + v0[i, 0]) - x[0], (l1 + v0[i, 1]) - x[1], (l2 + v0[i, 2]) - x[2]
        ri = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)  # (eq. 11)
        rmin = min(rmin, ri)
        b0, b1, b2 = a0 / ri, a1 / ri, a2 / ri  # (eq. 10)
        wi = ri - x[3]  # (eq. 8)
        if not first:
            wi -= b0 * v0[i, 0] + b1 * v0[i, 1] + b2 * v0[i, 2]
        b[i, 0], b[i, 1], b[i, 2], w[i] = b0, b1, b2, wi
        p = p_one if one else 1.0 / q[i]
        pb0, pb1, pb2 = p * b0, p * b1, p * b2  # a_i^T p_i with a_i = -[b_i, 1] (eq. 9), signs below
        n00, n01, n02, n03 = n00 + pb0 * b0, n01 + pb0 * b1, n02 + pb0 * b2, n03 + pb0
        n11, n12, n13, n22, n23, n33 = n11 + pb1 * b1, n12 + pb1 * b2, n13 + pb1, n22 + pb2 * b2, n23 + pb2, n33 + p
        g0, g1, g2, g3 = g0 - pb0 * wi, g1 - pb1 * wi, g2 - pb2 * wi, g3 - p * wi
    N = np.array([[n00, n01, n02, n03], [n01, n11, n12, n13], [n02, n12, n22, n23], [n03, n13, n23, n33]])
    rhs = np.array([g0, g1, g2, g3])
    extent = max(hi0 - lo0, hi1 - lo1, hi2 - lo2)
    return N[:u, :u].copy(), rhs[:u].copy(), rmin, amax, extent


def _correlates(b, w, dx, q, k, v):  # pragma: no cover - compiled
    """Sweep (2): k_i = -(a_i^T dx + w_i) / q_i (eq. 19), v_i = Sigma_i b_i k_i (eq. 13); returns v^T P v."""
    one = q.shape[0] == 1
    dr = dx[3] if dx.shape[0] == 4 else 0.0
    omega = 0.0
    for i in range(b.shape[0]):
        qi = q[0 if one else i]
        Adx = -(dx[0] * b[i, 0] + dx[1] * b[i, 1] + dx[2] * b[i, 2] + dr)  # a_i = [-b_i, -1] (eq. 9)
        ki = -(Adx + w[i]) / qi
        k[i] = ki
        s = qi * ki
        v[i, 0], v[i, 1], v[i, 2] = b[i, 0] * s, b[i, 1] * s, b[i, 2] * s
        omega += qi * ki * ki
    return omega


def _statistics(pts, o, v, b, k, q, x, Q, scale, red, e, wt):  # pragma: no cover - compiled
    """Sweep (3): main check max|f(l + v, x)| (eq. 4), redundancy numbers r_i = 1 - p_i a_i^T Q a_i,
    residuals along the normal e_i = -q_i k_i and the test values w_i = e_i / (scale sqrt(q_i r_i))."""
    one = q.shape[0] == 1
    four = Q.shape[0] == 4
    main = 0.0
    for i in range(pts.shape[0]):
        c0 = (pts[i, 0] - o[0]) + v[i, 0] - x[0]
        c1 = (pts[i, 1] - o[1]) + v[i, 1] - x[1]
        c2 = (pts[i, 2] - o[2]) + v[i, 2] - x[2]
        main = max(main, abs(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) - x[3]))
        b0, b1, b2 = b[i, 0], b[i, 1], b[i, 2]
        h = (Q[0, 0] * b0 * b0 + Q[1, 1] * b1 * b1 + Q[2, 2] * b2 * b2
             + 2.0 * (Q[0, 1] * b0 * b1 + Q[0, 2] * b0 * b2 + Q[1, 2] * b1 * b2))
        if four:
            h += 2.0 * (Q[3, 0] * b0 + Q[3, 1] * b1 + Q[3, 2] * b2) + Q[3, 3]
        qi = q[0 if one else i]
        ri = min(max(1.0 - h / qi, 0.0), 1.0)
        red[i] = ri
        e[i] = -qi * k[i]
        wt[i] = e[i] / (scale * np.sqrt(qi * ri)) if ri > 1e-10 else np.nan
    return main


def point_statistics(pts, origin, it, Qxx, scale, statistics):
    """Main check, redundancy numbers, normal residuals, w-test values and v (n, 3) of the iteration state
    ``it`` (b, v (n, 3), k, qbb, x) in one compiled sweep ``statistics`` (:func:`_statistics`)."""
    n = len(pts)
    ri, e, w = np.empty(n), np.empty(n), np.empty(n)
    main_check = statistics(pts, origin, it.v, it.b, it.k, it.qbb, it.x, Qxx, float(scale), ri, e, w)
    return main_check, ri, e, w, it.v


def compiled_sweeps():
    """The three compiled sweeps, or None without numba."""
    # (not SIMD: the coordinates may be UTM-sized, and a reordered l_i = p_i - o would lose their digits)
    if not have_numba():  # pragma: no cover - depends on the environment
        return None
    return tuple(compiled(f, error_model="numpy") for f in (_linearize_sums, _correlates, _statistics))
