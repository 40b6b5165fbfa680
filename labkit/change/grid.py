"""Compiled neighbour search for M3C2 (module ``labkit.change``): a sorted voxel grid and numba kernels.

Why not the kd-tree here: ``cKDTree.query_ball_point`` answers with one Python
list per query, and building those lists cost 60-70 % of an M3C2 run (measured:
10,000 cores, 65,000 points, 2.3 s of which 1.5 s in the ball queries). The
kernels below visit the voxels of a cylinder's (or ball's) axis-aligned
bounding box instead, test the points of each voxel and accumulate the sums in
place; nothing per point is allocated. Core points run in parallel (``prange``).

The grid: every point gets the integer voxel (ix, iy, iz) of edge ``cell``
and one int64 key; points are sorted by key, and a voxel is found by binary
search in the sorted unique keys (no dense 3-D array, so a large sparse extent
costs no memory).
"""

from __future__ import annotations

import numpy as np

from ..core.arrays import extent
from ..core.frame import load_origin_kernel
from ..neighbours.eigh3 import HAVE_NUMBA

if HAVE_NUMBA:
    import numba

    _njit = numba.njit(cache=True, nogil=True, parallel=True)
    _serial = numba.njit(cache=True, nogil=True)
    _inline = numba.njit(cache=True, nogil=True, inline="always")
    _prange = numba.prange
else:  # pragma: no cover - the kd-tree route in _change_search is used instead
    _njit = _serial = _inline = None
    _prange = range

load_origin_kernel()  # M3C2's first call reduces the clouds to a local origin (numba is loaded above)

# the types the callers pass the serial kernels (writeable C-contiguous arrays): loaded below at import
_GRID = "float64[:, ::1], int64[::1], int64[::1], float64[::1], int64[::1], float64"  # points, keys, start, lo, dims, cell
_SORT_SIGNATURE = "Tuple((float64[:, ::1], int64[::1], int64[::1]))(float64[:, ::1], float64[::1], float64, int64[::1], int64)"
_CYLINDER_SIGNATURE = f"void({_GRID}, float64[:, ::1], float64[:, ::1], float64, float64, int64[::1], float64[::1], float64[::1])"
_BALL_SIGNATURE = f"void({_GRID}, float64[:, ::1], float64, int64[::1], float64[:, ::1], float64[:, :, ::1])"

PARALLEL_FROM = 50_000  # core points; below, one thread (measured: starting the OpenMP team on a loaded
#                         2-core machine cost 30-60 ms against 0.5 ms of work for 829 cores)
COUNTING_CELLS = 8  # voxels in the grid's box per point up to which VoxelGrid sorts by counting (8 bytes each)


