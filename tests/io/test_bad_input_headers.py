"""LAS headers checked against the data (labkit.io.las): point counts, the bounds a box filter may not trust,
truncated LAZ files named as such."""

import struct

import laspy
import numpy as np
import pytest

from labkit.cloud import PointCloud
from labkit.core.errors import CloudFileError, EmptyRegionError
from labkit.io import read_cloud, write_cloud
from labkit.regions import crop_box


def _file(tmp_path, suffix=".las", n=1000, version="1.2", point_format=1, evlr=False):
    rng = np.random.default_rng(0)
    las = laspy.create(point_format=point_format, file_version=version)
    xyz = rng.uniform(0, 100, (n, 3)) + [500_000.0, 5_400_000.0, 0.0]
    las.header.offsets, las.header.scales = [500_000.0, 5_400_000.0, 0.0], [0.001] * 3
    las.x, las.y, las.z = xyz.T
    las.intensity = rng.integers(0, 1000, n)
    if evlr:
        from laspy.vlrs.vlrlist import VLRList

        las.evlrs = VLRList([laspy.VLR(user_id="test", record_id=7, description="an EVLR after the points",
                                       record_data=b"x" * 100)])
    path = tmp_path / f"f{suffix}"
    las.write(str(path))
    return path


def _patch(path, offset, fmt, *values):
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


def _set_count(path, count, version):
    _patch(path, 107, "<I", count)  # legacy point count
    if version == "1.4":
        _patch(path, 247, "<Q", count)  # LAS 1.4 64-bit point count


@pytest.mark.parametrize("version, point_format", [("1.2", 1), ("1.3", 1), ("1.4", 6)])
@pytest.mark.parametrize("announced", [999, 500, 1])
def test_header_counting_fewer_points_than_the_file_holds(tmp_path, version, point_format, announced):
    path = _file(tmp_path, version=version, point_format=point_format)
    _set_count(path, announced, version)
    with pytest.raises(CloudFileError, match=f"counts {announced} points but the file holds 1000"):
        read_cloud(path)


@pytest.mark.parametrize("version, point_format, evlr", [("1.2", 1, False), ("1.3", 1, False), ("1.4", 6, False),
                                                         ("1.4", 6, True), ("1.4", 7, True)])
def test_a_right_count_reads_without_alarm(tmp_path, version, point_format, evlr):
    """EVLRs after the points are not taken for points."""
    path = _file(tmp_path, version=version, point_format=point_format, evlr=evlr)
    assert len(read_cloud(path)) == 1000


# header bounds (max x, min x, max y, min y, max z, min z at byte 179) that do not describe the points
WRONG_BOUNDS = {
    "shifted far away": (1e6, 9e5, 1e6, 9e5, 10.0, 0.0),
    "shrunk to a corner": (500_001.0, 500_000.0, 5_400_001.0, 5_400_000.0, 1.0, 0.0),
    "all zero": (0.0,) * 6,
    "min above max": (500_000.0, 500_100.0, 5_400_000.0, 5_400_100.0, 0.0, 100.0),
}


@pytest.mark.parametrize("bounds", sorted(WRONG_BOUNDS))
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_box_filter_does_not_trust_wrong_header_bounds(tmp_path, bounds, suffix):
    path = _file(tmp_path, suffix)
    full = read_cloud(path)
    _patch(path, 179, "<6d", *WRONG_BOUNDS[bounds])
    box = (500_020.0, 5_400_020.0, 500_060.0, 5_400_070.0)
    got = read_cloud(path, bbox=box, chunk_size=97)
    want = crop_box(full, box)
    assert len(want) > 100
    np.testing.assert_array_equal(got.xyz, want.xyz)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_box_beside_the_points_names_their_extent(tmp_path, suffix):
    path = _file(tmp_path, suffix)
    with pytest.raises(EmptyRegionError, match=r"outside the extent of the points .*x 500000\.\d+\.\.5000(99|100)"):
        read_cloud(path, bbox=(0, 0, 10, 10))


