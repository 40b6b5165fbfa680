"""What the data tell ICP after re-matching: the tilt noise of the target normals (eq. 5.12b).

N = A^T P A of one adjustment holds, besides the information about the shift, a part that the random
tilt of the estimated target normals fakes while the correspondences stay fixed; after re-matching
it is gone. :func:`tilt_information` estimates that part, :func:`normal_information` keeps of a
point-to-point N only the components along the normals, and :func:`sandwich_precision` turns the
rest into the precision of the fixed point that determinability (eq. 5.12a) is judged on.
"""

from __future__ import annotations

import numpy as np

from ...core.jit import compiled, have_numba
from ...transforms import skew

#: The tilt information of eq. (5.12b) is summed over at most this many correspondences (an even subset).
TILT_ROWS = 8000


class TiltVariance:
    """Covariance of the random tilt of each target point's PCA normal, computed once per point (private).

    A plane fitted to k neighbours with noise sigma_n has, along each tangent eigen-direction e_j of
    the neighbours' spread lambda_j, a slope error of variance sigma_n^2 / (k lambda_j): the error
    of a regression slope. The tilt covariance is sum_j e_j e_j^T sigma_n^2 / (k lambda_j), with
    sigma_n^2 = k lambda_0 / (k - 3) (notebook 04, eq. 5). With ``surface='quadric'`` the normal is
    the quadric's (at the foot point near q_j), whose slopes are fitted together with the
    curvatures and tilt more: the covariance of the slopes at q_j from the quadric's fit is used.
    """

    def __init__(self, matcher):
        self.points, self.tree, self.k = matcher.target, matcher.tree, matcher.options["k"]
        self.slot = np.full(len(self.points), -1, dtype=np.int64)  # row in C of each computed point
        self.C = np.empty((0, 3, 3))  # only the points ever asked for (a few of a large target)
        quadric = matcher.options.get("surface") == "quadric"
        self.geometry = matcher.geometry if quadric else None
        self.stored = getattr(getattr(matcher, "geometry", None), "plane_tilt", None)  # kept with the normals
        self.source_normals = getattr(matcher, "source_normals", None)  # for the tilt the data show (observed_tilt)

    def __call__(self, j):
        if self.geometry is not None:  # the quadric's slopes (computed with the matching)
            C = self.geometry.tilt(j)
            bad = np.isnan(C[:, 0, 0])
            if bad.any():
                C[bad] = self._plane(j[bad])
            return C
        return self._plane(j)

    def _plane(self, j):
        if self.stored is not None:
            return self.stored(j)
        todo = np.unique(j[self.slot[j] < 0])
        if todo.size:
            new = [self._compute(todo[a : a + 50000]) for a in range(0, todo.size, 50000)]  # bounded gathers
            self.slot[todo] = len(self.C) + np.arange(todo.size)
            self.C = np.concatenate([self.C, *new])
        return self.C[self.slot[j]]

    def _compute(self, index):
        k = self.k
        nb = self.tree.query(self.points[index], k=k, workers=-1 if len(index) > 2000 else 1)[1]
        X = self.points[nb]
        X = X - X.mean(axis=1, keepdims=True)
        lam, V = np.linalg.eigh(np.einsum("cki,ckj->cij", X, X) / k)  # ascending
        s2 = np.clip(lam[:, 0], 0, None) * k / (k - 3)
        t = np.clip(lam[:, 1:], 1e-300, None)
        w = np.clip(s2[:, None] / (k * t), 0.0, 1.0)  # tilt variance along e_1, e_2
        return np.einsum("cj,cij,ckj->cik", w, V[:, :, 1:], V[:, :, 1:])


