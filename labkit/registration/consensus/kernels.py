"""Kernels of the consensus cube and of its branch and bound (notebook 06).

Geometry in index space. A grid cell ``i = (ix, iy, iz)`` stands for the
translation ``t = a0 + step * i``; a difference vector ``d = q - p`` becomes
``u = (d - a0) / step``. A pair (p, q) is *consistent* at t when (eq. 6.3, 6.4)

    |t - d| < R                 (search ball; R = eps for point-to-point)
    |n_q . (t - d)| < E         (slab; point-to-plane only)

so in every grid column (ix, iy) the consistent cells of one pair form one open
z-interval. A source point counts once per cell however many of its pairs are
consistent there (eq. 6.2): the kernels merge the intervals of one point per
column before they enter a difference array along z, whose cumulative sum is
the cube. Where one point has several disjoint intervals in a column, the
compiled kernel keeps them in a buffer and enters their union once the point is
done (sorted by column and start), instead of marking cells one by one.

The compiled kernel counts the grid in blocks of a few rows (x): the difference
array of a block stays in a core's cache while every source point adds its sheet
of cells, the intervals of one grid row are computed in a branch-free loop the
compiler vectorizes, and threads take whole blocks, so their counts never meet.

Two interchangeable implementations are provided: a compiled one (numba, used
when importable) and a vectorized numpy one (sort-based deduplication). Both
give identical counts.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:  # numba is a dependency of labkit; the numpy route stays for environments without it
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - depends on the environment
    numba = None
    HAVE_NUMBA = False


#: Bytes of the difference array of one block of grid rows (a core's cache)
BLOCK_BYTES = 1 << 19


def _njit(*args, **kwargs):
    if HAVE_NUMBA:
        return numba.njit(*args, cache=True, nogil=True, **kwargs)
    return lambda f: f


# --------------------------------------------------------------------------- cube: compiled
@_njit()
def _push(buf, n, col, z0, z1):  # pragma: no cover - compiled
    """Append the interval (col, z0, z1) to the (3, cap) buffer, doubling it when full."""
    if n == buf.shape[1]:
        bigger = np.empty((3, 2 * n), np.int64)
        bigger[:, :n] = buf
        buf = bigger
    buf[0, n] = col
    buf[1, n] = z0
    buf[2, n] = z1
    return buf, n + 1


@_njit()
def _emit_union(buf, n, nz, ny, wp, diff):  # pragma: no cover - compiled
    """Enter the union of the buffered intervals of one point, per column, into the difference array."""
    B = nz + 2
    keys = buf[0, :n] * B + buf[1, :n]
    order = np.argsort(keys)
    cur, s, e = -1, 0, -1
    for o in order:
        c, a, b = buf[0, o], buf[1, o], buf[2, o]
        if c == cur and a <= e + 1:  # overlapping or adjacent: one run of cells
            if b > e:
                e = b
            continue
        if cur >= 0:
            diff[cur // ny, s, cur % ny] += wp
            diff[cur // ny, e + 1, cur % ny] -= wp
        cur, s, e = c, a, b
    if cur >= 0:
        diff[cur // ny, s, cur % ny] += wp
        diff[cur // ny, e + 1, cur % ny] -= wp


@_njit()
def _row_intervals(uy, uz, rx, axx, ay, inv, Ek, steep, E, iy0, iy1, nz, rz0, rz1):  # pragma: no cover - compiled
    """z-interval [rz0, rz1] of one pair in the columns iy0..iy1 of one grid row (empty: rz0 > rz1).

    Ball and slab as in eq. 6.3, 6.4; ``Ek`` is E for a slab and a huge number for point-to-point.
    The branch-free loop over a row is vectorized by the compiler.
    """
    if steep:  # the slab does not depend on z
        for iy in range(iy0, iy1 + 1):
            ddy = iy - uy
            rem = rx - ddy * ddy
            a = axx + ay * ddy
            z0, z1 = nz, -1
            if rem > 0.0 and abs(a) < E:
                hz = np.sqrt(rem)
                z0 = max(0, int(np.floor(uz - hz)) + 1)
                z1 = min(nz - 1, int(np.ceil(uz + hz)) - 1)
            rz0[iy] = z0
            rz1[iy] = z1
        return
    for iy in range(iy0, iy1 + 1):
        ddy = iy - uy
        rem = rx - ddy * ddy
        hz = np.sqrt(rem if rem > 0.0 else 0.0)
        a = axx + ay * ddy
        s0 = (-Ek - a) * inv
        s1 = (Ek - a) * inv
        sl = s0 if s0 < s1 else s1
        sh = s1 if s0 < s1 else s0
        lo = uz - hz  # ball
        t0 = uz + sl  # slab
        lo = lo if lo > t0 else t0
        hi = uz + hz
        t1 = uz + sh
        hi = hi if hi < t1 else t1
        z0 = int(np.floor(lo)) + 1  # open interval: first and last whole cell inside
        z0 = z0 if z0 > 0 else 0
        z1 = int(np.ceil(hi)) - 1
        z1 = z1 if z1 < nz - 1 else nz - 1
        rz0[iy] = z0 if rem > 0.0 else nz
        rz1[iy] = z1


@_njit()
def _raster_block(ptr, U, Nrm, plane, R, E, w, ny, nz, ix_lo, ix_hi, out):  # pragma: no cover - compiled
    """Counts of the grid rows ix_lo..ix_hi-1 (written into ``out``), every pair of every point.

    The difference array of a few rows, (rows, nz + 1, ny), stays in the cache while every
    source point adds its sheet of cells; the state of the columns (the merged interval of the
    current point, its stamp) is as small.
    """
    nb = ix_hi - ix_lo
    ncol = nb * ny
    diff = np.zeros((nb, nz + 1, ny), out.dtype)
    stamp = np.full(ncol, -1, np.int64)  # p: one merged interval of point p; -2 - p: several (buffered)
    zlo = np.zeros(ncol, np.int64)
    zhi = np.zeros(ncol, np.int64)
    touched = np.empty(ncol, np.int64)
    rz0 = np.empty(ny, np.int64)
    rz1 = np.empty(ny, np.int64)
    buf = np.empty((3, 1024), np.int64)  # the intervals of columns where one point has several
    R2 = R * R
    for p in range(ptr.shape[0] - 1):
        wp = w[p]
        ntouched = 0
        nbuf = 0
        several = -2 - p
        for k in range(ptr[p], ptr[p + 1]):
            ux, uy, uz = U[k, 0], U[k, 1], U[k, 2]
            ix0 = max(ix_lo, int(np.floor(ux - R)) + 1)
            ix1 = min(ix_hi - 1, int(np.ceil(ux + R)) - 1)
            if ix0 > ix1:
                continue
            ax, ay, inv, Ek = 0.0, 0.0, 1.0, 1e300
            steep = False
            if plane:
                ax, ay = Nrm[k, 0], Nrm[k, 1]
                steep = abs(Nrm[k, 2]) <= 1e-12
                inv = 0.0 if steep else 1.0 / Nrm[k, 2]
                Ek = E
            for ix in range(ix0, ix1 + 1):
                ddx = ix - ux
                rx = R2 - ddx * ddx
                if rx <= 0.0:
                    continue
                hy = np.sqrt(rx)
                iy0 = max(0, int(np.floor(uy - hy)) + 1)
                iy1 = min(ny - 1, int(np.ceil(uy + hy)) - 1)
                _row_intervals(uy, uz, rx, ax * ddx, ay, inv, Ek, steep, E, iy0, iy1, nz, rz0, rz1)
                cbase = (ix - ix_lo) * ny
                for iy in range(iy0, iy1 + 1):
                    z0, z1 = rz0[iy], rz1[iy]
                    if z0 > z1:
                        continue
                    col = cbase + iy
                    st = stamp[col]
                    if st == p:
                        if z0 <= zhi[col] + 1 and z1 >= zlo[col] - 1:  # overlapping or adjacent: merge
                            if z0 < zlo[col]:
                                zlo[col] = z0
                            if z1 > zhi[col]:
                                zhi[col] = z1
                        else:  # a second, disjoint interval: buffer both, unite them at the end
                            stamp[col] = several
                            buf, nbuf = _push(buf, nbuf, col, zlo[col], zhi[col])
                            buf, nbuf = _push(buf, nbuf, col, z0, z1)
                    elif st == several:
                        buf, nbuf = _push(buf, nbuf, col, z0, z1)
                    else:  # first interval of this point in the column
                        stamp[col] = p
                        zlo[col] = z0
                        zhi[col] = z1
                        touched[ntouched] = col
                        ntouched += 1
        for j in range(ntouched):
            col = touched[j]
            if stamp[col] == p:
                il = col // ny
                iy = col - il * ny
                diff[il, zlo[col], iy] += wp
                diff[il, zhi[col] + 1, iy] -= wp
        if nbuf:
            _emit_union(buf, nbuf, nz, ny, wp, diff)
    # cumulative sum along z, written in the (x, y, z) order of the cube
    acc = np.zeros(ny, out.dtype)
    for il in range(nb):
        acc[:] = 0
        for z in range(nz):
            for iy in range(ny):
                acc[iy] += diff[il, z, iy]
                out[ix_lo + il, iy, z] = acc[iy]


# --------------------------------------------------------------------------- cube: numpy
def _raster_numpy(ptr, U, Nrm, plane, R, E, w, nx, ny, nz, diff, budget=4_000_000):
    """Same as the compiled kernel: candidate columns from a square template, then sorting."""
    Ri = int(np.ceil(R)) + 1
    off = np.arange(-Ri, Ri + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
    per_pair = ox.size
    n_src = ptr.size - 1
    start = 0
    while start < n_src:  # chunks of whole source points
        stop = int(np.searchsorted(ptr, ptr[start] + max(1, budget // per_pair), side="right")) - 1
        stop = min(max(stop, start + 1), n_src)
        _raster_chunk(ptr, U, Nrm, plane, R, E, w, (nx, ny, nz), diff, start, stop, ox, oy)
        start = stop


def _raster_chunk(ptr, U, Nrm, plane, R, E, w, shape, diff, start, stop, ox, oy):
    nx, ny, nz = shape
    k0, k1 = ptr[start], ptr[stop]
    if k1 == k0:
        return
    u = U[k0:k1]
    owner = np.repeat(np.arange(stop - start), np.diff(ptr[start : stop + 1]))
    ix = np.floor(u[:, :1]).astype(np.int64) + ox  # (m, T)
    iy = np.floor(u[:, 1:2]).astype(np.int64) + oy
    ddx, ddy = ix - u[:, :1], iy - u[:, 1:2]
    rem = R * R - ddx * ddx - ddy * ddy
    ok = (rem > 0) & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    hz = np.sqrt(np.where(ok, rem, 0.0))
    lo, hi = u[:, 2:3] - hz, u[:, 2:3] + hz
    if plane:
        n = Nrm[k0:k1]
        a = n[:, :1] * ddx + n[:, 1:2] * ddy
        nzk = n[:, 2:3]
        steep = np.abs(nzk) <= 1e-12
        safe = np.where(steep, 1.0, nzk)
        s0, s1 = (-E - a) / safe, (E - a) / safe
        s0, s1 = np.minimum(s0, s1), np.maximum(s0, s1)
        lo = np.where(steep, lo, np.maximum(lo, u[:, 2:3] + s0))
        hi = np.where(steep, hi, np.minimum(hi, u[:, 2:3] + s1))
        ok &= ~steep | (np.abs(a) < E)
    z0 = np.maximum(np.floor(lo).astype(np.int64) + 1, 0)
    z1 = np.minimum(np.ceil(hi).astype(np.int64) - 1, nz - 1)
    ok &= z0 <= z1
    col = (ix * ny + iy)[ok]
    z0, z1 = z0[ok], z1[ok]
    group = np.broadcast_to(owner[:, None], ok.shape)[ok] * (nx * ny) + col
    # sort by (point, column, start) and clip each interval to what earlier ones left uncovered
    B = nz + 2
    key = np.sort((group * B + z0) * B + z1)
    z1s, rest = key % B, key // B
    z0s, group = rest % B, rest // B
    kend = group * B + z1s
    prev = np.concatenate(([-1], np.maximum.accumulate(kend)[:-1]))
    kstart = np.maximum(group * B + z0s, prev + 1)
    keep = kstart <= kend
    col = group[keep] % (nx * ny)
    pts = group[keep] // (nx * ny) + start
    zs, ze = kstart[keep] - group[keep] * B, z1s[keep]
    wk = w[pts]
    n_diff = diff.size
    diff += np.bincount(col * (nz + 1) + zs, weights=wk, minlength=n_diff)
    diff -= np.bincount(col * (nz + 1) + ze + 1, weights=wk, minlength=n_diff)


def raster(ptr, U, Nrm, R, E, w, shape, *, use_numba=None, workers=1):
    """Consensus counts on the grid ``shape`` from pairs in index space (eq. 6.5).

    Parameters
    ----------
    ptr : int64 (n_src + 1,)
        Pairs of source point j are ``ptr[j]:ptr[j+1]``.
    U : float64 (m, 3)
        Difference vectors in index units.
    Nrm : float64 (m, 3) or None
        Target normals for the slab test (point-to-plane), None for point-to-point.
    R, E : float
        Ball radius and slab half-width in index units.
    w : (n_src,) float64 or integer
        Weight of every source point; integer weights give int32 counts, float weights float64.
    workers : int
        Threads of the compiled kernel; each counts whole grid rows (x), so the counts do not
        depend on the number of threads, not even in the last bit of float weights.
    """
    nx, ny, nz = shape
    plane = Nrm is not None
    nrm = Nrm if plane else np.zeros((1, 3))
    dtype = np.int32 if np.issubdtype(np.asarray(w).dtype, np.integer) else np.float64
    numba_ok = HAVE_NUMBA if use_numba is None else (use_numba and HAVE_NUMBA)
    if not numba_ok:
        diff = np.zeros(nx * ny * (nz + 1))
        _raster_numpy(ptr, U, nrm, plane, float(R), float(E), np.asarray(w, np.float64), nx, ny, nz, diff)
        counts = np.cumsum(diff.reshape(nx * ny, nz + 1), axis=1)[:, :nz].reshape(nx, ny, nz)
        return np.rint(counts).astype(dtype) if dtype is np.int32 else counts
    w = np.asarray(w, dtype)
    out = np.empty(shape, dtype)
    # blocks of grid rows whose difference array (rows, nz + 1, ny) fits in a core's cache
    rows = int(np.clip(BLOCK_BYTES // ((nz + 1) * ny * out.itemsize), 1, nx))
    starts = range(0, nx, rows)

    def block(a):
        _raster_block(ptr, U, nrm, plane, float(R), float(E), w, ny, nz, a, min(nx, a + rows), out)

    if workers <= 1 or len(starts) == 1:
        for a in starts:
            block(a)
    else:  # the compiled kernel releases the GIL; the threads take the blocks in turn
        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(block, starts))
    return out


# --------------------------------------------------------------------------- branch and bound
@_njit()
def _children_numba(act, src, D, Nrm, plane, centres, R, E, h, w, out_idx, out_len, ub, lb, sure):  # pragma: no cover
    m = act.shape[0]
    Ru, Eu = R + h, E + h  # enlarged: consistent somewhere in the box is possible
    Rs, Es = R - h, E - h  # shrunken: consistent everywhere in the box
    for c in range(centres.shape[0]):
        cx, cy, cz = centres[c, 0], centres[c, 1], centres[c, 2]
        n_out = 0
        su, sl, ss = 0.0, 0.0, 0.0
        j = 0
        while j < m:
            s = src[act[j]]
            group_start = n_out
            any_u, any_l, any_s = False, False, False
            while j < m and src[act[j]] == s:
                k = act[j]
                j += 1
                ex, ey, ez = cx - D[k, 0], cy - D[k, 1], cz - D[k, 2]
                d2 = ex * ex + ey * ey + ez * ez
                if d2 >= Ru * Ru:
                    continue
                dn = 0.0
                if plane:
                    dn = abs(Nrm[k, 0] * ex + Nrm[k, 1] * ey + Nrm[k, 2] * ez)
                    if dn >= Eu:
                        continue
                any_u = True
                out_idx[c, n_out] = k
                n_out += 1
                if d2 < R * R and dn < E:
                    any_l = True
                    if Rs > 0.0 and d2 < Rs * Rs and (not plane or dn < Es):
                        any_s = True
            if any_s:  # consistent in the whole box: count it once, drop its pairs
                ss += w[s]
                n_out = group_start
            else:
                if any_u:
                    su += w[s]
                if any_l:
                    sl += w[s]
        out_len[c] = n_out
        ub[c] = su
        lb[c] = sl
        sure[c] = ss


def _children_numpy(act, src, D, Nrm, plane, centres, R, E, h, w):
    e = centres[:, None, :] - D[act][None, :, :]  # (8, m, 3)
    d2 = np.einsum("cmi,cmi->cm", e, e)
    dn = np.abs(np.einsum("cmi,mi->cm", e, Nrm[act])) if plane else np.zeros_like(d2)
    up = (d2 < (R + h) ** 2) & (dn < E + h)
    low = (d2 < R * R) & (dn < E)
    certain = (d2 < max(R - h, 0.0) ** 2) & ((dn < E - h) if plane else True) & low
    s = src[act]
    n_src = w.size
    out, ub, lb, sure = [], np.zeros(len(centres)), np.zeros(len(centres)), np.zeros(len(centres))
    for c in range(len(centres)):
        is_sure = np.zeros(n_src, bool)
        is_sure[s[certain[c]]] = True
        keep = up[c] & ~is_sure[s]
        out.append(act[keep])
        sure[c] = w[is_sure].sum()
        ub[c] = w[np.unique(s[keep])].sum()
        lb[c] = w[np.unique(s[low[c] & ~is_sure[s]])].sum()
    return out, ub, lb, sure


def children(act, src, D, Nrm, centres, R, E, h, w, *, use_numba=None):
    """Bounds of the boxes with the given centres and half diagonal h (eq. 6.7, 6.8).

    ``act`` are the pairs (sorted by source point) that may be consistent
    somewhere in the parent box. A source point with a pair consistent in the
    whole child box (radius - h, eps - h) is *sure*: it is counted in ``sure``
    and its pairs are dropped. Returns per child the remaining pairs that pass
    the enlarged test (radius + h, eps + h), the weight of the uncertain points
    passing it (upper bound minus sure), the weight of the uncertain points
    consistent at the centre (exact consensus minus sure), and ``sure``.
    """
    plane = Nrm is not None
    nrm = Nrm if plane else np.zeros((1, 3))
    numba_ok = HAVE_NUMBA if use_numba is None else (use_numba and HAVE_NUMBA)
    if not numba_ok:
        return _children_numpy(act, src, D, nrm, plane, centres, R, E, h, w)
    nc = len(centres)
    out_idx = np.empty((nc, act.size), dtype=np.int64)
    out_len = np.zeros(nc, np.int64)
    ub, lb, sure = np.zeros(nc), np.zeros(nc), np.zeros(nc)
    _children_numba(act, src, D, nrm, plane, centres, R, E, h, w, out_idx, out_len, ub, lb, sure)
    return [out_idx[c, : out_len[c]].copy() for c in range(nc)], ub, lb, sure
