"""labkit.io.write.write_moved: the moved LAS/LAZ file, chunk by chunk, equals writing the moved cloud from memory.

The reference route is ``write_cloud(read_cloud(src).with_xyz(T(xyz)))``; the files are compared byte for byte
and point for point (laspy), across point formats, extra bytes, a CRS in feet, chunk bounds and a rotation.
"""

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from labkit.io import read_cloud, write_cloud  # noqa: E402
from labkit.io.write import write_moved  # noqa: E402
from labkit.transforms import apply_transform, make_transform, rotation_from_angles  # noqa: E402

UTM = np.array([512_345.0, 5_612_345.0, 80.0])


def _file(path, point_format, n=2500, seed=0, feet=False):
    """A LAS/LAZ file written by laspy alone, with extra bytes and (optionally) a CRS in US survey feet."""
    rng = np.random.default_rng(seed)
    version = "1.4" if point_format >= 6 else "1.2"
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.add_extra_dim(laspy.ExtraBytesParams(name="range", type=np.float32))
    header.scales, header.offsets = np.array([0.001, 0.001, 0.001]), np.array([512_000.0, 5_612_000.0, 0.0])
    if feet:
        header.add_crs(__import__("pyproj").CRS.from_epsg(2263))  # NAD83 / New York Long Island (ftUS)
    las = laspy.LasData(header)
    las.x = UTM[0] + rng.uniform(0, 200, n)
    las.y = UTM[1] + rng.uniform(0, 200, n)
    las.z = UTM[2] + rng.uniform(-5, 40, n)
    las.classification = rng.choice([1, 2, 6], n).astype(np.uint8)
    las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    las["range"] = rng.uniform(1, 2, n).astype(np.float32)
    las.write(str(path))
    return path


def _points(path):
    with laspy.open(str(path)) as r:
        las = r.read()
    return las, r.header


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("point_format", [1, 3, 6])
@pytest.mark.parametrize("rigid", [False, True])
def test_the_same_file_as_writing_the_moved_cloud(tmp_path, suffix, point_format, rigid):
    src = _file(tmp_path / f"src{suffix}", point_format)
    R = rotation_from_angles(0.001, -0.002, 0.003) if rigid else np.eye(3)
    T = make_transform(R, [0.23, -0.17, 0.11])
    cloud = read_cloud(src)
    ref = write_cloud(cloud.with_xyz(apply_transform(T, cloud.xyz)), tmp_path / f"ref{suffix}", chunk_size=1000)
    got = write_moved(src, tmp_path / f"got{suffix}", lambda xyz: apply_transform(T, xyz), chunk_size=1000)
    assert got == tmp_path / f"got{suffix}"
    assert (tmp_path / f"got{suffix}").read_bytes() == ref.read_bytes()
    a, b = _points(got)[0], _points(src)[0]
    for name in ("intensity", "classification", "range"):  # every attribute kept
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]))
    np.testing.assert_allclose(np.c_[a.x, a.y, a.z], apply_transform(T, np.c_[b.x, b.y, b.z]), atol=5e-4)


def test_a_file_in_feet_is_moved_in_metres_and_stored_in_feet(tmp_path):
    pytest.importorskip("pyproj")
    src = _file(tmp_path / "ft.laz", 1, feet=True)
    cloud = read_cloud(src)
    assert cloud.units.converted
    T = make_transform(np.eye(3), [0.3, 0.0, -0.2])  # metres
    ref = write_cloud(cloud.with_xyz(apply_transform(T, cloud.xyz)), tmp_path / "ref.laz")
    got = write_moved(src, tmp_path / "got.laz", lambda xyz: apply_transform(T, xyz))
    assert got.read_bytes() == ref.read_bytes()
    moved = read_cloud(got)
    np.testing.assert_allclose(moved.xyz - cloud.xyz, np.tile([0.3, 0.0, -0.2], (len(cloud), 1)), atol=1e-3)


def test_points_beyond_the_offsets_write_nothing(tmp_path):
    src = _file(tmp_path / "src.laz", 1)
    far = make_transform(np.eye(3), [3.0e6, 0.0, 0.0])  # 3000 km: beyond int32 at 1 mm from the offset
    out = tmp_path / "far.laz"
    assert write_moved(src, out, lambda xyz: apply_transform(far, xyz)) is None
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["src.laz"]
