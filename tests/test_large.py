"""Reading and writing large clouds: parallel LAZ, one array, chunked writes, header-first file selection."""

import tracemalloc

import laspy
import numpy as np
import pytest

from labkit.cloud import PointCloud
from labkit.core.errors import CloudFileError, EmptyRegionError, LabkitError
from labkit.io import cloud_files, files_in_box, read_cloud, read_clouds, write_cloud

ORIGIN = np.array([600_000.0, 5_400_000.0, 300.0])


def _terrain(n, rng, x0=0.0, y0=0.0, side=200.0, fmt6=False):
    """An ALS-like patch with UTM-sized coordinates and the usual attributes."""
    rng = np.random.default_rng(rng)
    x, y = rng.uniform(x0, x0 + side, n), rng.uniform(y0, y0 + side, n)
    z = 2.0 * np.sin(x / 37.0) + 0.01 * y + rng.normal(0, 0.02, n)
    attrs = {
        "classification": rng.choice([2, 5, 6] + ([40] if fmt6 else []), n).astype(np.uint8),
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "gps_time": rng.uniform(0, 1e5, n),
        "return_number": np.ones(n, np.uint8),
        "number_of_returns": np.ones(n, np.uint8),
    }
    return PointCloud(np.column_stack([x, y, z]) + ORIGIN, attrs, crs="EPSG:25832", name="patch")


def _laspy_xyz(path):
    las = laspy.read(str(path))
    return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]), las


@pytest.fixture(scope="module")
def laz(tmp_path_factory):
    folder = tmp_path_factory.mktemp("large")
    return write_cloud(_terrain(120_000, 1, fmt6=True), folder / "a.laz", chunk_size=25_000)


@pytest.mark.parametrize("parallel", [True, False])
def test_parallel_and_serial_laz_equal_laspy(laz, parallel):
    cloud = read_cloud(laz, chunk_size=20_000, parallel=parallel)
    xyz, las = _laspy_xyz(laz)
    np.testing.assert_array_equal(cloud.xyz, xyz)  # the same float64 operations, bit for bit
    for name in ("classification", "intensity", "gps_time"):
        np.testing.assert_array_equal(cloud[name], np.asarray(las[name]))


def test_only_the_asked_layers_give_the_same_values(laz):
    full = read_cloud(laz)
    assert max(full["classification"]) > 31  # point format 6+: layered LAZ
    some = read_cloud(laz, attributes=["intensity"], classes=[2, 40])
    keep = np.isin(full["classification"], [2, 40])
    assert list(some.attributes) == ["intensity"]
    np.testing.assert_array_equal(some.xyz, full.xyz[keep])
    np.testing.assert_array_equal(some["intensity"], full["intensity"][keep])


def test_read_keeps_one_array_and_no_second_copy(tmp_path):
    n = 200_000
    path = write_cloud(_terrain(n, 2), tmp_path / "m.las")
    read_cloud(path, attributes=[], chunk_size=20_000)  # warm up imports and caches
    tracemalloc.start()
    cloud = read_cloud(path, attributes=[], chunk_size=20_000)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    held = cloud.xyz.nbytes
    assert held == n * 24
    # a concatenation or a copy into the cloud would need at least 2 x 4.8 MB
    assert peak < 1.5 * held, f"peak {peak / 1e6:.1f} MB for a cloud of {held / 1e6:.1f} MB"
    assert not cloud.xyz.flags.writeable


def test_box_filter_equals_crop_of_the_full_read(laz):
    full = read_cloud(laz)
    box = [600_050.0, 5_400_020.0, 600_120.5, 5_400_150.0]
    part = read_cloud(laz, bbox=box, chunk_size=7_000)
    x, y = full.xyz[:, 0], full.xyz[:, 1]
    keep = (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])
    np.testing.assert_array_equal(part.xyz, full.xyz[keep])
    np.testing.assert_array_equal(part["gps_time"], full["gps_time"][keep])
    # a box that holds the whole header extent keeps every point (preallocated path)
    lo, hi = full.bounds
    whole = read_cloud(laz, bbox=[lo[0] - 1, lo[1] - 1, hi[0] + 1, hi[1] + 1], chunk_size=7_000)
    np.testing.assert_array_equal(whole.xyz, full.xyz)


def test_chunked_write_equals_one_chunk_and_laspy(tmp_path):
    cloud = _terrain(50_001, 3)
    a = write_cloud(cloud, tmp_path / "a.laz", chunk_size=7_000, parallel=True)
    b = write_cloud(cloud, tmp_path / "b.laz", chunk_size=10**6, parallel=False)
    xa, la = _laspy_xyz(a)
    xb, lb = _laspy_xyz(b)
    np.testing.assert_array_equal(xa, xb)
    assert np.abs(xa - cloud.xyz).max() <= 0.0005 + 1e-9  # rounding to the 1 mm grid
    for name in cloud.attributes:
        np.testing.assert_array_equal(np.asarray(la[name]), cloud[name])
    assert la.header.point_count == 50_001