@pytest.mark.parametrize("keep", [0.0005, 0.01, 0.3, 0.7, 0.95, 0.9999])
def test_truncated_laz_is_named_as_such(tmp_path, keep):
    path = write_cloud(PointCloud(np.random.default_rng(1).uniform(0, 100, (60_000, 3))), tmp_path / "t.laz")
    data = path.read_bytes()
    cut = tmp_path / "cut.laz"
    cut.write_bytes(data[: max(400, int(len(data) * keep))])
    with pytest.raises(CloudFileError, match="truncated") as info:
        read_cloud(cut)
    assert "Laszip" not in str(info.value)


@pytest.mark.parametrize("garbage", [b"\xff" * 64, b"\x00" * 64, bytes(range(64))])
def test_corrupt_laz_points_are_named_as_such(tmp_path, garbage):
    path = write_cloud(PointCloud(np.random.default_rng(1).uniform(0, 100, (60_000, 3))), tmp_path / "t.laz")
    data = bytearray(path.read_bytes())
    start = len(data) // 3
    data[start:start + len(garbage)] = garbage
    path.write_bytes(bytes(data))
    try:
        read_cloud(path)  # the LAZ codec may decode damaged bytes to other values without noticing
    except CloudFileError as exc:
        assert "corrupt" in str(exc) or "truncated" in str(exc)
        assert "Laszip" not in str(exc)


@pytest.mark.parametrize("version, point_format", [("1.2", 1), ("1.4", 6)])
@pytest.mark.parametrize("announced", [100_000, 60_000, 1])
def test_laz_header_counting_fewer_points_than_its_chunks_hold(tmp_path, version, point_format, announced):
    """A LAZ file of 120,000 points in chunks of 50,000: a count below the first point of the last chunk is refused."""
    path = _file(tmp_path, ".laz", n=120_000, version=version, point_format=point_format)
    _set_count(path, announced, version)
    held = "120000" if point_format >= 6 else "at least 100001"  # formats 6-10 record the last chunk's count
    with pytest.raises(CloudFileError, match=f"counts {announced} points but the file holds {held} "):
        read_cloud(path)


@pytest.mark.parametrize("announced", [100_001, 119_999, 120_001, 139_999, 150_001])
@pytest.mark.parametrize("options", [{}, {"parallel": False}, {"classes": [1, 2]},
                                     {"bbox": (500_000, 5_400_000, 500_050, 5_400_050)}])
def test_laz_count_off_inside_the_last_chunk_is_refused(tmp_path, announced, options):
    """Point format 6: the last of three chunks (20,000 points) records its count; a header off by
    less than a chunk, either way, is refused with or without filters, never read short or long."""
    path = _file(tmp_path, ".laz", n=120_000, version="1.4", point_format=6)
    _set_count(path, announced, "1.4")
    with pytest.raises(CloudFileError, match=f"counts {announced} points but the file holds 120000 "):
        read_cloud(path, **options)


@pytest.mark.parametrize("options", [{}, {"parallel": False}, {"classes": [1, 2]}])
def test_laz_count_beyond_its_chunks_is_refused(tmp_path, options):
    """Point format 1 (no count per chunk): three chunks hold at most 150,000 points."""
    path = _file(tmp_path, ".laz", n=120_000, version="1.2", point_format=1)
    _set_count(path, 150_001, "1.2")
    with pytest.raises(CloudFileError, match="counts 150001 points but the file has room for at most 150000"):
        read_cloud(path, **options)


@pytest.mark.parametrize("options", [{"classes": [1, 2]}, {"bbox": (500_000, 5_400_000, 500_050, 5_400_050)}])
def test_laz_count_short_of_its_chunks_is_refused_with_filters_too(tmp_path, options):
    path = _file(tmp_path, ".laz", n=120_000, version="1.2", point_format=1)
    _set_count(path, 60_000, "1.2")
    with pytest.raises(CloudFileError, match="counts 60000 points but the file holds at least 100001"):
        read_cloud(path, **options)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_read_clouds_asks_the_points_before_saying_empty(tmp_path, suffix):
    from labkit.io import read_clouds

    path = _file(tmp_path, suffix)
    full = read_cloud(path)
    _patch(path, 179, "<6d", *WRONG_BOUNDS["shifted far away"])
    box = (500_020.0, 5_400_020.0, 500_060.0, 5_400_070.0)
    np.testing.assert_array_equal(read_clouds([path], bbox=box).xyz, crop_box(full, box).xyz)
    with pytest.raises(EmptyRegionError, match="the points were read"):
        read_clouds([path], bbox=(0, 0, 10, 10))
