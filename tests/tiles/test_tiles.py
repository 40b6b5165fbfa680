"""Tiles, the shift field, the neighbour test, and the Dask paths (labkit.tiles)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labkit import tiles
from labkit.cloud import PointCloud
from labkit.core.errors import CloudFileError, LabkitError
from labkit.registration.result import RegistrationResult

ORIGIN = np.array([612_000.0, 5_701_000.0, 80.0])


def _terrain(xy):
    return 3 * np.sin(xy[:, 0] / 9.0) + 2 * np.cos(xy[:, 1] / 7.0) + 0.5 * np.sin((xy[:, 0] + xy[:, 1]) / 4.0)


def _survey(n=24_000, extent=(200.0, 100.0), seed=0, jump=0.08):
    """Two epochs of a wavy terrain; the target's right half (x >= 100 m) moved by `jump` more in X."""
    rng = np.random.default_rng(seed)
    xy_s = rng.uniform(0, 1, (n, 2)) * extent
    xy_t = rng.uniform(0, 1, (2 * n, 2)) * extent
    shift = np.array([0.05, -0.03, 0.02])
    tgt = np.c_[xy_t, _terrain(xy_t)]
    src = np.c_[xy_s, _terrain(xy_s)] - shift  # source + shift lies on the target surface
    moved = tgt[:, 0] >= 100.0
    tgt[moved, 0] += jump  # the right half slid in X (a "landslide" of the target epoch)
    cls_s = np.where(rng.uniform(size=len(src)) < 0.1, 5, 2).astype(np.uint8)
    cls_t = np.where(rng.uniform(size=len(tgt)) < 0.1, 5, 2).astype(np.uint8)
    return (PointCloud(src + ORIGIN, {"classification": cls_s}),
            PointCloud(tgt + ORIGIN, {"classification": cls_t}), shift)


def plane_translation(source, target):
    """A small independent point-to-plane translation estimator (Gauss-Newton, 5 iterations)."""
    s = np.asarray(getattr(source, "xyz", source))
    q = np.asarray(getattr(target, "xyz", target))
    o = q.mean(axis=0).round()
    s, q = s - o, q - o
    tree = cKDTree(q)
    _, nb = tree.query(q, k=10)
    nbp = q[nb] - q[nb].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", nbp, nbp))[1][:, :, 0]
    t = np.zeros(3)
    for _ in range(5):
        _, j = tree.query(s + t, k=1)
        A = normals[j]
        w = np.einsum("ij,ij->i", A, s + t - q[j])
        N = A.T @ A
        t = t - np.linalg.solve(N, A.T @ w)
    _, j = tree.query(s + t, k=1)
    v = np.einsum("ij,ij->i", normals[j], s + t - q[j])
    s0 = np.sqrt(v @ v / (len(v) - 3))
    cov = s0**2 * np.linalg.solve(N, np.eye(3))
    return RegistrationResult(t, np.eye(3), o, cov, ("tx", "ty", "tz"), s0, len(s), 1.0, True, 5, method="plane")


def test_tile_grid_anchors_and_partitions():
    grid = tiles.tile_grid((612_030.0, 5_701_010.0, 612_250.0, 5_701_090.0), 100.0)
    assert len(grid) == 3 and grid[0].bounds == (612_000.0, 5_701_000.0, 612_100.0, 5_701_100.0)
    xyz = np.random.default_rng(1).uniform([612_030, 5_701_010, 0], [612_250, 5_701_090, 1], (5000, 3))
    xyz[:3, 0] = [612_100.0, 612_200.0, 612_030.0]  # points on tile borders
    counts = sum(t.contains(xyz).astype(int) for t in grid)
    assert (counts == 1).all()
    buffered = tiles.tile_grid((0, 0, 250, 90), 100.0, buffer=5.0)
    assert buffered[1].read_bounds == (95.0, -5.0, 205.0, 105.0)
    with pytest.raises(LabkitError, match="size"):
        tiles.tile_grid((0, 0, 1, 1), 0)
    with pytest.raises(LabkitError, match="min <= max"):
        tiles.tile_grid((0, 0, -1, 1), 10)


def test_shift_field_recovers_shifts_and_finds_the_moved_half():
    src, tgt, shift = _survey()
    field = tiles.register_tiles(src, tgt, plane_translation, size=50.0, scheduler="serial", progress=False)
    assert len(field) == 8 and field.ok.all()
    left = field.centres[:, 0] < ORIGIN[0] + 100
    np.testing.assert_allclose(field.translations[left], np.tile(shift, (left.sum(), 1)), atol=0.01)
    np.testing.assert_allclose(field.translations[~left], np.tile(shift + [0.08, 0, 0], ((~left).sum(), 1)), atol=0.01)
    test = field.neighbour_test(alpha=0.01, extra_std=0.005)
    cross = left[test.pairs[:, 0]] != left[test.pairs[:, 1]]
    assert not test.agree[cross].any() and test.agree[~cross].all()
    assert test.n_areas == 2 and len(set(test.areas[left])) == 1 and len(set(test.areas[~left])) == 1
    assert "coherent areas" in test.summary() and "8 ok" in field.summary()