class VoxelGrid:
    """Points sorted by voxel: ``points[start[j]:start[j + 1]]`` lie in the voxel of key ``keys[j]``."""

    def __init__(self, local: np.ndarray, cell: float):
        if len(local):
            low, high = extent(local)
        else:
            low, high = np.zeros(3), np.zeros(3)
        while np.prod([int(s // cell) + 4 for s in high - low], dtype=object) > 2**62:  # keys must fit int64
            cell *= 2.0
        self.cell = float(cell)
        self.lo = low - self.cell
        # floor((x - lo) / cell) is monotone in x: its largest value is the one of the largest x
        self.dims = np.floor((high - self.lo) / self.cell).astype(np.int64) + 3
        total = int(np.prod(self.dims, dtype=object))
        if HAVE_NUMBA and local.dtype == np.float64 and total <= COUNTING_CELLS * len(local) + 2**16:
            # few voxels per point: a counting sort (one pass, stable) instead of a comparison sort
            self.points, self.keys, self.start = _counting_sort(np.ascontiguousarray(local),
                                                                self.lo, self.cell, self.dims, total)
            return
        ijk = np.floor((local - self.lo) / self.cell).astype(np.int64)
        key = (ijk[:, 0] * self.dims[1] + ijk[:, 1]) * self.dims[2] + ijk[:, 2]
        order = np.argsort(key, kind="stable")
        self.points = np.ascontiguousarray(local[order])
        sorted_keys = key[order]
        first = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])  # first point of each voxel
        self.keys = sorted_keys[first]
        self.start = np.append(first, len(key)).astype(np.int64)

if HAVE_NUMBA:

    @_serial
    def _counting_sort(local, lo, cell, dims, total):
        """Points sorted by voxel key (stable), the occupied keys and their start offsets, by counting sort.

        The keys are those of the comparison-sort route bit for bit: the same floor((x - lo) / cell).
        """
        n = local.shape[0]
        key = np.empty(n, dtype=np.int64)
        count = np.zeros(total, dtype=np.int64)
        for i in range(n):
            ix = np.int64(np.floor((local[i, 0] - lo[0]) / cell))
            iy = np.int64(np.floor((local[i, 1] - lo[1]) / cell))
            iz = np.int64(np.floor((local[i, 2] - lo[2]) / cell))
            k = (ix * dims[1] + iy) * dims[2] + iz
            key[i] = k
            count[k] += 1
        occupied = 0
        for v in range(total):
            if count[v] > 0:
                occupied += 1
        keys = np.empty(occupied, dtype=np.int64)
        start = np.empty(occupied + 1, dtype=np.int64)
        j, offset = 0, 0
        for v in range(total):  # count[v] becomes the next free slot of voxel v
            c = count[v]
            if c > 0:
                keys[j] = v
                start[j] = offset
                j += 1
            count[v] = offset
            offset += c
        start[occupied] = n
        points = np.empty((n, 3))
        for i in range(n):  # in input order: the points of one voxel keep their order (stable)
            q = count[key[i]]
            count[key[i]] = q + 1
            points[q, 0], points[q, 1], points[q, 2] = local[i, 0], local[i, 1], local[i, 2]
        return points, keys, start



if HAVE_NUMBA:

    @_inline
    def _span(c, e, lo, cell, n):
        """Voxel index range [a, b] covering c - e .. c + e, clipped to 0 .. n - 1."""
        a = int(np.floor((c - e - lo) / cell))
        b = int(np.floor((c + e - lo) / cell))
        return max(a, 0), min(b, n - 1)

    @_inline
    def _cylinder_one(pts, keys, start, lo, dims, cell, cores, normals, radius, depth, i):
        """Core i: count, mean and sum of squared deviations (Welford) of the axial coordinates."""
        r2 = radius * radius
        cx, cy, cz = cores[i, 0], cores[i, 1], cores[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        k, mu, s = 0, 0.0, 0.0
        if not (np.isfinite(nx) and np.isfinite(ny) and np.isfinite(nz)):
            return k, mu, s
        # axis-aligned bounding box of the cylinder
        ex = abs(nx) * depth + radius * np.sqrt(max(0.0, 1.0 - nx * nx))
        ey = abs(ny) * depth + radius * np.sqrt(max(0.0, 1.0 - ny * ny))
        ez = abs(nz) * depth + radius * np.sqrt(max(0.0, 1.0 - nz * nz))
        x0, x1 = _span(cx, ex, lo[0], cell, dims[0])
        y0, y1 = _span(cy, ey, lo[1], cell, dims[1])
        z0, z1 = _span(cz, ez, lo[2], cell, dims[2])
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                base = (ix * dims[1] + iy) * dims[2]
                j = np.searchsorted(keys, base + z0)  # first voxel of this column at or after z0
                while j < keys.shape[0] and keys[j] <= base + z1:
                    for q in range(start[j], start[j + 1]):
                        dx, dy, dz = pts[q, 0] - cx, pts[q, 1] - cy, pts[q, 2] - cz
                        d = dx * nx + dy * ny + dz * nz  # axial coordinate
                        if abs(d) > depth:
                            continue
                        if dx * dx + dy * dy + dz * dz - d * d > r2:  # distance from the axis
                            continue
                        k += 1
                        delta = d - mu
                        mu += delta / k
                        s += delta * (d - mu)
                    j += 1
        return k, mu, s

    @_inline
    def _ball_one(pts, keys, start, lo, dims, cell, cores, radius, i, count, first, second):
        """Core i: count, sum of (p - c) and sum of (p - c)(p - c)^T over the points within ``radius``."""
        r2 = radius * radius
        cx, cy, cz = cores[i, 0], cores[i, 1], cores[i, 2]
        x0, x1 = _span(cx, radius, lo[0], cell, dims[0])
        y0, y1 = _span(cy, radius, lo[1], cell, dims[1])
        z0, z1 = _span(cz, radius, lo[2], cell, dims[2])
        k = 0
        sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                base = (ix * dims[1] + iy) * dims[2]
                j = np.searchsorted(keys, base + z0)
                while j < keys.shape[0] and keys[j] <= base + z1:
                    for q in range(start[j], start[j + 1]):
                        dx, dy, dz = pts[q, 0] - cx, pts[q, 1] - cy, pts[q, 2] - cz
                        if dx * dx + dy * dy + dz * dz > r2:
                            continue
                        k += 1
                        sx += dx
                        sy += dy
                        sz += dz
                        sxx += dx * dx
                        sxy += dx * dy
                        sxz += dx * dz
                        syy += dy * dy
                        syz += dy * dz
                        szz += dz * dz
                    j += 1
        count[i] = k
        first[i, 0], first[i, 1], first[i, 2] = sx, sy, sz
        second[i, 0, 0], second[i, 1, 1], second[i, 2, 2] = sxx, syy, szz
        second[i, 0, 1] = second[i, 1, 0] = sxy
        second[i, 0, 2] = second[i, 2, 0] = sxz
        second[i, 1, 2] = second[i, 2, 1] = syz

    # Each kernel twice: a serial one (small machine code, loaded from the cache in a few ms, no thread
    # team to start: the first call of a fresh process) and a parallel one for many core points. The
    # per-core arithmetic is the same function, so both give bitwise the same numbers.
    @_serial
    def _cylinder_serial(pts, keys, start, lo, dims, cell, cores, normals, radius, depth, count, mean, m2):
        for i in range(cores.shape[0]):
            count[i], mean[i], m2[i] = _cylinder_one(pts, keys, start, lo, dims, cell, cores, normals, radius,
                                                     depth, i)

    @_njit
    def _cylinder_kernel(pts, keys, start, lo, dims, cell, cores, normals, radius, depth, count, mean, m2):
        for i in _prange(cores.shape[0]):
            count[i], mean[i], m2[i] = _cylinder_one(pts, keys, start, lo, dims, cell, cores, normals, radius,
                                                     depth, i)

    @_serial
    def _ball_serial(pts, keys, start, lo, dims, cell, cores, radius, count, first, second):
        for i in range(cores.shape[0]):
            _ball_one(pts, keys, start, lo, dims, cell, cores, radius, i, count, first, second)

    @_njit
    def _ball_moments_kernel(pts, keys, start, lo, dims, cell, cores, radius, count, first, second):
        for i in _prange(cores.shape[0]):
            _ball_one(pts, keys, start, lo, dims, cell, cores, radius, i, count, first, second)


if HAVE_NUMBA:
    # the serial kernels of a first call loaded from numba's disk cache now, when this module is imported, not
    # during the first call of a fresh process (5-8 ms each on this machine: ``bench_m3c2.py --first-call``);
    # other argument types (e.g. read-only arrays) still compile on demand
    for _f, _signature in ((_counting_sort, _SORT_SIGNATURE), (_cylinder_serial, _CYLINDER_SIGNATURE),
                           (_ball_serial, _BALL_SIGNATURE)):
        _f.compile(_signature)


def _kernel(m, serial, parallel):
    """The serial kernel below PARALLEL_FROM core points, else the parallel one."""
    return parallel if m >= PARALLEL_FROM else serial


def cylinder_stats(grid: VoxelGrid, cores, normals, radius, depth):
    """Count, mean and standard deviation (ddof = 1) of the axial coordinates in each cylinder (compiled)."""
    m = len(cores)
    count, mean, m2 = np.zeros(m, dtype=np.int64), np.zeros(m), np.zeros(m)
    _kernel(m, _cylinder_serial, _cylinder_kernel)(
        grid.points, grid.keys, grid.start, grid.lo, grid.dims, grid.cell, np.ascontiguousarray(cores),
        np.ascontiguousarray(normals), float(radius), float(depth), count, mean, m2)
    with np.errstate(invalid="ignore", divide="ignore"):
        std = np.where(count > 1, np.sqrt(m2 / (count - 1)), np.nan)
    return count, np.where(count > 0, mean, np.nan), std


def ball_covariances(grid: VoxelGrid, cores, radius):
    """Counts and covariances (eq. 2 of notebook 04, divided by m) of the points within ``radius`` of each core."""
    m = len(cores)
    count, first, second = np.zeros(m, dtype=np.int64), np.zeros((m, 3)), np.zeros((m, 3, 3))
    _kernel(m, _ball_serial, _ball_moments_kernel)(grid.points, grid.keys, grid.start, grid.lo, grid.dims, grid.cell,
                                                   np.ascontiguousarray(cores), float(radius), count, first, second)
    k = np.maximum(count, 1).astype(np.float64)
    mu = first / k[:, None]  # centroid relative to the core point
    C = second / k[:, None, None] - mu[:, :, None] * mu[:, None, :]  # offsets from the core: no cancellation
    return count, C
