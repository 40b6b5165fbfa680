"""Points of a cloud within a ball: one compiled pass over the points, no tree to build.

The verification asks a few dozen ball queries per detection; a k-d tree over
10^6 points costs about a second to build, a pass over them a few milliseconds.
The comparison is |x - c|^2 <= R^2, as in ``cKDTree.query_ball_point``.
numba loads on the first call, not on import; without it numpy does the work.
Residuals are d = sqrt(dx^2 + dy^2 + dz^2) - r summed in this order; numpy's routes
(einsum, norm) may differ from them by an ulp (about 1e-16 m at 1 m), so a point can
change sides of a band only within that distance of its edge.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import SIMD, compiled, have_numba

_KERNELS = {}  # (kernel, simd) -> the compiled kernel, or None without numba


def _jit(kernel, simd=False):
    """The compiled kernel (numba loads on its first call), or None without numba; ``simd``: loops over
    points in SIMD registers (:data:`labkit.core.jit.SIMD`)."""
    key = (kernel, simd)
    if key not in _KERNELS:  # (looked up once here: compiled's key costs a few microseconds per call)
        _KERNELS[key] = compiled(kernel, **(SIMD if simd else {})) if have_numba() else None
    return _KERNELS[key]


def _inside(x, y, z, c, R):  # pragma: no cover - compiled
    R2 = R * R
    out = np.empty(x.shape[0], dtype=np.int64)
    k = 0
    for i in range(x.shape[0]):  # compaction without a branch: write always, advance when inside
        dx, dy, dz = x[i] - c[0], y[i] - c[1], z[i] - c[2]
        out[k] = i
        k += dx * dx + dy * dy + dz * dz <= R2
    return out[:k].copy()


def _counts(X, c, radii):  # pragma: no cover - compiled
    R2 = radii * radii
    out = np.zeros(radii.shape[0], dtype=np.int64)
    R2max = R2.max() if R2.shape[0] else -1.0
    for i in range(X.shape[0]):
        dx, dy, dz = X[i, 0] - c[0], X[i, 1] - c[1], X[i, 2] - c[2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > R2max:
            continue  # outside every ball (most points): one comparison
        for j in range(radii.shape[0]):
            if d2 <= R2[j]:
                out[j] += 1
    return out



def _counts3(T, c, R2):  # pragma: no cover - compiled
    x, y, z = T[0], T[1], T[2]
    c0, c1, c2 = c[0], c[1], c[2]
    a, b, e = R2[0], R2[1], R2[2]
    na = nb = ne = 0
    for i in range(x.shape[0]):  # no branches: the compiler vectorizes the loop
        dx, dy, dz = x[i] - c0, y[i] - c1, z[i] - c2
        d2 = dx * dx + dy * dy + dz * dz
        na += d2 <= a
        nb += d2 <= b
        ne += d2 <= e
    return np.array([na, nb, ne], dtype=np.int64)


def ball_counts_t(T, c, radii):
    """:func:`ball_counts` for three radii on coordinates stored by axis, T (3, n) C-contiguous float64."""
    c = np.asarray(c, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    kernel = _jit(_counts3)
    if kernel is None:  # pragma: no cover
        return ball_counts(np.ascontiguousarray(T.T), c, radii)
    return kernel(T, c, radii * radii)


def ball_indices(X, c, R, by_axis=False):
    """Indices (ascending) of the points of X (n, 3), or (3, n) ``by_axis``, C-contiguous float64, within
    distance R of c."""
    c = np.asarray(c, dtype=np.float64)
    kernel = _jit(_inside)
    if kernel is None:  # pragma: no cover
        d = (X.T if by_axis else X) - c
        return np.flatnonzero(np.einsum("ij,ij->i", d, d) <= R * R)
    return kernel(*_columns(X, by_axis), c, float(R))


def ball_counts(X, c, radii):
    """Number of points of X within each of the distances ``radii`` of c."""
    c = np.asarray(c, dtype=np.float64)
    radii = np.atleast_1d(np.asarray(radii, dtype=np.float64))
    kernel = _jit(_counts)
    if kernel is None:  # pragma: no cover
        d = X - c
        d2 = np.einsum("ij,ij->i", d, d)
        return np.array([np.count_nonzero(d2 <= r * r) for r in radii])
    return kernel(X, c, radii)


def _shell(x, y, z, c, r, reach, close):  # pragma: no cover - compiled
    """Indices and d = |p - c| - r of the points within r + reach of c (``close``: and d > -reach)."""
    R2 = (r + reach) * (r + reach)
    n = x.shape[0]
    q = np.empty(n)
    e = np.empty(n)
    c0, c1, c2 = c[0], c[1], c[2]
    for i in range(n):  # squared distances, then residuals: loops without branches (SIMD, exact arithmetic)
        dx, dy, dz = x[i] - c0, y[i] - c1, z[i] - c2
        q[i] = dx * dx + dy * dy + dz * dz
    for i in range(n):
        e[i] = np.sqrt(q[i]) - r
    idx = np.empty(n, dtype=np.int64)
    k = 0
    for i in range(n):  # compaction in place (k <= i) without a branch: write always, advance when kept
        idx[k], e[k] = i, e[i]
        k += (q[i] <= R2) & ((not close) | (abs(e[i]) < reach))
    return idx[:k], e[:k]  # (views: no copies of the kept part)


def _shell_sparse(x, y, z, c, r, reach, close):  # pragma: no cover - compiled
    """:func:`_shell` for points mostly outside the ball: square roots only for those inside."""
    R2 = (r + reach) * (r + reach)
    n = x.shape[0]
    q = np.empty(n)
    for i in range(n):  # squared distances first: a loop without stores that depend on the data
        dx, dy, dz = x[i] - c[0], y[i] - c[1], z[i] - c[2]
        q[i] = dx * dx + dy * dy + dz * dz
    idx = np.empty(n, dtype=np.int64)
    k = 0
    for i in range(n):  # compaction without a branch: write always, advance when inside
        idx[k] = i
        k += q[i] <= R2
    d = np.empty(k)
    m = 0
    for j in range(k):
        dj = np.sqrt(q[idx[j]]) - r
        idx[m], d[m] = idx[j], dj
        m += (not close) or abs(dj) < reach
    return idx[:m].copy(), d[:m].copy()


def near_shell(X, c, r, reach, by_axis=False):
    """Indices (ascending), residuals d = |x - c| - r (eq. 25) and coordinates by axis (3, k) of the points
    of X (n, 3), or (3, n) ``by_axis``, with |d| < reach; one compiled pass and a gather."""
    idx, d = shell_points(X, c, r, reach, close=True, by_axis=by_axis)
    if not by_axis:
        return idx, d, gather(X, idx, by_axis=True)
    T = np.empty((3, len(idx)))
    for j, col in enumerate(_columns(X, by_axis)):
        np.take(col, idx, out=T[j])
    return idx, d, T


def _subtract(P, o, out):  # pragma: no cover - compiled
    for i in range(P.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = P[i, 0] - o[0], P[i, 1] - o[1], P[i, 2] - o[2]


def _subtract_both(P, o, out, T):  # pragma: no cover - compiled
    for i in range(P.shape[0]):
        a, b, e = P[i, 0] - o[0], P[i, 1] - o[1], P[i, 2] - o[2]
        out[i, 0], out[i, 1], out[i, 2] = a, b, e
        T[0, i], T[1, i], T[2, i] = a, b, e


def reduced(P, origin, by_axis=False):
    """``P - origin`` for points P (n, 3) float64 as a new array, in one compiled pass (numpy's broadcast
    runs an inner loop of three per row, about 4x slower); the same numbers. ``by_axis``: also the same
    numbers stored by axis (3, n), written in the same pass: ``(P - origin, (P - origin).T)``."""
    origin = np.asarray(origin, dtype=np.float64)
    kernel = _jit(_subtract_both if by_axis else _subtract)
    if kernel is None or P.dtype != np.float64 or not P.flags.c_contiguous or P.ndim != 2:  # pragma: no cover
        out = np.asarray(P, dtype=np.float64) - origin
        return (out, np.ascontiguousarray(out.T)) if by_axis else out
    out = np.empty(P.shape)
    if not by_axis:
        kernel(P, origin, out)
        return out
    T = np.empty((3, len(P)))
    kernel(P, origin, out, T)
    return out, T


def _gather(X, idx, by_axis_out):  # pragma: no cover - compiled
    k = idx.shape[0]
    out = np.empty((3, k)) if by_axis_out else np.empty((k, 3))
    for j in range(k):
        i = idx[j]
        if by_axis_out:
            out[0, j], out[1, j], out[2, j] = X[i, 0], X[i, 1], X[i, 2]
        else:
            out[j, 0], out[j, 1], out[j, 2] = X[i, 0], X[i, 1], X[i, 2]
    return out


def gather(X, idx, by_axis=False):
    """The rows X[idx] of points X (n, 3) C-contiguous float64, as (k, 3) or ``by_axis`` (3, k), in one
    compiled pass (numpy's take along axis 0 and the transposed copy cost 5-50x more); the same values."""
    kernel = _jit(_gather)
    idx = np.asarray(idx, dtype=np.int64)
    if kernel is None or X.dtype != np.float64 or not X.flags.c_contiguous:  # pragma: no cover
        P = np.take(X, idx, axis=0)
        return np.ascontiguousarray(P.T) if by_axis else P
    return kernel(X, idx, bool(by_axis))


def _tally(d, t, margin):  # pragma: no cover - compiled
    n = d.shape[0]
    on = np.empty(n, dtype=np.int64)
    k = inside = outside = 0
    t3 = 3.0 * t
    for i in range(n):  # compaction without a branch: write always, advance when on the shell
        a = d[i]
        on[k] = i
        k += abs(a) < t
        inside += a < -margin
        outside += (a >= t) & (a < t3)
    return on[:k].copy(), inside, outside


def shell_tally(d, t, margin=np.inf):
    """For residuals d: the indices with |d| < t (ascending), the number with d < -margin (inside) and
    with t <= d < 3 t (just outside the shell), in one compiled pass."""
    d = np.ascontiguousarray(d, dtype=np.float64)
    kernel = _jit(_tally)
    if kernel is None:  # pragma: no cover
        return (np.flatnonzero(np.abs(d) < t), int(np.count_nonzero(d < -margin)),
                int(np.count_nonzero((d >= t) & (d < 3.0 * t))))
    on, inside, outside = kernel(d, float(t), float(margin))
    return on, int(inside), int(outside)


def _ball_tally(x, y, z, c, r, reach, t, margin):  # pragma: no cover - compiled
    """:func:`_tally` of the residuals of the points within r + reach of c, without storing them."""
    R2 = (r + reach) * (r + reach)
    c0, c1, c2 = c[0], c[1], c[2]
    on = inside = outside = 0
    t3 = 3.0 * t
    for i in range(x.shape[0]):  # no branch on the data: the compiler vectorizes the counts
        dx, dy, dz = x[i] - c0, y[i] - c1, z[i] - c2
        q = dx * dx + dy * dy + dz * dz
        a = np.sqrt(q) - r
        ball = q <= R2
        on += ball & (abs(a) < t)
        inside += ball & (a < -margin)
        outside += ball & (a >= t) & (a < t3)
    return on, inside, outside


def ball_tally(T, c, r, reach, t, margin=np.inf):
    """The counts of :func:`shell_tally` (|d| < t, d < -margin, t <= d < 3 t) for the points of T (3, n) by
    axis within r + reach of c, in one compiled pass that stores nothing (:func:`shell_points`' arithmetic)."""
    c = np.asarray(c, dtype=np.float64)
    kernel = _jit(_ball_tally)
    if kernel is None:  # pragma: no cover
        _, d = shell_points(T, c, r, reach, by_axis=True)
        return (int(np.count_nonzero(np.abs(d) < t)), int(np.count_nonzero(d < -margin)),
                int(np.count_nonzero((d >= t) & (d < 3.0 * t))))
    on, inside, outside = kernel(T[0], T[1], T[2], c, float(r), float(reach), float(t), float(margin))
    return int(on), int(inside), int(outside)


def _residuals(x, y, z, c, r):  # pragma: no cover - compiled
    d = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        dx, dy, dz = x[i] - c[0], y[i] - c[1], z[i] - c[2]
        d[i] = np.sqrt(dx * dx + dy * dy + dz * dz) - r
    return d


def _columns(X, by_axis):
    """x, y, z of points stored by point (n, 3) or, with ``by_axis``, by axis (3, n) (SIMD-friendly)."""
    return (X[0], X[1], X[2]) if by_axis else (X[:, 0], X[:, 1], X[:, 2])


def residuals(X, x, by_axis=False, simd=True):
    """d = |x_i - c| - r (eq. 25) of the points X (n, 3), or (3, n) ``by_axis``, for the sphere x = [c, r];
    ``simd=False``: exactly the arithmetic of :func:`shell_points` (no fused multiply-adds)."""
    kernel = _jit(_residuals, simd=simd)
    if kernel is None or X.dtype != np.float64:  # pragma: no cover
        return np.linalg.norm((X.T if by_axis else X) - x[:3], axis=1) - x[3]
    return kernel(*_columns(X, by_axis), np.ascontiguousarray(x[:3], dtype=np.float64), float(x[3]))


def _in_shell(x, y, z, c, r, t):  # pragma: no cover - compiled
    t2 = t * t
    out = np.empty(x.shape[0], dtype=np.bool_)
    for i in range(x.shape[0]):
        dx, dy, dz = x[i] - c[0], y[i] - c[1], z[i] - c[2]
        d = np.sqrt(dx * dx + dy * dy + dz * dz) - r
        out[i] = d * d < t2
    return out


def _mark_shell(x, y, z, idx, c, r, t, mask):  # pragma: no cover - compiled
    t2 = t * t
    for i in range(x.shape[0]):  # :func:`_in_shell`'s arithmetic
        dx, dy, dz = x[i] - c[0], y[i] - c[1], z[i] - c[2]
        d = np.sqrt(dx * dx + dy * dy + dz * dz) - r
        if d * d < t2:
            mask[idx[i]] = True


def mark_shell(T, idx, c, r, t, n):
    """A mask of n points, True at idx[i] for the points T[:, i] (by axis, (3, k)) with d^2 < t^2: the mask
    ``m[idx[in_shell(T, c, r, t, by_axis=True)]] = True`` in one compiled pass, without the temporaries."""
    mask = np.zeros(n, dtype=np.bool_)
    kernel = _jit(_mark_shell)
    if kernel is None or T.dtype != np.float64:  # pragma: no cover
        mask[idx[in_shell(T, c, r, t, by_axis=True)]] = True
        return mask
    kernel(T[0], T[1], T[2], idx, np.ascontiguousarray(c, dtype=np.float64), float(r), float(t), mask)
    return mask


def in_shell(X, c, r, t, by_axis=False):
    """Mask of the points of X (n, 3), or (3, n) ``by_axis``, with d^2 < t^2, d = |x - c| - r (eqs. 25-26)."""
    kernel = _jit(_in_shell)
    if kernel is None or X.dtype != np.float64:  # pragma: no cover
        diff = (X.T if by_axis else X) - c
        d = np.sqrt(np.einsum("ij,ij->i", diff, diff)) - r
        return d * d < t * t
    return kernel(*_columns(X, by_axis), np.ascontiguousarray(c, dtype=np.float64), float(r), float(t))


def _normal_equations(x, y, z, mask, shift, c, r):  # pragma: no cover - compiled
    """J^T J (4, 4) and J^T d (4,) of the orthogonal sphere fit at (c, r), for the points - shift with
    mask_i; J^T J[3, 3] = -1 flags a point at the centre. No branch in the loop."""
    s00 = s01 = s02 = s11 = s12 = s22 = s0 = s1 = s2 = t0 = t1 = t2 = t3 = 0.0  # sums in registers
    k = zero = 0.0
    for i in range(x.shape[0]):
        wgt = np.float64(mask[i])
        dx = (x[i] - shift[0]) - c[0]
        dy = (y[i] - shift[1]) - c[1]
        dz = (z[i] - shift[2]) - c[2]
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        zero += wgt * np.float64(dist == 0.0)
        g = wgt / dist if dist > 0.0 else 0.0
        u0, u1, u2 = dx * g, dy * g, dz * g
        d = (dist - r) * wgt
        s00, s01, s02, s0 = s00 + u0 * u0, s01 + u0 * u1, s02 + u0 * u2, s0 + u0  # J^T J, row by row
        s11, s12, s1, s22, s2 = s11 + u1 * u1, s12 + u1 * u2, s1 + u1, s22 + u2 * u2, s2 + u2
        t0, t1, t2, t3, k = t0 - u0 * d, t1 - u1 * d, t2 - u2 * d, t3 - d, k + wgt  # J^T d
    JtJ = np.array([[s00, s01, s02, s0], [s01, s11, s12, s1], [s02, s12, s22, s2], [s0, s1, s2, k]])
    if zero > 0.0:
        JtJ[3, 3] = -1.0
    return JtJ, np.array([t0, t1, t2, t3])


def shell_points(X, c, r, reach, close=False, by_axis=False):
    """Indices of the points of X (n, 3), or (3, n) ``by_axis``, within r + reach of c and their residuals
    d = |x - c| - r (eq. 25); ``close``: only those with |d| < reach."""
    c = np.asarray(c, dtype=np.float64)
    kernel = _jit(_shell)
    if kernel is None:  # pragma: no cover
        X = np.ascontiguousarray(X.T) if by_axis else X
        idx = ball_indices(X, c, r + reach)
        diff = X[idx] - c
        d = np.sqrt(np.einsum("ij,ij->i", diff, diff)) - r
        keep = np.abs(d) < reach if close else slice(None)
        return idx[keep], d[keep]
    if not by_axis:  # a whole cloud by point: most points lie outside the ball
        kernel = _jit(_shell_sparse)
    return kernel(*_columns(X, by_axis), c, float(r), float(reach), bool(close))


def normal_equations(P, shift, c, r, mask=None, by_axis=False):
    """J^T J and J^T d of the orthogonal-distance sphere fit (rows J_i = -[u_i, 1], u_i the unit radial
    vector of P_i - shift about c) in one compiled pass; None when a point lies at the centre. P holds
    the points by point (n, 3) or ``by_axis`` (3, n) (C-contiguous float64: the sums run in SIMD
    registers); ``mask`` takes only the points with mask_i, without gathering them first."""
    kernel = _jit(_normal_equations, simd=True)
    if kernel is None or P.dtype != np.float64:  # pragma: no cover
        P = P.T if by_axis else P
        diff = (P if mask is None else P[mask]) - shift - c
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        if np.any(dist == 0):
            return None
        u, d = diff / dist[:, None], dist - r
        su = u.sum(axis=0)
        JtJ = np.empty((4, 4))
        JtJ[:3, :3], JtJ[:3, 3], JtJ[3, :3], JtJ[3, 3] = u.T @ u, su, su, len(diff)
        return JtJ, -np.append(u.T @ d, d.sum())
    if mask is None:
        mask = np.ones(P.shape[1] if by_axis else P.shape[0], dtype=np.bool_)
    JtJ, Jtd = kernel(*_columns(P, by_axis), mask, np.asarray(shift, dtype=np.float64), np.asarray(c, dtype=np.float64), float(r))
    return None if JtJ[3, 3] < 0 else (JtJ, Jtd)


def _band_median(d, band, nb):  # pragma: no cover - compiled
    """Median of |d_i| < band and their count: buckets by value, then the one or two middle buckets only."""
    scale = nb / band
    m = d.shape[0]
    bucket = np.empty(m, dtype=np.int32)
    over = float(nb + 1)
    for i in range(m):  # the bucket of each |d| (nb + 1: not inside the band), in a loop without branches
        a = abs(d[i])
        bucket[i] = int(min(a * scale, float(nb)) if a < band else over)  # monotone in a: the buckets keep the order
    counts = np.zeros(nb + 2, dtype=np.int64)
    for i in range(m):
        counts[bucket[i]] += 1
    n = m - counts[nb + 1]
    if n == 0:
        return np.nan, 0
    lo_rank, hi_rank = (n - 1) // 2, n // 2  # the middle order statistics (equal for odd n)
    below, b_lo = 0, 0
    while below + counts[b_lo] <= lo_rank:
        below += counts[b_lo]
        b_lo += 1
    b_hi, upto = b_lo, below + counts[b_lo]
    while upto <= hi_rank:
        b_hi += 1
        upto += counts[b_hi]
    vals = np.empty(upto - below + 1)  # the values of the middle bucket(s), gathered in one more pass
    k = 0
    for i in range(m):  # compaction without a branch: write always, advance when in the middle bucket(s)
        vals[k] = d[i]
        k += (bucket[i] >= b_lo) & (bucket[i] <= b_hi)
    vals = np.abs(vals[:k])
    vals.sort()
    lo, hi = vals[lo_rank - below], vals[hi_rank - below]
    return (lo + hi) / 2.0 if lo_rank != hi_rank else lo, n


def band_median(d, band, buckets=1024):
    """``(np.median(|d[|d| < band]|), count)`` in two streaming passes (no partition of a copy), exactly;
    (nan, 0) for no such d."""
    d = np.ascontiguousarray(d, dtype=np.float64)
    kernel = _jit(_band_median)
    if kernel is None:  # pragma: no cover
        a = np.abs(d[np.abs(d) < band])
        return (float(np.median(a)) if len(a) else float("nan")), len(a)
    m, n = kernel(d, float(band), int(buckets))
    return float(m), int(n)


def _shell_counts(G, Wsq, Csq, lo, hi):  # pragma: no cover - compiled
    out = np.zeros(G.shape[1], dtype=np.int64)
    for i in range(G.shape[0]):
        w = Wsq[i]
        for b in range(G.shape[1]):
            d2 = (w - 2.0 * G[i, b]) + Csq[b]  # numpy's Wsq[:, None] - 2.0 * G + Csq[None, :], term by term
            out[b] += (d2 > lo[b]) & (d2 < hi[b])
    return out


def shell_counts(G, Wsq, Csq, lo, hi):
    """For each column b: the i with lo_b < |w_i|^2 - 2 G_ib + |c_b|^2 < hi_b, G = W C^T (m, B); one pass over G,
    the same arithmetic as the (m, B) arrays of numpy, without them."""
    kernel = _jit(_shell_counts)
    if kernel is None or not G.flags.c_contiguous:  # pragma: no cover
        D2 = Wsq[:, None] - 2.0 * G + Csq[None, :]
        return ((D2 > lo) & (D2 < hi)).sum(axis=0)
    return kernel(G, Wsq, Csq, lo, hi)


def _plane_counts(x, y, z, nrm, off, t):  # pragma: no cover - compiled
    out = np.zeros(nrm.shape[0], dtype=np.int64)
    for b in range(nrm.shape[0]):
        n0, n1, n2, o = nrm[b, 0], nrm[b, 1], nrm[b, 2], off[b]
        k = 0
        for i in range(x.shape[0]):  # no branch: the compiler vectorizes the count
            k += abs(x[i] * n0 + y[i] * n1 + z[i] * n2 - o) < t
        out[b] = k
    return out


def plane_counts(Q, nrm, off, t):
    """Points of Q (m, 3) within t of each plane n_b . x = off_b (unit normals nrm (B, 3)), (B,)."""
    kernel = _jit(_plane_counts)
    if kernel is None:  # pragma: no cover
        return (np.abs(Q @ nrm.T - off[None, :]) < t).sum(axis=0)
    T = np.ascontiguousarray(Q.T)  # by axis: contiguous columns
    return kernel(T[0], T[1], T[2], np.ascontiguousarray(nrm), np.ascontiguousarray(off), float(t))


def _best_plane(x, y, z, tri, t):  # pragma: no cover - compiled
    """The plane through the point triple tri[b] with the most points within t: (b or -1, normal, offset)."""
    best, best_count = -1, -1
    nb = np.zeros(3)
    ob = 0.0
    for b in range(tri.shape[0]):
        i, j, k = tri[b, 0], tri[b, 1], tri[b, 2]
        u0, u1, u2 = x[j] - x[i], y[j] - y[i], z[j] - z[i]
        v0, v1, v2 = x[k] - x[i], y[k] - y[i], z[k] - z[i]
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0  # as numpy's cross
        norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if not norm > 1e-12:
            continue
        n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
        o = (x[i] * n0 + z[i] * n2) + y[i] * n1  # numpy's einsum order for three terms
        count = 0
        for m in range(x.shape[0]):  # no branch: the compiler vectorizes the count
            count += abs(x[m] * n0 + y[m] * n1 + z[m] * n2 - o) < t
        if count > best_count:  # the first of equal counts, as argmax
            best, best_count = b, count
            nb[0], nb[1], nb[2], ob = n0, n1, n2, o
    return best, nb, ob


def best_plane(Q, tri, t):
    """Of the planes through the point triples Q[tri[b]] (Q (m, 3), tri (B, 3)): the unit normal and offset
    (n . x = offset) of the one with the most points of Q within t (the first of equal counts), or None
    when every triple is degenerate; one compiled pass per plane, numpy's arithmetic."""
    kernel = _jit(_best_plane)
    if kernel is None:  # pragma: no cover
        nrm = np.cross(Q[tri[:, 1]] - Q[tri[:, 0]], Q[tri[:, 2]] - Q[tri[:, 0]])
        norm = np.linalg.norm(nrm, axis=1)
        ok = norm > 1e-12
        if not ok.any():
            return None
        nrm = nrm[ok] / norm[ok, None]
        off = np.einsum("bk,bk->b", Q[tri[ok, 0]], nrm)
        best = int(np.argmax(plane_counts(Q, nrm, off, t)))
        return nrm[best], float(off[best])
    T = np.ascontiguousarray(Q.T)
    b, nrm, off = kernel(T[0], T[1], T[2], np.ascontiguousarray(tri, dtype=np.int64), float(t))
    return None if b < 0 else (nrm, float(off))