def test_neighbour_test_closed_form():
    grid = tiles.tile_grid((0, 0, 299, 99), 100.0)  # 1 x 3 tiles
    t = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.5, 0, 0]])
    C = np.array([np.eye(3) * 1e-4, np.diag([4e-4, 1e-4, 1e-4]), np.eye(3) * 1e-4])
    det = [np.ones(3, bool), np.array([True, False, True]), np.ones(3, bool)]
    shifts = tuple(tiles.TileShift(g, ti, Ci, d, 1000, 1000, 900, 0.01, True, 0.1, "ok")
                   for g, ti, Ci, d in zip(grid, t, C, det))
    test = tiles.ShiftField(shifts, 100.0).neighbour_test(alpha=0.05)
    np.testing.assert_array_equal(test.pairs, [[0, 1], [1, 2]])
    # pair (0, 1): only X and Z enter (Y undetermined in tile 1); chi2 = 0.01^2 / 5e-4
    assert test.dof.tolist() == [2, 2]
    assert test.chi2[0] == pytest.approx(0.01**2 / 5e-4, rel=1e-12)
    assert test.chi2[1] == pytest.approx(0.49**2 / 5e-4, rel=1e-12)
    assert test.agree.tolist() == [True, False] and test.areas.tolist() == [0, 0, 1]
    widened = tiles.neighbour_test(tiles.ShiftField(shifts, 100.0), extra_std=0.5)
    assert widened.agree.all() and widened.n_areas == 1


def test_dask_local_and_distributed_equal_serial():
    distributed = pytest.importorskip("distributed")
    src, tgt, _ = _survey(n=8000, extent=(100.0, 100.0), seed=3)
    kw = dict(size=50.0, min_points=100)
    serial = tiles.register_tiles(src, tgt, plane_translation, scheduler="serial", progress=False, **kw)
    threads = tiles.register_tiles(src, tgt, plane_translation, scheduler="threads", progress=True, **kw)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        dist = tiles.register_tiles(src, tgt, plane_translation, client=client, progress=True, **kw)
    for other in (threads, dist):
        assert [s.tile.bounds for s in other.tiles] == [s.tile.bounds for s in serial.tiles]
        np.testing.assert_array_equal(other.translations, serial.translations)
        np.testing.assert_array_equal(other.covariances, serial.covariances)


def test_tiles_read_lazily_from_las_files(tmp_path):
    io = pytest.importorskip("labkit.io")
    src, tgt, _ = _survey(n=6000, extent=(100.0, 100.0), seed=4)
    # the source in two files split at x = 30 m (not on the tile grid), the target in one file
    left = src.xyz[:, 0] < ORIGIN[0] + 30
    paths = [io.write_cloud(src.subset(left), tmp_path / "s1.laz"), io.write_cloud(src.subset(~left), tmp_path / "s2.las")]
    tpath = io.write_cloud(tgt, tmp_path / "t.laz")
    from_files = tiles.register_tiles(paths, tpath, plane_translation, size=50.0, scheduler="sync", progress=False)
    # the same points, read whole, in memory
    parts = [io.read_cloud(p) for p in paths]
    s_mem = PointCloud(np.vstack([c.xyz for c in parts]),
                       {"classification": np.concatenate([c["classification"] for c in parts])})
    t_mem = io.read_cloud(tpath)
    in_memory = tiles.register_tiles(s_mem, t_mem, plane_translation, size=50.0, scheduler="serial", progress=False)
    assert [s.n_source for s in from_files.tiles] == [s.n_source for s in in_memory.tiles]
    np.testing.assert_allclose(from_files.translations, in_memory.translations, atol=1e-12)
    # classes filter while reading: only ground (2) of the source
    ground = tiles.register_tiles(paths, tpath, plane_translation, size=50.0, classes=[2], scheduler="serial",
                                  progress=False, min_points=10)
    ground_mem = tiles.register_tiles(s_mem, t_mem, plane_translation, size=50.0, classes=[2], scheduler="serial",
                                      progress=False, min_points=10)
    assert [s.n_source for s in ground.tiles] == [s.n_source for s in ground_mem.tiles]
    assert sum(s.n_source for s in ground.tiles) < 0.95 * sum(s.n_source for s in from_files.tiles)


