"""Local surface of a cloud at its points for the matching: PCA plane or quadric, noise, tilt (private).

The same PCA as :func:`labkit.features.local_pca` (notebook 04, eqs. 1-5) on the distinct points
of a compiled kd-tree, computed only at the points the matching asks for and cached per point
(:class:`Geometry`); the local quadric of ``surface='quadric'`` and the covariance of a plane
normal's random tilt (ICP's determinability test, eq. 5.12b) come from the same neighbourhoods.
Used by :mod:`labkit.registration.matching`.
"""

from __future__ import annotations

import threading

import numpy as np

from ...neighbours.eigh3 import HAVE_NUMBA, eigh3_analytic
from ...neighbours.kdtree import KDTree
from ...neighbours.kdtree_build import in_runs
from ...core.errors import LabkitError
from ...core.jit import compiled
from ...core.threads import cores
from ...neighbours.moments import covariances  # the shared kNN covariance kernel (compiled)
from .quadric_tilt import quadric_tilt

if HAVE_NUMBA:
    import numba


def _local_geometry(tree, cols, index, k):
    """Normals, local noise and change of curvature of the input points ``index`` from k neighbours.

    The same PCA as :func:`labkit.features.local_pca` (notebook 04, eqs. 1-5) on the
    tree's distinct points (exact duplicates merged), evaluated only at the query points.
    Noise is sigma_n = sqrt(k lambda_min / (k - 3)). Queries run in the tree's leaf
    order, which keeps the visited leaves in cache. Where the neighbourhood is a point
    or a line the normal and the noise are NaN.
    """
    pos = tree.representative[index]  # leaf position of each point's kept copy
    order = np.argsort(pos, kind="stable")
    out = _leaf_geometry(tree, cols, pos[order], k)[:3]
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return tuple(a[back] for a in out)


def _leaf_geometry(tree, cols, pos, k, quadric=False, eigenvalues=False, known=None):
    """:func:`_local_geometry` at the tree's own (distinct) points, given by sorted leaf positions.

    With ``quadric`` also the local quadric's coefficients and frame (the frame's normal
    oriented up), and its noise replaces the plane's: on a curved surface the plane's
    l3 holds the curvature too, and would down-weight and reject curved ground.
    The last element is always a function that returns the covariance (m, 3, 3) of the plane
    normal's random tilt (:func:`_plane_tilt`) from the same decomposition: ICP's determinability
    test (eq. 5.12b) needs it at the matched target points and would otherwise search their
    neighbours again. With ``eigenvalues`` the PCA's eigenvalues (m, 3), ascending and scaled by
    k / (k - 3) (lam[:, 0] = sigma_n^2), come just before it: the surface test of
    :func:`labkit.registration.selection.surface_mask` reads them from the same search.
    ``known`` (:class:`labkit.neighbours.treecache.NeighbourRows`, optional): the neighbours a first
    pass found; only the points whose neighbours it does not know are searched, and where it holds
    their PCA too (eigenvalues and eigenvectors) only the rest is decomposed (the same numbers:
    the covariances depend only on differences of the coordinates, :func:`~labkit.neighbours.moments.knn_moments`).
    """
    k = min(k, tree.n)
    threads = -1 if len(pos) > 2000 else 1  # threads cost more than they save on small queries
    pca = None
    if known is not None and known.k == k:
        # the plane needs no neighbours where their PCA is known (only those of the rows searched again,
        # kept apart: no (m, k) array for a few rows); the quadric fits them
        pca = None if known.pca is None else (np.empty((len(pos), 3)), np.empty((len(pos), 3, 3)))
        nb = np.empty((len(pos), k), dtype=np.intp) if quadric or pca is None else None
        rest = np.flatnonzero(~known.gather(tree, pos, nb, *(pca or ())))
        if len(rest):
            found = tree.query_leaf_positions(pos[rest], k, workers=threads if len(rest) > 2000 else 1)
            if nb is not None:
                nb[rest] = found
        if pca is not None and len(rest):
            def rest_pca(u, v):  # (rows alone: the same numbers in any ranges)
                pca[0][rest[u:v]], pca[1][rest[u:v]] = _pca_rows(tree, cols, found[u:v], k)

            _in_row_chunks(rest_pca, len(rest))
    else:
        nb = tree.query_leaf_positions(pos, k, workers=threads)
    m = len(pos)
    shapes = [(3,), (), (), (3,), (3, 2)] + ([(6,), (3, 3), (3,)] if quadric else [])
    out = [None] * len(shapes)  # written in place by the row chunks: no second copy of large results

    def work(a, b):
        part = _geometry_rows(tree, cols, pos[a:b], None if nb is None else nb[a:b], k, quadric,
                              None if pca is None else (pca[0][a:b], pca[1][a:b]))[: len(shapes)]
        if a == 0 and b == m:
            out[:] = part
            return
        for i, (v, shape) in enumerate(zip(part, shapes)):
            if out[i] is None:
                with _alloc_lock:
                    if out[i] is None:
                        out[i] = np.empty((m,) + shape, dtype=v.dtype)
            out[i][a:b] = v

    _in_row_chunks(work, m)
    n, noise, variation, lam, tangents, *fit = out
    tilt = lambda: _plane_tilt(lam, tangents, k)  # noqa: E731 - evaluated only where kept (the target)
    return (n, noise, variation, *fit, *([lam] if eigenvalues else []), tilt)


