"""The voxel-grid kernels of M3C2 (labkit.change.grid): serial and parallel kernels give bitwise the same sums."""

import numpy as np
import pytest

from labkit.change import grid as g

pytestmark = pytest.mark.skipif(not g.HAVE_NUMBA, reason="numba kernels only")


@pytest.mark.slow
def test_serial_and_parallel_kernels_agree_bitwise():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, (20_000, 3)) * [1, 1, 0.3]
    cores = rng.uniform(-4, 4, (700, 3)) * [1, 1, 0.3]
    normals = rng.normal(size=(700, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    normals[5] = np.nan  # no normal: count 0
    grid = g.VoxelGrid(pts, 0.4)
    args = (grid.points, grid.keys, grid.start, grid.lo, grid.dims, grid.cell, cores)
    out = []
    for kernel in (g._cylinder_serial, g._cylinder_kernel):
        count, mean, m2 = np.zeros(700, dtype=np.int64), np.zeros(700), np.zeros(700)
        kernel(*args, normals, 0.4, 0.9, count, mean, m2)
        out.append((count, mean, m2))
    assert out[0][0].sum() > 700 * 10 and out[0][0][5] == 0
    for a, b in zip(*out):
        assert np.array_equal(a, b)
    out = []
    for kernel in (g._ball_serial, g._ball_moments_kernel):
        count, first, second = np.zeros(700, dtype=np.int64), np.zeros((700, 3)), np.zeros((700, 3, 3))
        kernel(*args, 0.6, count, first, second)
        out.append((count, first, second))
    for a, b in zip(*out):
        assert np.array_equal(a, b)
    # brute force for the ball counts
    d2 = ((cores[:50, None, :] - pts[None]) ** 2).sum(axis=2)
    assert np.array_equal(out[0][0][:50], (d2 <= 0.36).sum(axis=1))


def test_the_parallel_kernel_is_used_from_parallel_from_core_points():
    assert g._kernel(g.PARALLEL_FROM - 1, "s", "p") == "s" and g._kernel(g.PARALLEL_FROM, "s", "p") == "p"


def test_grid_sorts_every_point_into_its_voxel():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(5000, 3)) * [30, 20, 2] + [4e5, 5e6, 300]
    grid = g.VoxelGrid(pts - pts.mean(axis=0), 0.7)
    ijk = np.floor((grid.points - grid.lo) / grid.cell).astype(np.int64)
    assert np.array_equal(grid.dims, ijk.max(axis=0) + 3) and ijk.min() >= 0
    key = (ijk[:, 0] * grid.dims[1] + ijk[:, 1]) * grid.dims[2] + ijk[:, 2]
    for j in rng.choice(len(grid.keys), 50, replace=False):
        assert np.all(key[grid.start[j]:grid.start[j + 1]] == grid.keys[j])
    assert np.all(np.diff(grid.keys) > 0) and grid.start[-1] == len(pts)


@pytest.mark.parametrize("cell", [0.1, 0.3, 2.0])
def test_counting_sort_gives_the_comparison_sort_grid_bitwise(cell, monkeypatch):
    # several distinct points per voxel, duplicates and points on voxel faces (coordinates on a 0.1 lattice):
    # the counting sort must give the same keys and keep the input order within a voxel
    rng = np.random.default_rng(5)
    pts = np.round(rng.uniform(-3, 3, (4000, 3)) * [1, 1, 0.2], 1)
    pts = np.vstack([pts, pts[::7]])[rng.permutation(4000 + 572)]
    counted = g.VoxelGrid(pts, cell)
    assert len(pts) * g.COUNTING_CELLS + 2**16 >= np.prod(counted.dims)  # the counting route was taken
    monkeypatch.setattr(g, "HAVE_NUMBA", False)  # the argsort route
    sorted_ = g.VoxelGrid(pts, cell)
    for a in ("points", "keys", "start", "lo", "dims"):
        assert np.array_equal(getattr(counted, a), getattr(sorted_, a)), a
    assert counted.cell == sorted_.cell


def test_first_call_kernels_are_loaded_at_import_and_read_only_input_still_works():
    """Importing the grid loads the serial kernels (and local_origin's) for the types M3C2 passes, so a fresh
    process's first call does not wait for numba's cache; other types, e.g. read-only arrays of a file, still
    compile on demand."""
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from labkit.change import grid as g\n"
        "from labkit.core import frame\n"
        "kernels = (g._counting_sort, g._cylinder_serial, g._ball_serial, frame._sums_kernel())\n"
        "print([len(k.signatures) for k in kernels])\n"
        "pts = np.random.default_rng(0).uniform(0, 10, (2000, 3))\n"
        "pts.setflags(write=False)\n"
        "print(frame.local_origin(pts).tolist(), len(g.VoxelGrid(pts, 0.5).keys) > 0)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "[1, 1, 1, 1]"  # loaded before any call
    assert out[1] == "[5.0, 5.0, 5.0] True"  # a read-only cloud: compiled on demand, the same origin
