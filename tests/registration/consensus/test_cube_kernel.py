"""The counting kernel of the consensus cube against a plain per-point reference, cell for cell.

The reference enters every pair of a source point into the columns of the whole grid, merges
the z-intervals of the point per column and adds them to one difference array along z (eq. 6.5):
the direct transcription of the definition the compiled kernel must reproduce exactly, whatever
its blocks of rows, its threads or the dtype of its counts.
"""

import numpy as np
import pytest

from labkit.registration import consensus_cube, consensus_inputs
from labkit.registration.consensus import kernels as K
from labkit.registration.consensus.inputs import candidate_pairs, grid
from labkit.synthetic import als_epochs

numba = pytest.importorskip("numba")


@numba.njit(cache=False)
def _reference(ptr, U, Nrm, plane, R, E, w, nx, ny, nz):
    """Counts by the definition: per point and column the union of its pairs' intervals."""
    diff = np.zeros((nx * ny, nz + 1))
    cover = np.zeros((nx * ny, nz), np.bool_)
    for p in range(ptr.shape[0] - 1):
        cover[:] = False
        for k in range(ptr[p], ptr[p + 1]):
            ux, uy, uz = U[k, 0], U[k, 1], U[k, 2]
            for ix in range(nx):
                for iy in range(ny):
                    ddx, ddy = ix - ux, iy - uy
                    rem = R * R - ddx * ddx - ddy * ddy
                    if rem <= 0.0:
                        continue
                    hz = np.sqrt(rem)
                    lo, hi = uz - hz, uz + hz
                    if plane:
                        a = Nrm[k, 0] * ddx + Nrm[k, 1] * ddy
                        if abs(Nrm[k, 2]) <= 1e-12:
                            if abs(a) >= E:
                                continue
                        else:
                            s0, s1 = (-E - a) / Nrm[k, 2], (E - a) / Nrm[k, 2]
                            lo = max(lo, uz + min(s0, s1))
                            hi = min(hi, uz + max(s0, s1))
                    for iz in range(max(0, int(np.floor(lo)) + 1), min(nz - 1, int(np.ceil(hi)) - 1) + 1):
                        cover[ix * ny + iy, iz] = True
        for c in range(nx * ny):  # the runs of covered cells enter the difference array
            for iz in range(nz):
                if cover[c, iz] and (iz == 0 or not cover[c, iz - 1]):
                    diff[c, iz] += w[p]
                if cover[c, iz] and (iz == nz - 1 or not cover[c, iz + 1]):
                    diff[c, iz + 1] -= w[p]
    out = np.empty((nx * ny, nz))
    for c in range(nx * ny):
        acc = 0.0
        for iz in range(nz):
            acc += diff[c, iz]
            out[c, iz] = acc
    return out.reshape(nx, ny, nz)


def reference(ptr, U, Nrm, R, E, w, shape):
    plane = Nrm is not None
    return _reference(ptr, U, Nrm if plane else np.zeros((1, 3)), plane, float(R), float(E), np.asarray(w, float),
                      *shape)


def tangled_pairs(rng, n_src=40, per_point=25, shape=(14, 17, 19), R=4.5):
    """Random pairs clustered per point with tilted, steep and exactly vertical planes:
    several disjoint intervals per column, pairs beyond the grid, every branch of the kernel."""
    gen = np.random.default_rng(rng)
    lens = gen.integers(0, per_point, n_src)
    ptr = np.concatenate(([0], np.cumsum(lens)))
    centre = gen.uniform(-3, np.array(shape) + 3, (n_src, 3))
    U = np.repeat(centre, lens, axis=0) + gen.normal(0, 3.0, (ptr[-1], 3))
    N = gen.normal(size=(ptr[-1], 3))
    N[::7, 2] = 0.0  # vertical planes: the slab does not depend on z
    N[1::5] = [0.0, 0.0, 1.0]
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return ptr, U, N, R, shape


@pytest.mark.parametrize("plane", [True, False])
@pytest.mark.parametrize("weighted", [False, True])
def test_kernel_equals_reference_on_tangled_pairs(plane, weighted, monkeypatch):
    ptr, U, N, R, shape = tangled_pairs(1)
    n_src = ptr.size - 1
    w = np.random.default_rng(2).uniform(0.1, 3.0, n_src) if weighted else np.ones(n_src, np.int32)
    ref = reference(ptr, U, N if plane else None, R, 1.3, w, shape)
    assert ref.max() >= 5  # many points overlap somewhere
    for block_bytes in (K.BLOCK_BYTES, 1):  # one block of rows, and one row per block
        monkeypatch.setattr(K, "BLOCK_BYTES", block_bytes)
        for workers in (1, 2):
            got = K.raster(ptr, U, N if plane else None, R, 1.3, w, shape, use_numba=True, workers=workers)
            assert got.shape == shape and got.dtype == (np.float64 if weighted else np.int32)
            if weighted:  # same additions in the same order: the same bits
                np.testing.assert_array_equal(got, ref)
            else:
                np.testing.assert_array_equal(got, np.rint(ref).astype(np.int32))
    numpy_route = K.raster(ptr, U, N if plane else None, R, 1.3, w, shape, use_numba=False)
    np.testing.assert_allclose(numpy_route, ref, atol=1e-9)


@pytest.mark.parametrize("metric", ["point_to_plane", "point_to_point"])
def test_cube_equals_reference_on_als(metric):
    pair = als_epochs("xyz", size=(16.0, 16.0), density=6, rng=4)
    src, tgt = pair.source.xyz[::4], pair.target.xyz
    cube = consensus_cube(src, tgt, extent=0.24, step=0.02, metric=metric, eps=0.05, center=[0.2, -0.2, 0.1])
    pb = consensus_inputs(src, tgt, metric, 0.05)
    axes, step = grid(0.24, 0.02, [0.2, -0.2, 0.1])
    a0, a1 = np.array([a[0] for a in axes]), np.array([a[-1] for a in axes])
    ptr, _, D, nrm = candidate_pairs(pb, a0, a1, pb.radius)
    ref = reference(ptr, (D - a0) / step, nrm, pb.radius / step, pb.eps / step, pb.w, cube.counts.shape)
    assert cube.counts.dtype == np.int32 and cube.best_count >= 10  # overlapping votes, not an empty cube
    np.testing.assert_array_equal(cube.counts, np.rint(ref).astype(np.int32))