def roughness(tree, cols, a, b, k, decided=None, ties=False, pca=False):
    """Noise about the local quadric and the PCA eigenvalues at the tree's distinct points ``a..b-1``.

    One k-nearest-neighbour search for both, leaf by leaf on the cores (``a``, ``b``: leaf bounds,
    :attr:`labkit.neighbours.kdtree.KDTree.leaf_bounds`; ``cols``: the tree's coordinate columns).
    Returns the noise (m,) as :class:`Geometry` states it with ``quadric=True`` (the plane's where no
    quadric was fitted, NaN where the neighbourhood is a point or a line), the eigenvalues (m, 3) of
    the covariance 1/k sum (notebook 04, eq. 2), ascending, and the neighbours (m, k) (leaf positions,
    sorted by distance). Used by :func:`labkit.registration.selection.surface_mask`.

    ``decided(noise, lam)`` (optional) says where an upper bound of the noise already settles the
    caller's question; there the quadric is not fitted and the noise returned is that bound. The
    bound: the quadric contains the constant height along the PCA normal, whose residual sum is
    k l3, so sigma_q^2 = RSS / (k - 6) <= k l3 / (k - 6) (and the plane's k l3 / (k - 3) is smaller),
    widened by 1e-6 against rounding. ``decided`` must be monotone: true for a noise means true for
    any smaller one. With ``ties`` the neighbours come with the search's tie flags (m,) (another point at
    exactly the k-th distance, :meth:`~labkit.neighbours.kdtree.KDTree.knn_of_leaves`), as (neighbours, ties).
    With ``pca`` the PCA itself comes last: eigenvalues (m, 3) scaled by k / (k - 3) and eigenvectors
    (m, 3, 3), as :func:`_leaf_geometry` would decompose these neighbourhoods again.
    """
    k = min(k, tree.n)
    # the neighbours (int32: half the memory, the selection keeps them for ICP) and covariances, one search
    nb, _, cov, *tie = tree.knn_of_leaves(a, b, k, workers=-1, moments=k, ties=ties,
                                          dtype=np.int32 if tree.n < 2**31 else np.intp)
    pos = np.arange(a, b)
    m = b - a
    lam, noise, vecs = np.empty((m, 3)), np.empty(m), np.empty((m, 3, 3))

    def plane(u, v):  # the PCA and the plane's noise of _geometry_rows (its normals and variation are not needed)
        lam[u:v], vecs[u:v] = _pca_of(cov[u:v], k)
        with np.errstate(invalid="ignore"):
            ok = lam[u:v, 1] > 1e-12 * lam[u:v, 2]  # not a point, not a line
        noise[u:v] = np.where(ok, np.sqrt(lam[u:v, 0]), np.nan)

    _in_row_chunks(plane, m)
    lam_1k = lam * ((k - 3) / k)  # back to the covariance 1/k sum
    todo = np.isfinite(noise) if k >= 7 else np.zeros(m, dtype=bool)  # k < 7: no quadric, the plane's noise
    if decided is not None and k >= 7:
        bound = np.sqrt(lam[:, 0] * ((k - 3) / (k - 6))) * (1 + 1e-6)  # lam[:, 0] = k l3 / (k - 3)
        sure = todo & decided(bound, lam_1k)
        noise[sure] = bound[sure]
        todo &= ~sure
    if len(rows := np.flatnonzero(todo)):
        noise[rows] = _leaf_geometry_at(tree, cols, pos[rows], nb[rows], k, (lam[rows], vecs[rows]))
    return (noise, lam_1k, (nb, tie[0]) if ties else nb) + (((lam, vecs),) if pca else ())