def normal_information(A, P, n, N, opts):
    """The part of N along the target normals: what a shift changes after re-matching (eq. 5.12b).

    Point-to-plane rows already are that part (N itself). A point-to-point residual q - p also holds
    the offset between the two samplings along the surface; a shift along the surface re-matches the
    points and leaves that offset's mean unchanged, so only the rows' components along the normal,
    A^T n, carry information. Without this, point-to-point ICP on two samplings of one surface
    claimed millimetres in X and Y while 10-100 stated sigma off.
    """
    if opts.metric == "point_to_plane":
        return N
    n = n() if callable(n) else n  # the normals of the rows (or a function that gathers them: only needed here)
    a = np.einsum("mru,mr->mu", A, np.nan_to_num(n))  # A^T n per row
    return np.einsum("m,mu,mv->uv", P, a, a)


def tilt_information(corr, rows, P, opts, R=None):
    """The part of N that the random tilt of the target normals fakes (eq. 5.12b), scaled parameters.

    A point-to-plane row a_i = G_i n_i (G = I, or [[p]x / L; I] for rigid) uses the estimated normal
    n = n0 + e with a tilt e of covariance C_i (see :class:`TiltVariance`). E[a a^T] = G (n0 n0^T + C_e) G^T: the
    second part is information about the shift only while the correspondences stay fixed; after
    re-matching, a random tilt points elsewhere. On a flat field it is all that N contains, and it
    would make X and Y look determined to centimetres.
    """
    u = 6 if opts.dof == "rigid" else 3
    if len(rows) == 0:
        return np.zeros((u, u))
    if len(rows) > TILT_ROWS:  # an even subset estimates the sum (the tilts are computed once per point)
        stride = -(-len(rows) // TILT_ROWS)
        total = P.sum()
        rows, P = rows[::stride], P[::stride]
        P = P * (total / max(P.sum(), 1e-300))
    C = opts.tilt(corr.target_index[rows])  # (m, 3, 3) tilt covariance of each target normal
    if R is not None:  # the tilt the data show where it exceeds the model's (eq. 5.12c)
        excess = _excess(observed_tilt(corr, rows, P, opts, R), _weighted_sum(P, C) / P.sum())
        if opts.dof != "rigid" and have_numba():  # sum_m P (C + excess) without the shifted copy of C
            return compiled(_weighted_sum_kernel)(P, C, excess)
        C = C + excess
    if opts.dof == "rigid":
        p = corr.source_xyz[rows] - opts.origin
        G = np.concatenate([skew(p) / opts.L, np.broadcast_to(np.eye(3), (len(p), 3, 3))], axis=1)
        return np.einsum("m,mai,mij,mbj->ab", P, G, C, G)
    return _weighted_sum(P, C)


def _weighted_sum(P, C):
    """sum_m P_m C_m of the (m, 3, 3) covariances C: np.einsum("m,mij->ij"), compiled in its order (the same
    numbers)."""
    if not have_numba():  # pragma: no cover - depends on the environment
        return np.einsum("m,mij->ij", P, C)
    return compiled(_weighted_sum_kernel)(P, C, np.zeros((3, 3)))


def _weighted_sum_kernel(P, C, X):  # pragma: no cover - compiled
    """sum_m P_m (C_m + X), the terms added in row order (np.einsum's order), (C + X) formed first as numpy would."""
    out = np.zeros((3, 3))
    for i in range(P.shape[0]):
        for a in range(3):
            for b in range(3):
                out[a, b] += P[i] * (C[i, a, b] + X[a, b])
    return out


def observed_tilt(corr, rows, P, opts, R):
    """Tilt covariance of one epoch's normals as the data show it: half the weighted mean of D D^T (eq. 5.12c).

    D = R n_s - n_t is the difference between the source normal (moved) and the target normal of each
    pair. Where both epochs sample one surface, D holds the two normals' tilt noise (C_s + C_t, about 2 C);
    where the surface's fine relief is new in each epoch (grass, crops, ploughed or trodden ground, low
    vegetation left in the ground class), D holds that as well, and the model of :class:`TiltVariance`
    (white noise about a smooth surface) misses it: on such flat fields ICP walked metres in X and Y
    while it stated +-6 cm. None without source normals.
    """
    ns = getattr(opts.tilt, "source_normals", None)
    if ns is None or len(rows) == 0:
        return None
    if have_numba():  # one pass over the rows, the same operations (see _observed_kernel)
        S, ok = compiled(_observed_kernel)(ns, rows, np.ascontiguousarray(R, dtype=np.float64), corr.target_normal, P)
        return 0.5 * S / P[ok].sum() if ok.any() else None
    a = np.einsum("ij,kj->ik", ns[rows], R)
    b = corr.target_normal[rows]
    a = a * np.sign(np.einsum("ij,ij->i", a, b))[:, None]  # normals are unsigned
    D = a - b
    ok = np.isfinite(D).all(axis=1)
    if not ok.any():
        return None
    return 0.5 * np.einsum("m,mi,mj->ij", P[ok], D[ok], D[ok]) / P[ok].sum()


def _observed_kernel(ns, rows, R, tn, P):  # pragma: no cover - compiled
    """sum P D D^T over the rows with a finite D = s R n_s - n_t (s: the sign of R n_s . n_t), and those rows: the
    rotation and the dot product with einsum's sums, the outer products added in row order (its order too)."""
    m = rows.shape[0]
    ok = np.zeros(m, np.bool_)
    s00 = s01 = s02 = s10 = s11 = s12 = s20 = s21 = s22 = 0.0  # the sums in variables (not stored every row)
    for r in range(m):
        i = rows[r]
        x, y, z = ns[i, 0], ns[i, 1], ns[i, 2]
        a0 = (x * R[0, 0] + z * R[0, 2]) + y * R[0, 1]
        a1 = (x * R[1, 0] + z * R[1, 2]) + y * R[1, 1]
        a2 = (x * R[2, 0] + z * R[2, 2]) + y * R[2, 1]
        b0, b1, b2 = tn[i, 0], tn[i, 1], tn[i, 2]
        dot = (a0 * b0 + a2 * b2) + a1 * b1
        s = 1.0 if dot > 0 else (-1.0 if dot < 0 else (0.0 if dot == 0 else np.nan))  # np.sign
        d0, d1, d2 = a0 * s - b0, a1 * s - b1, a2 * s - b2
        if np.isfinite(d0) and np.isfinite(d1) and np.isfinite(d2):
            ok[r] = True
            pd = P[r] * d0
            s00 += pd * d0
            s01 += pd * d1
            s02 += pd * d2
            pd = P[r] * d1
            s10 += pd * d0
            s11 += pd * d1
            s12 += pd * d2
            pd = P[r] * d2
            s20 += pd * d0
            s21 += pd * d1
            s22 += pd * d2
    return np.array([[s00, s01, s02], [s10, s11, s12], [s20, s21, s22]]), ok


def _excess(observed, model):
    """The part of ``observed`` beyond ``model`` (both 3 x 3): eigenvalues of the difference clipped at 0."""
    if observed is None:
        return np.zeros((3, 3))
    lam, V = np.linalg.eigh(0.5 * (observed - model + (observed - model).T))
    return (V * np.clip(lam, 0, None)) @ V.T


def sandwich_precision(N, N_sig):
    """(N_sig^-1 N N_sig^-1)^-1 = N_sig N^-1 N_sig with N_sig's negative eigenvalues set to 0 (eq. 5.12b).

    Its eigenvalues give sigma0 / sqrt(lambda) = the standard deviation of the fixed point along each
    direction; a direction that holds no information beyond the tilt noise gets 0.
    """
    lam, V = np.linalg.eigh(0.5 * (N_sig + N_sig.T))
    S = (V * np.clip(lam, 0, None)) @ V.T
    Pi = S @ np.linalg.lstsq(N, S, rcond=None)[0]
    return 0.5 * (Pi + Pi.T)
