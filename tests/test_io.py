"""labkit.io: LAS/LAZ, ASCII and NumPy files; chunked filtered reading; atomic writes.

Reference files are written with laspy directly (not with labkit), and the
expected coordinates are computed from the stored integers as X * scale + offset.
"""

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from labkit import regions  # noqa: E402
from labkit.cloud import PointCloud  # noqa: E402
from labkit.errors import CloudFileError, EmptyRegionError, LabkitError  # noqa: E402
from labkit.io import cloud_info, read_cloud, write_cloud  # noqa: E402

UTM_OFFSET = np.array([32_500_000.0, 5_600_000.0, 0.0])  # zone-prefixed easting, 8 digits


def _laspy_file(path, *, version, point_format, n=2000, scales=(0.01, 0.01, 0.0001), offsets=UTM_OFFSET, seed=0):
    """Write a LAS/LAZ file with laspy alone; return (expected xyz, expected attributes)."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales, header.offsets = np.array(scales), np.array(offsets)
    las = laspy.LasData(header)
    X = rng.integers(0, 20_000, n, dtype=np.int32)
    Y = rng.integers(0, 20_000, n, dtype=np.int32)
    Z = rng.integers(-500_000, 500_000, n, dtype=np.int32)
    las.X, las.Y, las.Z = X, Y, Z
    attrs = {
        "classification": rng.integers(0, 19 if point_format < 6 else 60, n).astype(np.uint8),
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "return_number": rng.integers(1, 6, n).astype(np.uint8),
        "number_of_returns": rng.integers(1, 6, n).astype(np.uint8),
        "point_source_id": rng.integers(0, 65535, n).astype(np.uint16),
    }
    if "gps_time" in header.point_format.dimension_names:
        attrs["gps_time"] = rng.uniform(3e8, 4e8, n)
    if "red" in header.point_format.dimension_names:
        for c in ("red", "green", "blue"):
            attrs[c] = rng.integers(0, 65535, n).astype(np.uint16)
    if "nir" in header.point_format.dimension_names:
        attrs["nir"] = rng.integers(0, 65535, n).astype(np.uint16)
    for k, v in attrs.items():
        las[k] = v
    las.write(str(path))
    xyz = np.column_stack([X, Y, Z]) * np.array(scales) + np.array(offsets)
    return xyz, attrs


# ---------------------------------------------------------------------------- reading LAS written by laspy
@pytest.mark.parametrize(
    "version, point_format",
    [("1.2", 0), ("1.2", 1), ("1.2", 2), ("1.2", 3), ("1.3", 4), ("1.4", 6), ("1.4", 7), ("1.4", 8)],
)
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_read_laspy_files(tmp_path, version, point_format, suffix):
    path = tmp_path / f"f{point_format}{suffix}"
    xyz, attrs = _laspy_file(path, version=version, point_format=point_format, n=500)
    cloud = read_cloud(path)
    assert cloud.xyz.dtype == np.float64
    assert np.abs(cloud.xyz - xyz).max() < 1e-6  # stored integers, exactly scaled (float64 rounding only)
    for k, v in attrs.items():
        np.testing.assert_array_equal(cloud[k], v, err_msg=k)
    assert cloud.name == f"f{point_format}"


@pytest.mark.parametrize("minor", [0, 1])
def test_read_las_1_0_and_1_1(tmp_path, minor):
    # laspy cannot write 1.0/1.1; the 1.2 header differs only in the version byte for format 1
    src = tmp_path / "v12.las"
    xyz, attrs = _laspy_file(src, version="1.2", point_format=1, n=300)
    data = bytearray(src.read_bytes())
    data[25] = minor  # version minor (LAS spec: byte 25)
    path = tmp_path / f"v1{minor}.las"
    path.write_bytes(bytes(data))
    cloud = read_cloud(path)
    assert np.abs(cloud.xyz - xyz).max() < 1e-6
    np.testing.assert_array_equal(cloud["classification"], attrs["classification"])


@pytest.mark.parametrize("scales", [(0.01, 0.01, 0.01), (0.0001, 0.0001, 0.0001), (0.001, 0.001, 0.0005)])
def test_unusual_scales_and_large_offsets(tmp_path, scales):
    offsets = (4_500_000.0, 5_900_000.0, 300.0)
    path = tmp_path / "s.laz"
    xyz, _ = _laspy_file(path, version="1.4", point_format=6, n=400, scales=scales, offsets=offsets)
    cloud = read_cloud(path)
    assert np.abs(cloud.xyz - xyz).max() < 1e-6


def test_crs_from_wkt_and_geotiff_keys(tmp_path):
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr

    wkt = 'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89"],AUTHORITY["EPSG","25832"]]'
    las = laspy.create(point_format=6, file_version="1.4")
    las.x, las.y, las.z = [500000.0, 500001.0], [5600000.0, 5600001.0], [10.0, 11.0]
    las.header.vlrs.append(WktCoordinateSystemVlr(wkt))
    las.write(str(tmp_path / "wkt.las"))
    assert read_cloud(tmp_path / "wkt.las").crs == wkt

    las = laspy.create(point_format=1, file_version="1.2")
    las.x, las.y, las.z = [500000.0, 500001.0], [5600000.0, 5600001.0], [10.0, 11.0]
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys = [GeoKeyEntryStruct(1024, 0, 1, 1), GeoKeyEntryStruct(3072, 0, 1, 25832)]
    vlr.geo_keys_header.number_of_keys = 2
    las.header.vlrs.append(vlr)
    las.write(str(tmp_path / "geokeys.las"))
    assert read_cloud(tmp_path / "geokeys.las").crs == "EPSG:25832"
    assert cloud_info(tmp_path / "geokeys.las").crs == "EPSG:25832"


def test_extra_bytes_dimension_is_kept(tmp_path):
    las = laspy.create(point_format=3, file_version="1.2")
    las.add_extra_dim(laspy.ExtraBytesParams(name="range", type=np.float32))
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.zeros(5)
    las["range"] = np.linspace(1, 2, 5).astype(np.float32)
    las.write(str(tmp_path / "eb.las"))
    cloud = read_cloud(tmp_path / "eb.las")
    np.testing.assert_array_equal(cloud["range"], np.linspace(1, 2, 5).astype(np.float32))


# ---------------------------------------------------------------------------- round trips through labkit
def _cloud(n=3000, seed=1, **extra):
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(0, 200, n), rng.uniform(0, 200, n), rng.uniform(-5, 40, n)]) + [
        512_345.0,
        5_612_345.0,
        80.0,
    ]
    attrs = {
        "classification": rng.choice([1, 2, 5, 6, 9, 11], n).astype(np.uint8),
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "return_number": rng.integers(1, 4, n).astype(np.uint8),
        "number_of_returns": np.full(n, 3, np.uint8),
        "gps_time": rng.uniform(3e8, 3.1e8, n),
        "point_source_id": rng.integers(1, 9, n).astype(np.uint16),
        **extra,
    }
    return PointCloud(xyz, attrs, crs="EPSG:25832", name="demo")


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("scale", [0.001, 0.01, 0.0001])
def test_las_round_trip_to_the_scale(tmp_path, suffix, scale):
    cloud = _cloud(planarity=np.linspace(0, 1, 3000))
    path = write_cloud(cloud, tmp_path / f"rt{suffix}", scale=scale)
    back = read_cloud(path)
    assert np.abs(back.xyz - cloud.xyz).max() <= scale / 2 * (1 + 1e-6)
    for k, v in cloud.attributes.items():
        np.testing.assert_array_equal(back[k], v, err_msg=k)
    assert back.crs == "EPSG:25832"
    info = cloud_info(path)
    np.testing.assert_allclose(info.scales, scale)
    assert (info.offsets % 1000 == 0).all() and (info.offsets <= cloud.xyz.min(axis=0)).all()
    assert info.compressed == (suffix == ".laz")


def test_auto_scale_rewrites_a_las_file_without_loss(tmp_path):
    src = tmp_path / "src.las"
    xyz, _ = _laspy_file(src, version="1.4", point_format=6, n=500, scales=(0.01, 0.01, 0.0001))
    cloud = read_cloud(src)
    out = write_cloud(cloud, tmp_path / "copy.las", scale=None)
    np.testing.assert_allclose(cloud_info(out).scales, [0.01, 0.01, 0.0001])
    assert np.abs(read_cloud(out).xyz - xyz).max() < 1e-6  # same grid: no rounding at all


def test_auto_point_format_and_wkt_crs(tmp_path):
    wkt = 'LOCAL_CS["site grid"]'
    cloud = _cloud(n=50).with_attributes(classification=np.full(50, 40, np.uint8))
    cloud = PointCloud(cloud.xyz, cloud.attributes, crs=wkt)
    path = write_cloud(cloud, tmp_path / "c40.laz")
    info = cloud_info(path)
    assert info.point_format == 6 and info.version == "1.4"  # class 40 needs the 8-bit field
    back = read_cloud(path)
    assert back.crs == wkt and (back["classification"] == 40).all()
    with pytest.raises(LabkitError, match="classification"):
        write_cloud(cloud, tmp_path / "c40_f1.las", point_format=1)
    assert not (tmp_path / "c40_f1.las").exists()


def test_scale_too_fine_for_the_extent(tmp_path):
    cloud = PointCloud([[0.0, 0, 0], [300_000.0, 0, 0]])
    with pytest.raises(LabkitError, match="coarser scale"):
        write_cloud(cloud, tmp_path / "big.las", scale=0.0001)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix, sep", [(".csv", ","), (".txt", " "), (".xyz", " ")])
def test_ascii_round_trip(tmp_path, suffix, sep):
    cloud = _cloud(n=400)
    path = write_cloud(cloud, tmp_path / f"a{suffix}")
    first = path.read_text().splitlines()[0]
    assert first.split(sep)[:4] == ["x", "y", "z", "classification"]
    back = read_cloud(path)
    assert np.abs(back.xyz - cloud.xyz).max() <= 0.0005 + 1e-9
    for k, v in cloud.attributes.items():
        assert back[k].dtype == v.dtype, k
        np.testing.assert_allclose(back[k], v, rtol=1e-13, err_msg=k)


def test_ascii_without_header_and_other_separators(tmp_path):
    rng = np.random.default_rng(3)
    table = np.column_stack([rng.uniform(0, 10, (50, 3)) + [600_000, 5_500_000, 0], rng.integers(0, 9, 50)])
    np.savetxt(tmp_path / "plain.xyz", table, fmt="%.3f %.3f %.3f %d")
    cloud = read_cloud(tmp_path / "plain.xyz")
    np.testing.assert_allclose(cloud.xyz, table[:, :3], atol=5e-4)
    np.testing.assert_array_equal(cloud["column_3"], table[:, 3])

    np.savetxt(tmp_path / "semi.csv", table, fmt="%.3f;%.3f;%.3f;%d", header="X;Y;Z;Class", comments="")
    np.testing.assert_array_equal(read_cloud(tmp_path / "semi.csv")["classification"], table[:, 3])

    # CloudCompare's export: '//X,Y,Z,Intensity' and columns in any order
    cc = np.column_stack([table[:, 3], table[:, 2], table[:, 0], table[:, 1]])
    np.savetxt(tmp_path / "cc.txt", cc, fmt="%d,%.3f,%.3f,%.3f", header="//Intensity,Z,X,Y", comments="")
    back = read_cloud(tmp_path / "cc.txt")
    np.testing.assert_allclose(back.xyz, table[:, :3], atol=5e-4)
    assert back["intensity"].dtype == np.uint16


def test_numpy_files(tmp_path):
    cloud = _cloud(n=300)
    arr = np.column_stack([cloud.xyz, cloud["classification"]])
    np.save(tmp_path / "plain.npy", arr)
    back = read_cloud(tmp_path / "plain.npy")
    np.testing.assert_array_equal(back.xyz, cloud.xyz)
    np.testing.assert_array_equal(back["column_3"], cloud["classification"])

    rec = np.zeros(300, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("classification", "u1")])
    rec["x"], rec["y"], rec["z"], rec["classification"] = *cloud.xyz.T, cloud["classification"]
    np.save(tmp_path / "rec.npy", rec)
    back = read_cloud(tmp_path / "rec.npy", classes=[2])
    np.testing.assert_array_equal(back.xyz, cloud.xyz[cloud["classification"] == 2])

    path = write_cloud(cloud, tmp_path / "c.npz")
    back = read_cloud(path)
    np.testing.assert_array_equal(back.xyz, cloud.xyz)  # npz is lossless
    assert back.crs == cloud.crs and set(back.attributes) == set(cloud.attributes)


# ---------------------------------------------------------------------------- chunked, filtered reading
POLY = [(512_380.0, 5_612_360.0), (512_520.0, 5_612_400.0), (512_470.0, 5_612_530.0), (512_400.0, 5_612_450.0)]


@pytest.mark.parametrize("suffix", [".las", ".laz", ".csv", ".npz"])
def test_chunked_filtered_read_equals_crop_after_full_read(tmp_path, suffix):
    cloud = _cloud(n=5000)
    path = write_cloud(cloud, tmp_path / f"big{suffix}")
    full = read_cloud(path)
    bbox = (512_400.0, 5_612_380.0, 512_500.0, 5_612_500.0)
    expected = regions.crop_classes(regions.crop_polygon(regions.crop_box(full, bbox), POLY), [2, 6])
    got = read_cloud(path, bbox=bbox, polygon=POLY, classes=[2, 6], chunk_size=613)
    assert 0 < len(got) < len(full)
    np.testing.assert_array_equal(got.xyz, expected.xyz)
    for k in full.attributes:
        np.testing.assert_array_equal(got[k], expected[k])


def test_read_only_some_attributes(tmp_path):
    path = write_cloud(_cloud(n=100), tmp_path / "a.laz")
    cloud = read_cloud(path, attributes=["classification"])
    assert list(cloud.attributes) == ["classification"]


def test_progress_bar_on_stderr(tmp_path, capsys):
    path = write_cloud(_cloud(n=1000), tmp_path / "p.laz")
    read_cloud(path, chunk_size=100, progress=True)
    err = capsys.readouterr().err
    assert "p.laz" in err and "100.0%" in err and "1,000 of 1,000" in err


# ---------------------------------------------------------------------------- bad input
def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(CloudFileError, match="nothere.laz"):
        read_cloud(tmp_path / "nothere.laz")
    (tmp_path / "cloud.ply").write_text("ply\n")
    with pytest.raises(CloudFileError, match=r"cloud\.ply"):
        read_cloud(tmp_path / "cloud.ply")
    with pytest.raises(CloudFileError, match="not a file"):
        read_cloud(tmp_path)
    assert issubclass(CloudFileError, ValueError)


def test_corrupt_files_name_the_file(tmp_path):
    (tmp_path / "garbage.las").write_bytes(b"LASF" + bytes(range(256)) * 3)
    with pytest.raises(CloudFileError, match="garbage.las"):
        read_cloud(tmp_path / "garbage.las")
    (tmp_path / "text.laz").write_text("this is no point cloud")
    with pytest.raises(CloudFileError, match="text.laz"):
        read_cloud(tmp_path / "text.laz")

    good = write_cloud(_cloud(n=3000), tmp_path / "good.laz")
    data = good.read_bytes()
    (tmp_path / "cut.laz").write_bytes(data[: len(data) // 2])
    with pytest.raises(CloudFileError, match="cut.laz"):
        read_cloud(tmp_path / "cut.laz")
    bad = bytearray(data)
    bad[100:104] = (2**32 - 1).to_bytes(4, "little")  # billions of VLRs announced
    (tmp_path / "vlrs.laz").write_bytes(bytes(bad))
    with pytest.raises(CloudFileError, match="vlrs.laz.*VLRs"):
        read_cloud(tmp_path / "vlrs.laz")
    good = write_cloud(_cloud(n=3000), tmp_path / "good.las")
    data = good.read_bytes()
    (tmp_path / "cut.las").write_bytes(data[: len(data) - 1000])
    with pytest.raises(CloudFileError, match="cut.las"):
        read_cloud(tmp_path / "cut.las")


def test_bad_text_files(tmp_path):
    (tmp_path / "empty.csv").write_text("\n\n")
    with pytest.raises(CloudFileError, match="empty.csv"):
        read_cloud(tmp_path / "empty.csv")
    (tmp_path / "bad.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    with pytest.raises(CloudFileError, match="bad.csv"):
        read_cloud(tmp_path / "bad.csv")
    (tmp_path / "nan.txt").write_text("1 2 3\nnan 2 3\n")
    with pytest.raises(CloudFileError, match="nan.txt.*NaN"):
        read_cloud(tmp_path / "nan.txt")
    (tmp_path / "noz.csv").write_text("x,y,h\n1,2,3\n")
    with pytest.raises(CloudFileError, match="z"):
        read_cloud(tmp_path / "noz.csv")
    (tmp_path / "two.txt").write_text("1 2\n3 4\n")
    with pytest.raises(CloudFileError, match="3 columns"):
        read_cloud(tmp_path / "two.txt")


def test_empty_filters_raise_empty_region(tmp_path):
    path = write_cloud(_cloud(n=500), tmp_path / "e.laz")
    with pytest.raises(EmptyRegionError, match="outside the extent"):
        read_cloud(path, bbox=(0, 0, 10, 10))
    with pytest.raises(EmptyRegionError, match=r"classes \[17\]"):
        read_cloud(path, classes=17)
    assert issubclass(EmptyRegionError, ValueError)
    plain = tmp_path / "plain.xyz"
    plain.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(CloudFileError, match="no classification"):
        read_cloud(plain, classes=[2])


# ---------------------------------------------------------------------------- atomic writes
@pytest.mark.parametrize("suffix", [".laz", ".csv"])
def test_failed_write_leaves_no_file(tmp_path, monkeypatch, suffix):
    cloud = _cloud(n=5000)
    calls = {"n": 0}

    def fail_on_second_chunk(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full (simulated)")
        return original(*args, **kwargs)

    if suffix == ".laz":
        original = laspy.LasWriter.write_points
        monkeypatch.setattr(laspy.LasWriter, "write_points", fail_on_second_chunk)
    else:
        original = np.savetxt
        monkeypatch.setattr(np, "savetxt", fail_on_second_chunk)
    with pytest.raises(CloudFileError, match="disk full"):
        write_cloud(cloud, tmp_path / f"out{suffix}", chunk_size=1000)
    assert calls["n"] == 2  # it really failed half way
    assert list(tmp_path.iterdir()) == []  # neither the file nor a temporary is left


def test_failed_overwrite_keeps_the_old_file(tmp_path, monkeypatch):
    path = write_cloud(_cloud(n=200), tmp_path / "keep.las")
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("interrupted")

    monkeypatch.setattr(laspy.LasWriter, "write_points", boom)
    with pytest.raises(RuntimeError):
        write_cloud(_cloud(n=300, seed=9), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.las"]


def test_write_into_missing_folder(tmp_path):
    with pytest.raises(CloudFileError, match="does not exist"):
        write_cloud(_cloud(n=10), tmp_path / "no" / "such.laz")


def test_written_files_get_the_usual_permissions(tmp_path):
    """Atomic writes go through mkstemp (mode 0600); the result must have 0666 minus the umask."""
    import os
    import stat

    from labkit._atomic import atomic_write_text

    mask = os.umask(0o022)
    try:
        cloud = PointCloud(np.arange(12.0).reshape(4, 3))
        files = [write_cloud(cloud, tmp_path / f"c{s}") for s in (".laz", ".csv", ".npz")]
        files.append(atomic_write_text(tmp_path / "t.json", "{}"))
    finally:
        os.umask(mask)
    for f in files:
        assert stat.S_IMODE(f.stat().st_mode) == 0o644, f
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f.name for f in files)  # no temp files left