def test_bad_input_and_reported_failures(tmp_path):
    src, tgt, _ = _survey(n=4000, extent=(100.0, 100.0), seed=5)
    with pytest.raises(CloudFileError, match="not found"):
        tiles.register_tiles(tmp_path / "missing.laz", tgt, plane_translation)
    with pytest.raises(LabkitError, match="do not overlap"):
        tiles.register_tiles(src, tgt.with_xyz(tgt.xyz + [1000, 0, 0]), plane_translation)
    with pytest.raises(LabkitError, match="scheduler"):
        tiles.register_tiles(src, tgt, plane_translation, scheduler="gpu")

    def broken(s, t):
        raise LabkitError("degenerate tile")

    failed = tiles.register_tiles(src, tgt, broken, size=50.0, scheduler="serial", progress=False)
    assert [s.status for s in failed.tiles] == ["failed"] * 4 and "degenerate tile" in failed.tiles[0].message
    sparse = tiles.register_tiles(src, tgt, plane_translation, size=50.0, min_points=5000, scheduler="serial",
                                  progress=False)
    assert all(s.status == "too few points" for s in sparse.tiles) and np.isnan(sparse.translations).all()
    assert sparse.neighbour_test().n_areas == 0
    # the CSV: one line per tile; a failed write leaves nothing behind
    path = failed.to_csv(tmp_path / "field.csv")
    assert len(path.read_text().splitlines()) == 5
    with pytest.raises(LabkitError, match="does not exist"):
        failed.to_csv(tmp_path / "no" / "field.csv")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.csv"]


def test_write_tiles_partitions_the_cloud(tmp_path):
    io = pytest.importorskip("labkit.io")
    src, _, _ = _survey(n=3000, extent=(120.0, 70.0), seed=6)
    paths = tiles.write_tiles(src, tmp_path, 50.0, prefix="als2016")
    # 120 m x 70 m from a round corner: 3 x 2 tiles, named after their south-west corners
    assert [p.name for p in paths][:2] == ["als2016_612000_5701000.laz", "als2016_612050_5701000.laz"]
    assert len(paths) == 6
    back = [io.read_cloud(p) for p in paths]
    assert sum(len(c) for c in back) == len(src)
    xyz = np.vstack([c.xyz for c in back])
    d, _ = cKDTree(src.xyz).query(xyz)
    assert d.max() <= 0.001  # the 1 mm LAS scale
    for p, c in zip(paths, back):  # every file holds only its own tile
        x0, y0 = map(float, p.stem.split("_")[1:])
        assert (c.xyz[:, 0] >= x0 - 1e-3).all() and (c.xyz[:, 0] < x0 + 50).all()
        assert (c.xyz[:, 1] >= y0 - 1e-3).all() and (c.xyz[:, 1] < y0 + 50).all()
    with pytest.raises(LabkitError, match="does not exist"):
        tiles.write_tiles(src, tmp_path / "missing", 50.0)
    with pytest.raises(LabkitError, match="suffix"):
        tiles.write_tiles(src, tmp_path, 50.0, suffix=".csv")