def test_write_reports_every_chunk(tmp_path):
    events = []
    write_cloud(_terrain(10_500, 4), tmp_path / "p.laz", chunk_size=2_000, progress=events.append)
    steps = [e for e in events if not e.finished]
    assert [e.n for e in steps] == [2_000] * 5 + [500]
    assert events[-1].finished and events[-1].done == 10_500 and events[-1].desc == "writing p.laz"


def test_read_reports_every_chunk(laz):
    events = []
    read_cloud(laz, chunk_size=50_000, progress=events.append)
    assert [e.n for e in events if not e.finished] == [50_000, 50_000, 20_000]
    assert events[-1].total == 120_000


def test_write_refuses_coordinates_beyond_int32(tmp_path):
    cloud = PointCloud(np.array([[0.0, 0, 0], [5e6, 0, 0]]))
    with pytest.raises(LabkitError, match="coarser scale"):
        write_cloud(cloud, tmp_path / "far.las", scale=1e-4, chunk_size=1)
    assert not (tmp_path / "far.las").exists()


# ---------------------------------------------------------------------------- many files
@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    """Four 100 m tiles of one survey in a folder, plus a text file elsewhere."""
    folder = tmp_path_factory.mktemp("tiles")
    paths = []
    for k, (i, j) in enumerate([(0, 0), (1, 0), (0, 1), (1, 1)]):
        c = _terrain(8_000, 10 + k, x0=100.0 * i, y0=100.0 * j, side=100.0)
        paths.append(write_cloud(c, folder / f"t{i}{j}.laz"))
    return folder, paths


def test_cloud_files_from_folder_glob_and_list(tiles):
    folder, paths = tiles
    assert cloud_files(folder) == sorted(paths)
    assert cloud_files(str(folder / "t0*.laz")) == [folder / "t00.laz", folder / "t01.laz"]
    assert cloud_files([paths[1], folder / "t1*.laz"]) == [paths[1], folder / "t11.laz"]
    with pytest.raises(CloudFileError, match="no point-cloud file matches"):
        cloud_files(str(folder / "*.xyz"))
    with pytest.raises(CloudFileError, match="not found"):
        cloud_files([folder / "nope.laz"])


def test_files_in_box_by_header_extent(tiles):
    folder, _ = tiles
    x0, y0 = ORIGIN[:2]
    names = lambda box: [p.name for p in files_in_box(folder, box)]  # noqa: E731
    assert names([x0 + 10, y0 + 10, x0 + 20, y0 + 20]) == ["t00.laz"]
    assert names([x0 + 90, y0 + 10, x0 + 110, y0 + 20]) == ["t00.laz", "t10.laz"]
    assert names([x0 + 90, y0 + 90, x0 + 110, y0 + 110]) == ["t00.laz", "t01.laz", "t10.laz", "t11.laz"]
    assert names([x0 + 500, y0, x0 + 600, y0 + 10]) == []


def test_read_clouds_equals_cropping_all_files(tiles):
    folder, paths = tiles
    x0, y0 = ORIGIN[:2]
    box = [x0 + 60, y0 + 70, x0 + 140, y0 + 95]  # meets t00 and t10 only
    got = read_clouds(folder, bbox=box, chunk_size=3_000)
    full = [read_cloud(p) for p in paths]
    allxyz = np.concatenate([c.xyz for c in full])
    keep = (allxyz[:, 0] >= box[0]) & (allxyz[:, 0] <= box[2]) & (allxyz[:, 1] >= box[1]) & (allxyz[:, 1] <= box[3])
    np.testing.assert_array_equal(got.xyz, allxyz[keep])
    alli = np.concatenate([c["intensity"] for c in full])
    np.testing.assert_array_equal(got["intensity"], alli[keep])
    assert got.crs == "EPSG:25832" and got.name == "t00+1 files"


def test_read_clouds_skips_files_by_header_without_reading(tiles, monkeypatch):
    folder, _ = tiles
    import labkit.io.many as many  # read_clouds reads each file through the read_cloud it imported

    read = []
    real = many.read_cloud
    monkeypatch.setattr(many, "read_cloud", lambda p, **kw: read.append(p.name) or real(p, **kw))
    x0, y0 = ORIGIN[:2]
    read_clouds(folder, bbox=[x0 + 150, y0 + 150, x0 + 160, y0 + 160])
    assert read == ["t11.laz"]
    with pytest.raises(EmptyRegionError, match="keeps no point"):
        read_clouds(folder, bbox=[x0 - 50, y0 - 50, x0 - 10, y0 - 10])


def test_read_clouds_refuses_mixed_crs(tmp_path):
    a = write_cloud(_terrain(100, 20), tmp_path / "a.laz")
    other = _terrain(100, 21)
    b = write_cloud(PointCloud(other.xyz, other.attributes, crs="EPSG:25833"), tmp_path / "b.laz")
    with pytest.raises(CloudFileError, match="different CRS"):
        read_clouds([a, b])