def _leaf_geometry_at(tree, cols, pos, nb, k, pca):
    """The quadric's noise (the plane's where none was fitted) at ``pos`` with the neighbours ``nb`` and
    their PCA ``pca`` (eigenvalues, eigenvectors), on the cores."""
    out = np.empty(len(pos))

    def work(u, v):
        out[u:v] = _geometry_rows(tree, cols, pos[u:v], nb[u:v], k, True, (pca[0][u:v], pca[1][u:v]))[1]

    _in_row_chunks(work, len(pos))
    return out


def _in_row_chunks(work, m, rows=8_000):
    """``work(a, b)`` over a few row ranges per core covering ``0..m``, taken by whichever thread is free
    (:func:`labkit.neighbours.kdtree_build.in_runs`; the kernels release the GIL). Each row is computed alone:
    the same numbers as one call ``work(0, m)``."""
    threads = min(cores(), max(1, m // rows))
    in_runs(work, np.linspace(0, m, 4 * threads + 1).astype(int) if threads > 1 else [0, m], threads)


_alloc_lock = threading.Lock()


def _pca_rows(tree, cols, nb, k):
    """Eigenvalues (m, 3), ascending and scaled by k / (k - 3), and eigenvectors (m, 3, 3) of the
    neighbourhoods ``nb``: the local PCA (notebook 04, eqs. 1-5) that :func:`_geometry_rows` starts from."""
    return _pca_of(covariances(tree.data, None, nb, cols)[1], k)  # the local PCA's kernel (eqs. 1-2)


def _pca_of(cov, k):  # _pca_rows from the covariances (eq. 2, divided by k; scaled in place)
    cov *= k / (k - 3) if k > 3 else np.nan  # redundancy k - 3 of the plane (eq. 5): lambda_min is sigma_n^2
    lam, vecs = eigh3_analytic(cov)  # as np.linalg.eigh (closed form), ascending: normal = eigenvector of lambda_min
    return np.clip(lam, 0, None), vecs


def _geometry_rows(tree, cols, pos, nb, k, quadric, pca=None):
    """The PCA (and quadric) of :func:`_leaf_geometry` at the points ``pos`` with neighbours ``nb``:
    normal, noise, variation, eigenvalues, tangents (and coefficients, frame, slope covariance), and
    the eigenvectors last. ``pca``: (eigenvalues, eigenvectors) of these rows from :func:`_pca_rows`,
    when a first pass computed them (the covariances depend only on differences of the coordinates:
    the same numbers in any frame); the plane then reads no neighbours (``nb`` may be None)."""
    if pca is None:
        lam, vecs = _pca_rows(tree, cols, nb, k)
    else:  # the quadric's frame changes the eigenvectors in place below
        lam, vecs = pca[0], pca[1].copy() if quadric else pca[1]
    with np.errstate(invalid="ignore"):
        ok = lam[:, 1] > 1e-12 * lam[:, 2]  # not a point, not a line (features._determined)
    n, noise, variation = (_plane_rows if HAVE_NUMBA else _plane_rows_numpy)(lam, vecs, ok)
    tangents = vecs[:, :, 1:].copy() if quadric else vecs[:, :, 1:]  # (the quadric's frame changes below)
    if quadric:
        vecs[~ok] = np.nan
        flip = vecs[:, 2, 0] < 0  # orient the frame's normal up; h and its coefficients flip with it
        vecs[flip, :, 0] *= -1
        coef, sig, slope = np.empty((len(pos), 6)), np.empty(len(pos)), np.empty((len(pos), 3))
        _quadric(tree.data, nb, pos, vecs, coef, sig, slope)
        fit = np.isfinite(sig)  # else (k < 7, degenerate fit) the plane stays
        _, n_q = _on_quadric(coef[fit], vecs[fit], np.zeros((int(fit.sum()), 3)))
        n[fit] = n_q  # the surface normal at the point itself
        return n, np.where(fit, sig, noise), variation, lam, tangents, coef, vecs, slope
    return n, noise, variation, lam, tangents, vecs


def _plane_rows_numpy(lam, vecs, ok):
    """The plane's normal (oriented up), noise sqrt(l3) and change of curvature l3 / sum(l) per row; NaN where
    not ``ok`` (a point or a line)."""
    n = vecs[:, :, 0]
    n = np.where(n[:, 2:3] < 0, -n, n)
    n[~ok] = np.nan
    noise = np.where(ok, np.sqrt(lam[:, 0]), np.nan)
    variation = lam[:, 0] / np.maximum(lam.sum(axis=1), 1e-300)  # change of curvature l3 / sum(l)
    return n, noise, np.where(ok, variation, np.nan)


@compiled
def _plane_rows(lam, vecs, ok):  # pragma: no cover - compiled
    """:func:`_plane_rows_numpy` in one pass (the same operations: sum(l) as (l1 + l2) + l3, as numpy sums a row)."""
    m = lam.shape[0]
    n, noise, variation = np.empty((m, 3)), np.empty(m), np.empty(m)
    for i in range(m):
        if not ok[i]:
            n[i, 0] = n[i, 1] = n[i, 2] = noise[i] = variation[i] = np.nan
            continue
        flip = vecs[i, 2, 0] < 0
        for c in range(3):
            n[i, c] = -vecs[i, c, 0] if flip else vecs[i, c, 0]
        noise[i] = np.sqrt(lam[i, 0])
        total = (lam[i, 0] + lam[i, 1]) + lam[i, 2]
        if total < 1e-300:
            total = 1e-300
        variation[i] = lam[i, 0] / total
    return n, noise, variation


def _plane_tilt(lam, tangents, k):
    """Covariance of the random tilt of PCA plane normals: sum_j e_j e_j^T sigma_n^2 / (k lambda_j).

    Along each tangent eigen-direction e_j (spread lambda_j) the slope of a plane fitted to k points
    with noise sigma_n has the variance of a regression slope, sigma_n^2 / (k lambda_j); sigma_n^2 =
    k lambda_0 / (k - 3) (notebook 04, eq. 5). ``lam`` (m, 3) ascending, already scaled by k / (k - 3)
    as in :func:`_leaf_geometry` (lam[:, 0] = sigma_n^2), ``tangents`` (m, 3, 2) the eigenvectors e_1, e_2.
    """
    if HAVE_NUMBA:  # one pass, no (m, 3, 3) temporaries: the same operations
        return _plane_tilt_rows(lam, tangents, float(k - 3), k * 1e-300)
    raw = np.maximum((k - 3) * lam[:, 1:], k * 1e-300)  # k lambda_j of the unscaled covariance
    w = np.clip(lam[:, :1] / raw, 0.0, 1.0)  # tilt variance along e_1, e_2
    e1, e2 = tangents[:, :, 0], tangents[:, :, 1]
    return w[:, 0, None, None] * e1[:, :, None] * e1[:, None, :] + w[:, 1, None, None] * e2[:, :, None] * e2[:, None, :]


@compiled
def _plane_tilt_rows(lam, tangents, k3, floor):  # pragma: no cover - compiled
    """:func:`_plane_tilt` row by row: w_j = clip(l0 / max((k - 3) l_j, k 1e-300), 0, 1) and
    (w_1 e1 e1^T) + (w_2 e2 e2^T), each product formed as numpy's broadcast forms it."""
    m = lam.shape[0]
    out = np.empty((m, 3, 3))
    for i in range(m):
        w0, w1 = _tilt_share(lam[i, 0], k3 * lam[i, 1], floor), _tilt_share(lam[i, 0], k3 * lam[i, 2], floor)
        for a in range(3):
            for b in range(3):
                e1, e2 = (w0 * tangents[i, a, 0]) * tangents[i, b, 0], (w1 * tangents[i, a, 1]) * tangents[i, b, 1]
                out[i, a, b] = e1 + e2
    return out


@compiled(inline="always")
def _tilt_share(l0, raw, floor):  # pragma: no cover - compiled
    """clip(l0 / max(raw, floor), 0, 1) with numpy's NaN rules (a NaN stays NaN)."""
    if raw < floor:
        raw = floor
    x = l0 / raw
    if x < 0.0:
        x = 0.0
    elif x > 1.0:
        x = 1.0
    return x


def _quadric_kernel(X, nb, qpos, V, coef, sig, slope):  # pragma: no cover - compiled
    """Local quadric h = a u^2 + b uv + c v^2 + d u + e v + f per neighbourhood, in the PCA frame at q.

    (u, v) are the coordinates along the two largest eigenvectors, h along the normal
    (V's columns: eigenvalues ascending), all relative to the query point q itself and
    scaled by the neighbourhood's extent for conditioning. Least squares by the 6x6
    normal equations (Gaussian elimination with partial pivoting);
    sig = sqrt(RSS / (m - 6)), the noise about the curved surface; ``slope`` holds the
    covariance (var d, cov de, var e) of the surface's slopes at q, sig^2 times the (d, e)
    block of the inverse normal matrix: the random tilt of the quadric's normal.
    """
    m, k = nb.shape
    N = np.empty((6, 6))
    g = np.empty(6)
    r = np.empty(6)
    c = np.empty((6, 3))
    for i in range(m):
        q = qpos[i]
        nx, ny, nz = V[i, 0, 0], V[i, 1, 0], V[i, 2, 0]
        ax, ay, az = V[i, 0, 2], V[i, 1, 2], V[i, 2, 2]
        bx, by, bz = V[i, 0, 1], V[i, 1, 1], V[i, 2, 1]
        slope[i, :] = np.nan
        if not (np.isfinite(nx) and np.isfinite(ax) and np.isfinite(bx)) or k < 7:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        s2 = 0.0
        for j in range(k):
            p = nb[i, j]
            wx, wy, wz = X[p, 0] - X[q, 0], X[p, 1] - X[q, 1], X[p, 2] - X[q, 2]
            s2 += wx * wx + wy * wy + wz * wz
        s = np.sqrt(s2 / k)
        if s == 0.0:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        N[:, :] = 0.0
        g[:] = 0.0
        hh = 0.0
        for j in range(k):
            p = nb[i, j]
            wx, wy, wz = X[p, 0] - X[q, 0], X[p, 1] - X[q, 1], X[p, 2] - X[q, 2]
            u = (wx * ax + wy * ay + wz * az) / s
            v = (wx * bx + wy * by + wz * bz) / s
            h = wx * nx + wy * ny + wz * nz
            r[0], r[1], r[2], r[3], r[4], r[5] = u * u, u * v, v * v, u, v, 1.0
            for a in range(6):
                g[a] += r[a] * h
                for b in range(a, 6):
                    N[a, b] += r[a] * r[b]
            hh += h * h
        for a in range(6):
            for b in range(a):
                N[a, b] = N[b, a]
        A = N.copy()
        c[:, :] = 0.0  # right-hand sides: g, and the unit vectors of d and e (their inverse columns)
        c[:, 0] = g
        c[3, 1] = 1.0
        c[4, 2] = 1.0
        ok = True
        for col in range(6):  # elimination with partial pivoting
            piv = col
            for row in range(col + 1, 6):
                if abs(A[row, col]) > abs(A[piv, col]):
                    piv = row
            if abs(A[piv, col]) <= 1e-12 * abs(N[col, col]) + 1e-300:
                ok = False
                break
            if piv != col:
                for b in range(6):
                    A[col, b], A[piv, b] = A[piv, b], A[col, b]
                for b in range(3):
                    c[col, b], c[piv, b] = c[piv, b], c[col, b]
            for row in range(col + 1, 6):
                f = A[row, col] / A[col, col]
                for b in range(col, 6):
                    A[row, b] -= f * A[col, b]
                for b in range(3):
                    c[row, b] -= f * c[col, b]
        if not ok:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        for b in range(3):
            for col in range(5, -1, -1):
                t = c[col, b]
                for a in range(col + 1, 6):
                    t -= A[col, a] * c[a, b]
                c[col, b] = t / A[col, col]
        rss = hh
        for a in range(6):
            rss -= c[a, 0] * g[a]
        sig[i] = np.sqrt(max(rss, 0.0) / (k - 6))
        # back to metres: u_scaled = u / s
        coef[i, 0], coef[i, 1], coef[i, 2] = c[0, 0] / (s * s), c[1, 0] / (s * s), c[2, 0] / (s * s)
        coef[i, 3], coef[i, 4], coef[i, 5] = c[3, 0] / s, c[4, 0] / s, c[5, 0]
        s2n = sig[i] * sig[i] / (s * s)
        slope[i, 0], slope[i, 1], slope[i, 2] = s2n * c[3, 1], s2n * 0.5 * (c[4, 1] + c[3, 2]), s2n * c[4, 2]


if HAVE_NUMBA:
    _quadric = numba.njit(cache=True, nogil=True)(_quadric_kernel)
else:  # pragma: no cover - depends on the environment
    _quadric = _quadric_kernel


def _scatter_cached_numpy(slot, pos, rows, normals_buf, noise_buf, normals, noise):
    s = slot[pos]
    normals[rows], noise[rows] = normals_buf[s], noise_buf[s]


if HAVE_NUMBA:

    @numba.njit(cache=True, nogil=True)
    def _scatter_cached(slot, pos, rows, normals_buf, noise_buf, normals, noise):  # pragma: no cover - compiled
        """normals[rows] = normals_buf[slot[pos]], noise[rows] = noise_buf[slot[pos]] in one pass."""
        for r in range(rows.shape[0]):
            s, i = slot[pos[r]], rows[r]
            normals[i, 0], normals[i, 1], normals[i, 2] = normals_buf[s, 0], normals_buf[s, 1], normals_buf[s, 2]
            noise[i] = noise_buf[s]
else:  # pragma: no cover - depends on the environment
    _scatter_cached = _scatter_cached_numpy


def _foot_into_numpy(slot, pos, rows, coef_buf, frame_buf, d, nt):
    """d[rows] and nt[rows] replaced, where a quadric was fitted, by the offset to the foot point on the
    quadric of the cached points ``pos`` (through the point itself) from ``q - d`` and the normal there."""
    s = slot[pos]
    coef = coef_buf[s]
    coef[:, 5] = 0.0  # the surface through the measured q itself (see _Matcher.__call__)
    off, normal = _on_quadric(coef, frame_buf[s], -d[rows])
    fit = np.isfinite(off[:, 0])
    d[rows[fit]], nt[rows[fit]] = off[fit], normal[fit]


if HAVE_NUMBA:

    @numba.njit(cache=True, nogil=True)
    def _foot_into(slot, pos, rows, coef_buf, frame_buf, d, nt):  # pragma: no cover - compiled
        """:func:`_foot_into_numpy` in one pass, without gathered copies: the same arithmetic in numpy's order
        (the products of :func:`_on_quadric` left to right, its row sums over strided frame columns in
        sequence), the same numbers to the bit. (The frame is read in place: a view per row costs more than the row.)"""
        for r in range(rows.shape[0]):
            i, s = rows[r], slot[pos[r]]
            a, b, c, e1, e2 = coef_buf[s, 0], coef_buf[s, 1], coef_buf[s, 2], coef_buf[s, 3], coef_buf[s, 4]
            w0, w1, w2 = -d[i, 0], -d[i, 1], -d[i, 2]
            u = (w0 * frame_buf[s, 0, 2] + w1 * frame_buf[s, 1, 2]) + w2 * frame_buf[s, 2, 2]  # along t1
            v = (w0 * frame_buf[s, 0, 1] + w1 * frame_buf[s, 1, 1]) + w2 * frame_buf[s, 2, 1]  # along t2
            h = (w0 * frame_buf[s, 0, 0] + w1 * frame_buf[s, 1, 0]) + w2 * frame_buf[s, 2, 0]  # along n
            hs = ((((a * u * u + b * u * v) + c * v * v) + e1 * u) + e2 * v) + 0.0
            gu, gv = (2 * a * u + b * v) + e1, (b * u + 2 * c * v) + e2
            n0 = (frame_buf[s, 0, 0] - gu * frame_buf[s, 0, 2]) - gv * frame_buf[s, 0, 1]
            n1 = (frame_buf[s, 1, 0] - gu * frame_buf[s, 1, 2]) - gv * frame_buf[s, 1, 1]
            n2 = (frame_buf[s, 2, 0] - gu * frame_buf[s, 2, 2]) - gv * frame_buf[s, 2, 1]
            length = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
            n0, n1, n2 = n0 / length, n1 / length, n2 / length
            if n2 < 0:
                n0, n1, n2 = -n0, -n1, -n2
            o = hs - h
            off0 = o * frame_buf[s, 0, 0]
            if np.isfinite(off0):
                d[i, 0], d[i, 1], d[i, 2] = off0, o * frame_buf[s, 1, 0], o * frame_buf[s, 2, 0]
                nt[i, 0], nt[i, 1], nt[i, 2] = n0, n1, n2
else:  # pragma: no cover - depends on the environment
    _foot_into = _foot_into_numpy


def _on_quadric(coef, frame, w):
    """Offset from points to the local quadric along its frame normal, and the surface normal there.

    In the frame at q (columns of ``frame``: normal n, minor tangent t2, major tangent t1):
    (u, v, h) = w . (t1, t2, n) for w = p - q; the surface height is
    h_s(u, v) = a u^2 + b uv + c v^2 + d u + e v + f; the foot point is
    q' = p + (h_s - h) n, and the surface normal there n - dh_s/du t1 - dh_s/dv t2 (normalised).
    """
    n, t2, t1 = frame[:, :, 0], frame[:, :, 1], frame[:, :, 2]
    u = np.einsum("ij,ij->i", w, t1)
    v = np.einsum("ij,ij->i", w, t2)
    h = np.einsum("ij,ij->i", w, n)
    a, b, c, d, e, f = coef.T
    hs = a * u * u + b * u * v + c * v * v + d * u + e * v + f
    gu, gv = 2 * a * u + b * v + d, b * u + 2 * c * v + e
    normal = n - gu[:, None] * t1 - gv[:, None] * t2
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(normal[:, 2:3] < 0, -normal, normal)
    return (hs - h)[:, None] * n, normal


class Geometry:
    """Normals and noise of one cloud, computed on demand and cached (private).

    ICP with a thinned source needs the target normals only at the few target
    points that are ever matched; computing them lazily saves most of the work.
    The cache holds one entry per distinct point (leaf position of the kd-tree, exact
    duplicates merged) for the whole ICP call: the target does not move, so no point
    is computed twice. Storage is compact: a slot per computed point (``slot``, -1 for
    none) into buffers that grow with the points actually used, so that a 10-million-point
    target whose ICP touches 300,000 points holds 300,000 normals, not 10 million.
    ``n_computed`` counts the points whose geometry was computed (tests use it).
    """

    def __init__(self, points, k, normals=None, tree=None, quadric=False, keep_tilt=False, known=None):
        self.tree = KDTree(points, merge_duplicates=True) if tree is None else tree
        self.k, self.quadric, self.keep_tilt = k, quadric, keep_tilt
        self.known = known  # neighbours a first pass over the same cloud found (NeighbourRows), or None
        self.cols = np.ascontiguousarray(self.tree.data.T)  # coordinate columns for contiguous gathers
        self.given = normals  # per input point, or None
        self.slot = np.full(self.tree.n, -1, dtype=np.int32 if self.tree.n < 2**31 else np.int64)
        self.n_computed = 0
        self._store = {}  # name -> buffer (capacity, ...), rows 0..n_computed-1 used

    def _grow(self, values):
        """Append the rows of each named array to its buffer (doubling the capacity when full)."""
        n_new = len(next(iter(values.values())))
        for name, v in values.items():
            buf = self._store.get(name)
            need = self.n_computed + n_new
            if buf is None and self.n_computed == 0 and v.flags.c_contiguous and v.base is None:
                self._store[name] = v  # the first rows as they came (a whole cloud at once: no copy)
                continue
            if buf is None or len(buf) < need:
                cap = max(need, 2 * (0 if buf is None else len(buf)), 1024)
                bigger = np.empty((cap,) + v.shape[1:], dtype=v.dtype)
                if buf is not None:
                    bigger[: self.n_computed] = buf[: self.n_computed]
                self._store[name] = buf = bigger
            buf[self.n_computed : need] = v
        self.n_computed += n_new

    _SHAPES = dict(normals=(3,), noise=(), coef=(6,), frame=(3, 3), slope=(3,), tilt=(3, 3))

    def _get(self, name, pos):
        if name not in self._store:  # nothing computed yet (e.g. no pairs at all)
            return np.full((len(pos),) + self._SHAPES[name], np.nan)
        return np.take(self._store[name], self.slot[pos], axis=0)  # (a gather by index: faster than [])

    def _compute(self, pos):
        """Compute and cache the points ``pos`` (leaf positions) that the cache does not hold yet."""
        todo = self.slot[pos] < 0
        if todo.any():
            mark = np.zeros(self.tree.n, dtype=bool)
            mark[pos[todo]] = True
            new = np.flatnonzero(mark)  # sorted leaf positions: coherent queries, no sort
            out = _leaf_geometry(self.tree, self.cols, new, self.k, self.quadric, known=self.known)
            values = dict(normals=out[0], noise=out[1])
            if self.keep_tilt:
                values["tilt"] = out[-1]()
            if self.quadric:
                values.update(coef=out[3], frame=out[4], slope=out[5])
            self.slot[new] = np.arange(self.n_computed, self.n_computed + len(new))
            self._grow(values)

    def at_positions(self, pos):
        """Compute and cache the points at the leaf positions ``pos`` (e.g. a search's answers) ahead of :meth:`at`."""
        self._compute(np.asarray(pos, dtype=np.intp))

    def at(self, index, need_noise=False):
        pos = self.tree.representative[index]
        if need_noise or self.given is None:
            self._compute(pos)
        normals = self._get("normals", pos) if self.given is None else self.given[index]
        noise = self._get("noise", pos) if need_noise or self.given is None else np.full(len(pos), np.nan)
        return normals, noise

    def at_rows(self, index, rows, normals, noise, need_noise=False):
        """:meth:`at` written into ``normals[rows]`` and ``noise[rows]``: once the cache holds the points, one
        compiled pass gathers and scatters their rows instead of four copies."""
        if self.given is not None or not HAVE_NUMBA or len(index) == 0:
            normals[rows], noise[rows] = self.at(index, need_noise)
            return
        pos = self.tree.representative[index]
        self._compute(pos)  # the points not cached yet
        _scatter_cached(self.slot, pos, rows, self._store["normals"], self._store["noise"], normals, noise)

    def foot(self, index, w):
        """Offsets (m, 3) from the points ``q + w`` to the local quadric of ``q`` = point ``index``, and
        the surface normals there (requires :meth:`at` first); rows without a quadric get NaN offsets."""
        pos = self.tree.representative[index]
        coef = self._get("coef", pos)  # a copy (fancy indexing)
        coef[:, 5] = 0.0  # the surface through the measured q itself (see _Matcher.__call__)
        return _on_quadric(coef, self._get("frame", pos), w)

    def foot_at_rows(self, index, rows, d, nt, pos=None):
        """:meth:`foot` from ``q - d[rows]`` written into ``d[rows]`` and ``nt[rows]`` where a quadric was fitted
        (requires :meth:`at` first; ``pos``: the leaf positions of ``index``, when known): one compiled pass."""
        if "coef" not in self._store or len(rows) == 0:
            return  # no quadric computed: nothing fitted
        pos = self.tree.representative[index] if pos is None else pos
        _foot_into(self.slot, pos, rows, self._store["coef"], self._store["frame"], d, nt)

    def plane_tilt(self, index):
        """Covariance (m, 3, 3) of the random tilt of the PCA plane normals at the points ``index``
        (:func:`_plane_tilt`), stored with the normals (``keep_tilt``); computed here for points not
        yet matched."""
        if not self.keep_tilt:
            raise LabkitError("this geometry keeps no tilt covariances (keep_tilt=False)")
        pos = self.tree.representative[index]
        self._compute(pos)  # (the normals and noise themselves are not needed here)
        return self._get("tilt", pos)

    def tilt(self, index):
        """Covariance (m, 3, 3) of the random tilt of the quadric normals at the points ``index``.

        The normal n - d t1 - e t2 at q tilts by -(dd t1 + de t2) with the covariance of the
        fitted slopes (d, e) (requires :meth:`at` first; NaN where no quadric was fitted).
        """
        return quadric_tilt(self._store, self.slot, self.tree.representative[index], self._get)

    def compute(self, index, k):
        """Normals, noise and change of curvature at ``index`` with k neighbours (no caching)."""
        return _local_geometry(self.tree, self.cols, index, k)