def test_files_in_two_reference_systems_are_refused_before_any_tile_runs(tmp_path, monkeypatch):
    """A tile would join its files (regions.merge refuses mixed CRS): the headers are compared first."""
    import labkit.tiles.register as R

    src, tgt, _ = _survey(n=6000, extent=(100.0, 50.0), seed=7)
    (tmp_path / "s").mkdir(), (tmp_path / "t").mkdir()
    left = src.xyz[:, 0] < ORIGIN[0] + 50
    tiles.write_tiles(PointCloud(src.xyz[left], crs="EPSG:25832"), tmp_path / "s", 50.0, prefix="a")
    tiles.write_tiles(PointCloud(src.xyz[~left], crs="EPSG:25833"), tmp_path / "s", 50.0, prefix="b")
    tiles.write_tiles(PointCloud(tgt.xyz, crs="EPSG:25832"), tmp_path / "t", 50.0)
    monkeypatch.setattr(R, "register_tile", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(CloudFileError, match=r"source files are in different reference systems: \['EPSG:25832'"):
        tiles.register_tiles(tmp_path / "s", tmp_path / "t", plane_translation, size=50.0, scheduler="serial")
    monkeypatch.undo()
    same = tiles.register_tiles(tmp_path / "t", tmp_path / "t", plane_translation, size=50.0, scheduler="serial")
    assert [s.status for s in same.tiles] == ["ok", "ok"]  # one CRS: runs


def test_undetermined_components_stay_out_of_statistics_and_arrows():
    import matplotlib

    matplotlib.use("Agg")
    from labkit.plotting.compare import plot_shift_field

    def shift(col, t, det):
        tile = tiles.Tile(0, col, (100.0 * col, 0.0, 100.0 * (col + 1), 100.0))
        return tiles.TileShift(tile, np.array(t), np.eye(3) * 1e-6, np.array(det), 900, 900, 800, 1.0, True,
                               0.1, "ok")

    # the field tile (col 1) holds X and Y at 0: they must not pull the median or the spread
    field = tiles.ShiftField((shift(0, [0.10, 0.20, 0.05], [True] * 3), shift(1, [0.0, 0.0, 0.06], [False, False, True]),
                              shift(2, [0.12, 0.22, 0.07], [True] * 3)), 100.0, "test")
    assert np.isnan(field.determined_translations[1, :2]).all()
    text = field.summary()
    assert "[+0.1100, +0.2100, +0.0600] m" in text  # medians of the determined values only
    assert "undetermined            1 tiles (not determined: X in 1, Y in 1, Z in 0" in text
    assert field.status.tolist() == ["ok", "undetermined", "ok"]  # the verdict follows the determined axes
    ax = plot_shift_field(field)
    q = next(c for c in ax.collections if hasattr(c, "U"))  # arrows only where X or Y is determined
    assert np.allclose(q.U, [0.10, 0.12]) and np.allclose(q.V, [0.20, 0.22])
    assert any("XY undet." in t.get_text() for t in ax.texts)


@pytest.mark.slow
def test_distributed_worker_processes_equal_serial():
    """Worker processes (not threads): the tile jobs and labkit's ICP method travel by pickle and give
    exactly the serial numbers."""
    distributed = pytest.importorskip("distributed")
    from labkit.registration import compare
    from labkit.synthetic import als_epochs

    pair = als_epochs("xyz", size=(80.0, 40.0), density=3.0, rng=5)
    method = compare.standard_methods(["icp"])["icp"]
    kw = dict(size=40.0, min_points=100)
    serial = tiles.register_tiles(pair.source, pair.target, method, scheduler="serial", progress=False, **kw)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        dist = tiles.register_tiles(pair.source, pair.target, method, client=client, progress=False, **kw)
    assert len(serial) == 2 and serial.ok.all()
    np.testing.assert_array_equal(dist.translations, serial.translations)
    np.testing.assert_array_equal(dist.covariances, serial.covariances)


@pytest.mark.parametrize("buffer", [0.0, 2.5, 7.0])
def test_binned_cut_equals_masking_every_tile(buffer):
    """The cells-first cut gives every tile exactly the points Tile.contains selects (edges included)."""
    from labkit.tiles.survey import _cut_all, _for_tile

    rng = np.random.default_rng(8)
    xyz = np.r_[rng.uniform(-3, 33, (3000, 3)), np.round(rng.uniform(0, 30, (500, 3)))]  # many on tile edges
    xyz = np.r_[xyz, [[1e7, -1e7, 0.0]]]  # one point far outside the grid
    cloud = PointCloud(xyz, {"i": np.arange(len(xyz))})
    grid = tiles.tile_grid((0, 0, 30, 30), 5.0, buffer=buffer)
    for data in (xyz, cloud):
        for t, got in zip(grid, _cut_all(data, grid)):
            want = _for_tile(data, t)
            np.testing.assert_array_equal(getattr(got, "xyz", got), getattr(want, "xyz", want))
    sizes = [len(c) for c in _cut_all(cloud, grid)]
    if buffer == 0:  # no buffer: the tiles partition the points inside the grid
        inside = ((xyz[:, :2] >= 0) & (xyz[:, :2] < 35)).all(axis=1)
        assert sum(sizes) == inside.sum()


# --------------------------------------------------------------------------- campaigns: folders, resume, schedulers
class _Counting:
    """plane_translation that counts its calls (the tiles actually computed)."""

    def __init__(self):
        self.calls = 0

    def __call__(self, source, target):
        self.calls += 1
        return plane_translation(source, target)


def test_results_folder_resumes_without_recomputing(tmp_path):
    src, tgt, _ = _survey(n=12_000)
    method = _Counting()
    first = tiles.register_tiles(src, tgt, method, size=50.0, scheduler="threads", results=tmp_path / "r")
    files = sorted((tmp_path / "r").glob("tile_*.json"))
    assert method.calls == len(first) == len(files) == 8 and first.n_reused == 0
    stamps = {p.name: p.stat().st_mtime_ns for p in files}
    again = tiles.register_tiles(src, tgt, method, size=50.0, scheduler="threads", results=tmp_path / "r")
    assert method.calls == 8 and again.n_reused == 8  # a rerun computes nothing new ...
    assert {p.name: p.stat().st_mtime_ns for p in files} == stamps  # ... and writes nothing
    np.testing.assert_array_equal(again.translations, first.translations)
    np.testing.assert_array_equal(again.covariances, first.covariances)
    assert [t.tile.bounds for t in again.tiles] == [t.tile.bounds for t in first.tiles]
    # a killed run: two tiles never written, one cut short; exactly those three are computed
    files[0].unlink(), files[3].unlink(), files[5].write_text('{"tile": ')
    resumed = tiles.register_tiles(src, tgt, method, size=50.0, scheduler="serial", results=tmp_path / "r")
    assert method.calls == 11 and resumed.n_reused == 5
    np.testing.assert_allclose(resumed.translations, first.translations, rtol=0, atol=1e-12)
    # other options or other input: nothing is reused
    tiles.register_tiles(src, tgt, method, size=50.0, min_points=300, scheduler="serial", results=tmp_path / "r")
    assert method.calls == 19
    moved = PointCloud(src.xyz + [0.01, 0, 0], src.attributes)
    tiles.register_tiles(moved, tgt, method, size=50.0, min_points=300, scheduler="serial", results=tmp_path / "r")
    assert method.calls == 27


def test_progress_counts_tiles_on_every_scheduler():
    src, tgt, _ = _survey(n=6000)
    for scheduler in ("serial", "threads", "sync"):
        events = []
        field = tiles.register_tiles(src, tgt, plane_translation, size=50.0, scheduler=scheduler,
                                     progress=events.append)
        steps = [e for e in events if not e.finished]
        assert len(steps) == len(field) == 8 and events[-1].done == events[-1].total == 8, scheduler
        assert all(e.desc == "tiles" for e in events)


def test_folders_and_globs_of_tiles_read_only_what_a_tile_needs(tmp_path):
    io = pytest.importorskip("labkit.io")
    src, tgt, _ = _survey(n=8000, seed=5)
    (tmp_path / "s").mkdir(), (tmp_path / "t").mkdir()
    s_paths = tiles.write_tiles(src, tmp_path / "s", 50.0)
    tiles.write_tiles(tgt, tmp_path / "t", 50.0, prefix="ref")
    by_folder = tiles.register_tiles(tmp_path / "s", str(tmp_path / "t" / "ref_*.laz"), plane_translation,
                                     size=50.0, buffer=5.0, scheduler="serial")
    listed = tiles.register_tiles(s_paths, sorted((tmp_path / "t").iterdir()), plane_translation,
                                  size=50.0, buffer=5.0, scheduler="serial")
    np.testing.assert_array_equal(by_folder.translations, listed.translations)
    # a tile task receives only the files whose header meets its buffered box
    survey = tiles.survey._survey(str(tmp_path / "s"))
    tile = tiles.tile_grid(survey.bounds(), 50.0, buffer=5.0)[0]
    near = survey.for_tile(tile)
    want = io.files_in_box(str(tmp_path / "s"), tile.read_bounds)
    assert sorted(near.paths) == sorted(str(p) for p in want) and 1 <= len(near.paths) < len(s_paths)
    with pytest.raises(CloudFileError, match="no point-cloud file"):
        tiles.register_tiles(str(tmp_path / "nothing_*.laz"), tmp_path / "t", plane_translation)


@pytest.mark.parametrize("text, ok", [
    ("threads", True), ("cluster", True), ("serial", True), ("tcp://127.0.0.1:8786", True),
    ("tcp://scheduler.lab.local:8786", True), ("tls://[::1]:9000", True),
    ("tcp://127.0.0.1", False), ("tcp://host:99999", False), ("127.0.0.1:8786", False), ("gpu", False),
    ("http://host:8786", False), ("", False), (None, False),
])
def test_scheduler_names_and_addresses(text, ok):
    if ok:
        assert tiles.check_scheduler(text) == text
    else:
        with pytest.raises(LabkitError, match="scheduler"):
            tiles.check_scheduler(text)


@pytest.mark.slow
def test_unreachable_scheduler_is_a_clear_error():
    pytest.importorskip("distributed")
    src, tgt, _ = _survey(n=3000)
    with pytest.raises(LabkitError, match="cannot reach the Dask scheduler at tcp://127.0.0.1:9"):
        tiles.register_tiles(src, tgt, plane_translation, size=50.0, scheduler="tcp://127.0.0.1:9")


class _Marked:
    """plane_translation that leaves a file per call in ``folder`` (counts calls across worker threads and
    processes, where an in-memory counter would be a copy)."""

    def __init__(self, folder, crash_after=None):
        self.folder, self.crash_after = str(folder), crash_after

    def __call__(self, source, target):
        import time
        import uuid
        from pathlib import Path

        if self.crash_after is not None and len(list(Path(self.folder).iterdir())) >= self.crash_after:
            raise RuntimeError("worker lost")  # not a labkit error: the run stops
        result = plane_translation(source, target)
        time.sleep(0.2)  # a tile takes a moment, so that the interrupt meets tiles still queued
        (Path(self.folder) / uuid.uuid4().hex).touch()
        return result


def _calls(folder) -> int:
    return len(list(folder.iterdir()))


def _settled(calls, results, quiet: float = 1.0, timeout: float = 60.0) -> int:
    """Wait until every finished call has its JSON and none has finished for ``quiet`` s (tasks that were
    running when the run stopped complete and are written)."""
    import time

    t_end, last, since = time.monotonic() + timeout, -1, time.monotonic()
    while time.monotonic() < t_end:
        n = _calls(calls)
        if n != last:
            last, since = n, time.monotonic()
        elif time.monotonic() - since >= quiet and len(list(results.glob("tile_*.json"))) == n:
            break
        time.sleep(0.1)
    return last


@pytest.mark.parametrize("how", ["ctrl-c", "crash"])
def test_interrupted_run_on_a_cluster_by_address_resumes(tmp_path, how):
    """A run on a LocalCluster named by its tcp:// address stops after three tiles - Ctrl-C in the client
    (raised from the progress callback) or an error in a worker; the rerun computes only the tiles without
    a result file and gives the field of an uninterrupted run."""
    distributed = pytest.importorskip("distributed")
    src, tgt, _ = _survey(n=12_000)
    kw = dict(size=50.0, min_points=100)
    reference = tiles.register_tiles(src, tgt, plane_translation, scheduler="serial", **kw)
    calls, results = tmp_path / "calls", tmp_path / "results"
    calls.mkdir()
    method = _Marked(calls)
    stop, error = (_Marked(calls, crash_after=3), RuntimeError) if how == "crash" else (method, KeyboardInterrupt)

    def interrupt(event):
        if event.done >= 3 and not event.finished:
            raise KeyboardInterrupt

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tcp://")
        with pytest.raises(error):
            tiles.register_tiles(src, tgt, stop, scheduler=address, progress=interrupt if how == "ctrl-c" else None,
                                 results=results, **kw)
        first = _settled(calls, results)  # tiles still running when the run stopped finish and are written
        saved = len(list(results.glob("tile_*.json")))
        assert 3 <= saved == first < len(reference)
        resumed = tiles.register_tiles(src, tgt, method, scheduler=address, results=results, **kw)
    assert _calls(calls) - first == len(reference) - saved  # only the missing tiles were computed
    assert resumed.n_reused == saved and resumed.ok.all()
    np.testing.assert_array_equal(resumed.translations, reference.translations)
    np.testing.assert_array_equal(resumed.covariances, reference.covariances)
    assert [t.tile.bounds for t in resumed.tiles] == [t.tile.bounds for t in reference.tiles]


# --------------------------------------------------------------------------- real data: the tile verdicts
def _check_tile_rows(path):
    """Every row of a shift_field.csv: 'ok' only when converged with dX, dY, dZ and their std; an axis not in
    'determined' and every axis of a tile that is not ok/undetermined is an empty cell; returns the rows."""
    import csv

    rows = list(csv.DictReader(open(path, newline="")))
    for r in rows:
        cells = [r[c] for c in ("dx", "dy", "dz", "sx", "sy", "sz")]
        if r["status"] == "ok":
            assert r["converged"] == "True" and r["determined"] == "XYZ"
            assert all(np.isfinite(float(v)) for v in cells), r
        for a, axis in zip("xyz", "XYZ"):
            shown = r["status"] in ("ok", "undetermined") and axis in r["determined"]
            assert (r[f"d{a}"] != "") == shown and (r[f"s{a}"] != "") == shown, r
        if r["converged"] != "True":
            assert r["status"] != "ok" and r["determined"] == "" and not any(cells), r
    return rows


def test_real_autzen_tiles_ok_only_when_converged_and_determined(realdata, tmp_path, capsys):
    """The two real Autzen epochs (sparse ALS ground, 13 years apart) in 15 m tiles: no tile is ok unless it converged
    and determines dX, dY and dZ; undetermined components and tiles stopped by --max-iterations print no number."""
    from labkit.cli.main import main

    e = realdata / "epochs"
    argv = [str(e / "autzen-bmx-2023.las"), "--target", str(e / "autzen-bmx-2010.las"), "--size", "15",
            "--min-points", "50", "--scheduler", "serial", "--quiet"]
    assert main(["tiles", *argv, "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    rows = _check_tile_rows(tmp_path / "a" / "shift_field.csv")
    registered = [r for r in rows if r["status"] in ("ok", "undetermined", "not converged")]
    undetermined = [r for r in rows if r["status"] == "undetermined"]
    assert len(registered) >= 4 and undetermined  # sparse tiles: some component the data do not determine
    assert any(r["determined"] == "" for r in undetermined) or any(r["dx"] == "" for r in undetermined)
    assert "undetermined" in out and "not determined" in out
    # the same tiles stopped after one iteration: all 'not converged', no shift, no area
    assert main(["tiles", *argv, "--max-iterations", "1", "--out", str(tmp_path / "b")]) == 0
    rows = _check_tile_rows(tmp_path / "b" / "shift_field.csv")
    assert sum(r["status"] == "not converged" for r in rows) == len(registered)
    assert all(r["area"] == "-1" for r in rows) and "not converged" in capsys.readouterr().out


def test_real_autzen_tiles_with_the_widened_gate_keep_the_verdicts(realdata, tmp_path, capsys):
    """consensus+icp (ICP's gate widened to twice the point spacing of sparse tiles) on the Autzen epochs in 15 and
    30 m tiles: every tile with a registration is 'undetermined' (50-190 ground points, X and Y not determined;
    measured: 5 of 5 and 3 of 3), its undetermined components empty in the CSV, none 'ok'."""
    from labkit.cli.main import main

    e = realdata / "epochs"
    if not (e / "autzen-bmx-2010.las").is_file():
        pytest.skip("Autzen epochs absent")
    for size in ("15", "30"):
        out = tmp_path / size
        assert main(["tiles", str(e / "autzen-bmx-2023.las"), "--target", str(e / "autzen-bmx-2010.las"), "--size",
                     size, "--min-points", "50", "--scheduler", "serial", "--method", "consensus+icp", "--quiet",
                     "--out", str(out)]) == 0
        rows = _check_tile_rows(out / "shift_field.csv")
        registered = [r for r in rows if r["status"] != "too few points"]
        assert registered and all(r["status"] == "undetermined" and "X" not in r["determined"] for r in registered)
    assert "undetermined" in capsys.readouterr().out


@pytest.mark.slow
def test_sparse_synthetic_tiles_with_the_widened_gate_are_honest(tmp_path):
    """A synthetic ALS survey at 0.1 pts/m^2 (about 2 m between points: no pair within ICP's 1 m gate, so consensus+icp
    widens it) in 50 m tiles: no tile is 'ok' with X, Y it cannot determine, the CSV leaves them empty, and every
    stated component lies within 3 std of the truth (measured: 9 of 9 tiles undetermined in X, Y; Z within 1.2 std)."""
    from labkit import regions
    from labkit.synthetic import als_epochs

    pair = als_epochs("xyz", size=(150.0, 150.0), density=0.1, shift=(0.23, -0.17, 0.11), rng=14)
    source = regions.crop_box(pair.source, (*pair.origin[:2], *(pair.origin[:2] + 150.0)))
    field = tiles.register_tiles(source, pair.target, "consensus+icp", size=50.0, scheduler="serial", min_points=50)
    rows = _check_tile_rows(field.to_csv(tmp_path / "f.csv", field.neighbour_test(0.05)))
    assert len(rows) == 9 and not any(r["status"] == "ok" for r in rows)
    truth = pair.truth[:3, 3]
    for s in field.tiles:
        if s.converged:
            std = np.sqrt(np.diag(s.covariance))
            stated = np.isfinite(std) & (std < 0.1)
            assert np.all(np.abs(s.translation - truth)[stated] <= 3 * std[stated]), (s.translation - truth, std)


@pytest.mark.slow
def test_sparse_synthetic_tiles_where_icp_walks_from_its_start_state_it():
    """A synthetic ALS survey at 0.5 pts/m^2 (about 1.4 m between points: pairs within ICP's 1 m gate) in 50 m tiles
    through consensus+icp: ICP walks away from a right consensus start on some tiles (up to 116 mm in X, 59 mm
    in Y), so the covariance must cover the disagreement. ICP's own std covers the walks now (the t factor of
    the few cells that fix X and Y: 77 mm in Y where it walked 59 mm; the residuals alone once said 9 mm and
    the start's disagreement had to add d d^T), and the agreement test scales it on the tiles where the two
    still differ by more than their stds say. Every stated component within 3 std of the truth (measured:
    largest 2.1 std; 6.6 and 3.2 std before either), every tile still 'ok', and the tiles whose ICP agrees with
    its start keep ICP's std."""
    from labkit import regions
    from labkit.synthetic import als_epochs

    pair = als_epochs("xyz", size=(200.0, 200.0), density=0.5, shift=(0.23, -0.17, 0.11), rng=14)
    source = regions.crop_box(pair.source, (*pair.origin[:2], *(pair.origin[:2] + 200.0)))
    field = tiles.register_tiles(source, pair.target, "consensus+icp", size=50.0, scheduler="serial", min_points=50)
    assert len(field) == 16 and field.ok.all()
    z = np.abs(field.translations - pair.truth[:3, 3]) / np.sqrt([np.diag(s.covariance) for s in field.tiles])
    assert np.all(z <= 3), z.round(1)
    scaled = ["covariance x" in s.message for s in field.tiles]
    assert 2 <= sum(scaled) < 16, [s.message for s in field.tiles]


@pytest.mark.slow
def test_real_als_halves_tiles_flag_a_moved_tile_and_keep_verdicts(realdata, tmp_path):
    """Real ALS (IGN, mostly flat ground): random halves as two epochs with a known shift, 100 m tiles. Tiles
    that are ok recover the shift; a tile whose shift is raised by 15 cm is flagged as disagreeing with its
    neighbours (CSV column 'flag'), its neighbours are not."""
    import dataclasses

    from labkit.io import read_cloud

    cloud = read_cloud(realdata / "als" / "las_with_several_extra_byte_bloc.laz")
    keep = np.random.default_rng(3).uniform(size=len(cloud)) < 0.25  # a quarter: 4 pts/m^2 per epoch
    half = np.random.default_rng(4).uniform(size=len(cloud)) < 0.5
    shift = np.array([0.25, -0.15, 0.05])
    source = cloud.subset(keep & half)
    source = source.with_xyz(source.xyz - shift)
    field = tiles.register_tiles(source, cloud.subset(keep & ~half), "icp", size=100.0, scheduler="threads")
    ok = field.ok
    assert ok.sum() >= 6 and all(s.converged for s in field.tiles if s.ok)
    assert np.abs(field.translations[ok] - shift).max() < 0.1
    test = field.neighbour_test(0.05, extra_std=0.02)
    k = int(np.flatnonzero(ok & (test.neighbours_tested >= 3))[0])
    moved = tiles.ShiftField(tuple(dataclasses.replace(s, translation=s.translation + [0, 0, 0.15]) if n == k else s
                                   for n, s in enumerate(field.tiles)), field.size, field.method)
    test = moved.neighbour_test(0.05, extra_std=0.02)
    assert np.flatnonzero(test.disagreeing).tolist() == [k]
    assert test.neighbours_disagree[k] == test.neighbours_tested[k] >= 3
    rows = _check_tile_rows(moved.to_csv(tmp_path / "f.csv", test))
    assert [n for n, r in enumerate(rows) if r["flag"]] == [k] and "disagreeing" in test.summary()


def test_not_converged_tile_is_not_ok_and_has_no_shift():
    """A hand-made tile that did not converge (e.g. a result read back from an older run marked 'ok')."""
    import dataclasses

    tile = tiles.Tile(0, 0, (0.0, 0.0, 100.0, 100.0))
    s = tiles.TileShift(tile, np.array([3.9, 0.1, 0.0]), np.eye(3) * 0.02, np.ones(3, bool), 900, 900, 800, 1.0,
                        False, 0.1, "ok")
    field = tiles.ShiftField((s,), 100.0)
    assert not s.ok and not s.usable and s.verdict == "not converged" and field.status.tolist() == ["not converged"]
    assert np.isnan(field.determined_translations).all()
    held = dataclasses.replace(s, converged=True, covariance=np.diag([np.inf, 1e-4, 1e-4]))
    assert held.verdict == "undetermined" and held.determined.tolist() == [False, True, True]


def test_tiles_from_files_in_feet_cut_the_same_points_as_in_memory(realdata, tmp_path):
    """A real ALS file in US survey feet (4_6_crop.las): the tile grid is laid out in metres, like the points that
    read_cloud returns, so the tiles read from the files hold exactly the points of the tiles cut in memory."""
    from labkit.io import read_cloud, write_cloud

    path = realdata / "als" / "4_6_crop.las"
    cloud = read_cloud(path)  # metres
    half = np.random.default_rng(5).uniform(size=len(cloud)) < 0.5
    whole = read_cloud(path, units="native")
    a = write_cloud(whole.subset(half), tmp_path / "a.las")  # still in feet, with the file's CRS
    b = write_cloud(whole.subset(~half), tmp_path / "b.las")
    from_files = tiles.register_tiles(a, b, plane_translation, size=30.0, scheduler="serial", progress=False)
    in_memory = tiles.register_tiles(cloud.subset(half), cloud.subset(~half), plane_translation, size=30.0,
                                     scheduler="serial", progress=False)
    n_files = [s.n_source for s in from_files.tiles]
    assert sum(n_files) > 0.9 * half.sum()
    assert n_files == [s.n_source for s in in_memory.tiles]


@pytest.mark.parametrize("buffer", [0.0, 5.0])
def test_cached_whole_files_give_each_tile_the_points_of_a_box_filtered_read(tmp_path, buffer):
    io = pytest.importorskip("labkit.io")
    from labkit.core.errors import EmptyRegionError
    from labkit.tiles.survey import _FileCache, _survey as survey_of

    src, _, _ = _survey(n=6000, seed=7)
    on_lines = src.xyz.copy()
    on_lines[::50, 0] = ORIGIN[0] + 50.0 * np.round((on_lines[::50, 0] - ORIGIN[0]) / 50.0)  # exactly on a grid line
    on_lines[::70, 1] = ORIGIN[1] + 50.0
    (tmp_path / "s").mkdir()
    tiles.write_tiles(PointCloud(on_lines, dict(src.attributes)), tmp_path / "s", 50.0)
    files = survey_of(str(tmp_path / "s"))
    for tile in tiles.tile_grid(files.bounds(), 50.0, buffer=buffer):
        near = files.for_tile(tile)
        parts = []
        for p in near.paths:  # the read without a cache: a closed box filter while reading
            try:
                parts.append(io.read_cloud(p, bbox=tile.read_bounds))
            except EmptyRegionError:
                pass
        want = [c.subset(tile.contains(c.xyz)) for c in parts]
        want = np.vstack([c.xyz for c in want]) if want else np.zeros((0, 3))
        got = near.load(tile)
        np.testing.assert_array_equal(np.asarray(getattr(got, "xyz", got)).reshape(-1, 3), want)
        if len(want):
            classes = np.concatenate([c["classification"][tile.contains(c.xyz)] for c in parts])
            np.testing.assert_array_equal(got["classification"], classes)
    # a file written again is read again (the cache key holds its size and time); the budget evicts old files
    cache = _FileCache(budget=1)
    path = str(sorted((tmp_path / "s").iterdir())[0])
    first = cache.get(path, None)
    assert cache.get(path, None) is first
    io.write_cloud(first.subset(np.arange(len(first)) % 2 == 0), path)
    assert len(cache.get(path, None)) == (len(first) + 1) // 2 and len(cache._items) == 1
