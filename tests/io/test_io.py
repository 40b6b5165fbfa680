"""labkit.io: LAS/LAZ, ASCII and NumPy files; chunked filtered reading; atomic writes.

Reference files are written with laspy directly (not with labkit), and the
expected coordinates are computed from the stored integers as X * scale + offset.
"""

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from labkit import regions  # noqa: E402
from labkit.cloud import PointCloud  # noqa: E402
from labkit.core.errors import CloudFileError, EmptyRegionError, LabkitError  # noqa: E402
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
    with pytest.raises(CloudFileError, match="RuntimeError: interrupted"):
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

    from labkit.core.atomic import atomic_write_text

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


# ---------------------------------------------------------------------------- units from the file
from pathlib import Path  # noqa: E402

from labkit.core.units import parse_wkt, units_from_wkt  # noqa: E402
from labkit.core.units import UnitsError  # noqa: E402

DATA_REAL = Path(__file__).resolve().parents[2] / "data" / "real"
US_FT, FT = 1200.0 / 3937.0, 0.3048  # metres per US survey foot / international foot (definitions)


def _raw_xyz(path):
    """Stored coordinates X * scale + offset, straight from laspy (no labkit)."""
    las = laspy.read(str(path))
    return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])


# file -> (X/Y unit, Z unit, conflict expected); from the CRS records as described in shared/realdata/README.md
REAL_UNITS = {
    "epochs/autzen-bmx-2010.las": ("metre", "US survey foot", False),
    "epochs/autzen-bmx-2023.las": ("metre", "US survey foot", False),
    "als/interesting.las": ("foot", "foot", False),
    "als/4_6_crop.las": ("US survey foot", "US survey foot", False),
    "als/file_with_both_wkt_and_geotiff_vlrs.las": ("US survey foot", "US survey foot", True),
    "als/MixedConifer.laz": ("metre", "metre", False),
    "als/las_with_several_extra_byte_bloc.laz": ("metre", "metre", False),
    "als/append-bug.laz": ("metre", "metre", False),
    "als/faceraster_numerical_imprecision.laz": ("metre", "metre", False),
    "als/fullwave.laz": ("metre", "metre", False),
    "als/warsaw_small.las": ("unknown", "unknown", False),
    "als/sample_c.las": ("unknown", "unknown", False),
    "dim/pybathysfm_sample_sfm_epsg27700.laz": ("metre", "metre", False),
    "tls/plane.laz": ("metre", "metre", False),
    "tls/vegetation_1_3.las": ("unknown", "unknown", False),
}
_FACTOR = {"metre": 1.0, "US survey foot": US_FT, "foot": FT, "unknown": 1.0}


@pytest.mark.parametrize("name", sorted(REAL_UNITS))
def test_units_of_the_real_files(realdata, name):
    h, v, conflict = REAL_UNITS[name]
    path = realdata / name
    info = cloud_info(path)
    assert (info.units.horizontal, info.units.vertical) == (h, v)
    assert (info.units.conflict is not None) == conflict
    raw = _raw_xyz(path)
    metres = read_cloud(path)
    factors = np.array([_FACTOR[h], _FACTOR[h], _FACTOR[v]])
    np.testing.assert_allclose(metres.xyz, raw * factors, rtol=1e-15, atol=0)
    assert metres.units.converted == bool((factors != 1).any())
    assert metres.units.is_metric or metres.units.coordinates == ("unknown", "unknown")
    native = read_cloud(path, units="native")
    np.testing.assert_array_equal(native.xyz, raw)
    assert native.units.coordinates == (h, v)
    # the header summary labels each axis with the file's unit, never metres for feet
    text = info.summary()
    short = {"metre": "m", "US survey foot": "ftUS", "foot": "ft", "unknown": "(units not stated)"}
    min_line = next(line for line in text.split("\n") if line.startswith("min "))
    assert short[h] in min_line and short[v] in min_line
    if h != "metre" and v != "metre":
        assert not any(line.rstrip().endswith(" m") for line in text.split("\n") if line[:4] in ("min ", "max "))


def test_epsg_4326_is_refused_before_any_metric_step(realdata):
    path = realdata / "als" / "epsg_4326.las"
    with pytest.raises(UnitsError, match="longitude/latitude"):
        read_cloud(path)
    cloud = read_cloud(path, units="native")
    np.testing.assert_array_equal(cloud.xyz, _raw_xyz(path))  # reading for non-metric use is exact
    assert cloud.units.angular and not cloud.units.is_metric
    from labkit.features import normals

    with pytest.raises(UnitsError, match="degrees of longitude/latitude"):
        normals(cloud, k=8)
    with pytest.raises(UnitsError, match="degrees"):
        cloud.require_metric()


def test_units_travel_with_subsets_transforms_and_merges():
    cloud = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-2010.las")
    assert cloud.units.converted and cloud.units.vertical == "US survey foot"
    for derived in (cloud.subset(np.arange(10)), cloud.with_xyz(cloud.xyz + 1.0),
                    cloud.with_attributes(flag=np.zeros(len(cloud))), regions.merge(cloud, cloud)):
        assert derived.units == cloud.units
    native = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-2010.las", units="native")
    with pytest.raises(LabkitError, match="different units"):
        regions.merge(cloud, native)


def test_feet_and_metres_of_one_area_agree_after_conversion():
    """Independent check: interesting.las (Oregon Lambert, international feet) and the Autzen epochs
    (the same projection in metres, heights in US survey feet) cover the same ground. Converted to
    metres, the ground of interesting.las around the epochs' patch has the epochs' height."""
    epoch = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-2010.las")
    thin = read_cloud(DATA_REAL / "als" / "interesting.las", classes=[2])
    centre = epoch.xyz.mean(axis=0)
    d = np.hypot(*(thin.xyz[:, :2] - centre[:2]).T)
    near = thin.xyz[np.argsort(d)[:5]]
    assert d[np.argsort(d)[4]] < 300.0  # same place in metres (in feet the frames would be 3.3x apart)
    assert abs(np.median(near[:, 2]) - np.median(epoch.xyz[:, 2])) < 5.0  # flat valley floor: within 5 m
    native = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-2010.las", units="native")
    assert abs(np.median(near[:, 2]) - np.median(native.xyz[:, 2])) > 250.0  # unconverted feet are far off


@pytest.mark.parametrize("name", ["epochs/autzen-bmx-2010.las", "als/4_6_crop_every24.las",
                                  "als/interesting.las", "als/file_with_both_wkt_and_geotiff_vlrs_every25.las"])
@pytest.mark.parametrize("suffix", [".las", ".npz"])
def test_converted_clouds_are_written_in_their_file_units(tmp_path, name, suffix):
    original = DATA_REAL / name
    cloud = read_cloud(original)
    out = write_cloud(cloud, tmp_path / f"copy{suffix}", scale=None)
    back_native = read_cloud(out, units="native")
    np.testing.assert_allclose(back_native.xyz, _raw_xyz(original), rtol=0, atol=1e-6)  # feet again
    assert back_native.units.coordinates == (cloud.units.horizontal, cloud.units.vertical)
    back = read_cloud(out)
    np.testing.assert_allclose(back.xyz, cloud.xyz, rtol=0, atol=1e-6)
    assert back.units.is_metric


def test_filters_act_in_metres_on_a_feet_file():
    path = DATA_REAL / "als" / "4_6_crop_every24.las"
    full = read_cloud(path)
    lo, hi = full.xyz.min(axis=0), full.xyz.max(axis=0)
    box = (lo[0], lo[1], (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2)
    got = read_cloud(path, bbox=box, chunk_size=100)
    want = regions.crop_box(full, box)
    np.testing.assert_array_equal(got.xyz, want.xyz)
    assert 0 < len(got) < len(full)


def test_contradicting_wkt_and_geokeys_decided_by_the_wkt_bit(tmp_path):
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr

    wkt = ('PROJCS["local TM",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
           'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
           'PARAMETER["false_easting",500000],UNIT["metre",1]]')
    results = {}
    for version, bit in (("1.4", True), ("1.4", False), ("1.2", False)):
        las = laspy.create(point_format=6 if version == "1.4" else 1, file_version=version)
        las.x, las.y, las.z = [1000.0, 1001.0], [2000.0, 2001.0], [10.0, 11.0]
        keys = GeoKeyDirectoryVlr()
        keys.geo_keys = [GeoKeyEntryStruct(1024, 0, 1, 1), GeoKeyEntryStruct(3076, 0, 1, 9002)]
        keys.geo_keys_header.number_of_keys = 2
        las.header.vlrs.extend([keys, WktCoordinateSystemVlr(wkt)])
        if version == "1.4":
            las.header.global_encoding.wkt = bit
        path = tmp_path / f"v{version}_{bit}.las"
        las.write(str(path))
        cloud = read_cloud(path)
        results[(version, bit)] = cloud
        assert "WKT says X/Y in metre" in cloud.units.conflict and "GeoKeys say X/Y in foot" in cloud.units.conflict
    assert results[("1.4", True)].units.horizontal == "metre"
    np.testing.assert_allclose(results[("1.4", True)].xyz[:, 2], [10.0, 11.0])
    for key in (("1.4", False), ("1.2", False)):
        assert results[key].units.horizontal == "foot" and results[key].units.source == "GeoKeys"
        np.testing.assert_allclose(results[key].xyz[:, 2], np.array([10.0, 11.0]) * FT, rtol=1e-15)


def test_real_conflicting_file_uses_the_wkt_and_records_why():
    info = cloud_info(DATA_REAL / "als" / "file_with_both_wkt_and_geotiff_vlrs_every25.las")
    assert info.units.source == "WKT" and info.units.horizontal == "US survey foot"
    assert "EPSG:32104 is a metre CRS" in info.units.conflict and "LAS 1.4 WKT bit" in info.units.conflict
    assert "CONFLICT" in info.summary()


# WKT texts written by hand after the OGC 01-009 / 18-010r7 grammar and the ESRI dialect
WKT2_FTUS = ('PROJCRS["NAD83 / Texas Central (ftUS)",BASEGEOGCRS["NAD83",DATUM["North American Datum 1983",'
             'ELLIPSOID["GRS 1980",6378137,298.257222101,LENGTHUNIT["metre",1]]],ANGLEUNIT["degree",0.0174532925199433]],'
             'CONVERSION["SPCS83 Texas Central zone (US Survey feet)",METHOD["Lambert Conic Conformal (2SP)"],'
             'PARAMETER["Easting at false origin",2296583.333,LENGTHUNIT["metre",1]]],'
             'CS[Cartesian,2],AXIS["easting (X)",east,ORDER[1],LENGTHUNIT["US survey foot",0.304800609601219]],'
             'AXIS["northing (Y)",north,ORDER[2],LENGTHUNIT["US survey foot",0.304800609601219]],ID["EPSG",2277]]')


@pytest.mark.parametrize("text, expected", [
    (WKT2_FTUS, ("US survey foot", None)),  # the CONVERSION's metre parameter must not count
    ('COMPOUNDCRS["x",' + WKT2_FTUS + ',VERTCRS["NAVD88 height (ftUS)",VDATUM["North American Vertical Datum 1988"],'
     'CS[vertical,1],AXIS["gravity-related height (H)",up,LENGTHUNIT["US survey foot",0.304800609601219]]]]',
     ("US survey foot", "US survey foot")),
    ('GEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563]],'
     'CS[ellipsoidal,2],AXIS["latitude",north],AXIS["longitude",east],ANGLEUNIT["degree",0.0174532925199433]]',
     ("degree", None)),
    ('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],'
     'UNIT["degree",0.0174532925199433]]', ("degree", None)),
    ('PROJCS["NAD_1983_StatePlane_Oregon_North_FIPS_3601_Feet_Intl",GEOGCS["GCS_North_American_1983",'
     'DATUM["D_North_American_1983",SPHEROID["GRS_1980",6378137.0,298.257222101]],PRIMEM["Greenwich",0.0],'
     'UNIT["Degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic"],UNIT["Foot",0.3048]]', ("foot", None)),
    ('BOUNDCRS[SOURCECRS[' + WKT2_FTUS + '],TARGETCRS[GEOGCRS["WGS 84",DATUM["WGS 84",ELLIPSOID["WGS 84",6378137,'
     '298.257223563]],CS[ellipsoidal,2],ANGLEUNIT["degree",0.0174532925199433]]],ABRIDGEDTRANSFORMATION["t",'
     'METHOD["Geocentric translations"],PARAMETER["X-axis translation",1,LENGTHUNIT["metre",1]]]]',
     ("US survey foot", None)),
    ('PROJCS["x",GEOGCS["y"],UNIT["kilometre",1000]]', ("kilometre", None)),
])
def test_wkt_units(text, expected):
    h, v = units_from_wkt(text)
    assert (h[0] if h else None, v[0] if v else None) == expected


@pytest.mark.parametrize("text", ["", "not a crs", "POLYGON((6 15, 10 10, 20 10))", 'PROJCS["x",UNIT["m",1]',
                                  "PROJCS[]]"])
def test_non_crs_text_is_not_taken_for_a_crs(text):
    assert units_from_wkt(text) is None or units_from_wkt(text) == (None, None)


def test_wkt_parser_reads_nested_strings_and_numbers():
    root = parse_wkt('A["q""uote",1.5e3,B[ENUM,-2]]')
    assert root.key == "A" and root.args[0] == 'q"uote' and root.args[1] == 1500.0
    assert root.first("B").args == ["ENUM", -2.0]


def test_point_cloud_units_from_its_crs_text():
    assert PointCloud(np.zeros((2, 3)), crs="EPSG:4326").units.angular
    assert PointCloud(np.zeros((2, 3)), crs="EPSG:32632").units.is_metric
    feet = PointCloud(np.zeros((2, 3)), crs="EPSG:2903").units  # NAD83(HARN) / New Mexico Central (ftUS)
    assert (feet.horizontal, feet.vertical) == ("US survey foot", "US survey foot")
    assert feet.horizontal_to_metre == US_FT
    assert not PointCloud(np.zeros((2, 3))).units.known
    with pytest.raises(LabkitError, match="Units"):
        PointCloud(np.zeros((2, 3)), units="m")


# ---------------------------------------------------------------------------- PLY
def _ply_bytes(fmt, xyz, intensity, extra_header=""):
    n = len(xyz)
    head = (f"ply\nformat {fmt} 1.0\ncomment written by the test\n{extra_header}element vertex {n}\n"
            "property double x\nproperty double y\nproperty double z\nproperty ushort intensity\n"
            "property float scalar_Deviation\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    dev = (np.arange(n) / 7.0).astype(np.float32)
    if fmt == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r} {i} {d!r}\n" for (x, y, z), i, d in zip(xyz.tolist(), intensity.tolist(),
                                                                                  dev.astype(float).tolist()))
        return head.encode() + body.encode() + b"3 0 1 2\n", dev
    end = "<" if fmt == "binary_little_endian" else ">"
    rec = np.zeros(n, dtype=[("x", end + "f8"), ("y", end + "f8"), ("z", end + "f8"), ("i", end + "u2"), ("d", end + "f4")])
    rec["x"], rec["y"], rec["z"], rec["i"], rec["d"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], intensity, dev
    face = np.array([3], np.uint8).tobytes() + np.array([0, 1, 2], end + "i4").tobytes()
    return head.encode() + rec.tobytes() + face, dev


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_files(tmp_path, fmt):
    rng = np.random.default_rng(4)
    xyz = rng.uniform(0, 50, (500, 3)) + [32_500_000.0, 5_600_000.0, 0.0]
    intensity = rng.integers(0, 65535, 500).astype(np.uint16)
    data, dev = _ply_bytes(fmt, xyz, intensity)
    path = tmp_path / "c.ply"
    path.write_bytes(data)
    cloud = read_cloud(path, chunk_size=77)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud["intensity"], intensity)
    np.testing.assert_allclose(cloud["scalar_deviation"], dev, rtol=1e-6)
    assert cloud["intensity"].dtype == np.uint16
    box = (xyz[:, 0].min(), xyz[:, 1].min(), np.median(xyz[:, 0]), np.median(xyz[:, 1]))
    np.testing.assert_array_equal(read_cloud(path, bbox=box).xyz, regions.crop_box(cloud, box).xyz)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_agrees_with_open3d(tmp_path, fmt):
    o3d = pytest.importorskip("open3d")
    xyz = np.random.default_rng(5).normal(size=(300, 3)) * 10
    path = tmp_path / "o.ply"
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=fmt == "ascii")
    if fmt == "binary_big_endian":  # open3d writes little endian only: swap the body by hand
        raw = path.read_bytes()
        head, body = raw.split(b"end_header\n", 1)
        head = head.replace(b"binary_little_endian", b"binary_big_endian")
        props = [ln.split()[1] for ln in head.decode().splitlines() if ln.startswith("property")]
        dt = np.dtype([(f"p{i}", "<" + {"double": "f8", "float": "f4"}[t]) for i, t in enumerate(props)])
        rec = np.frombuffer(body, dtype=dt)
        path.write_bytes(head + b"end_header\n" + rec.astype(dt.newbyteorder(">")).tobytes())
    ours = read_cloud(path).xyz
    theirs = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "o.ply")).points) if fmt != "binary_big_endian" else xyz
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9 if fmt != "ascii" else 1e-5)


@pytest.mark.parametrize("suffix", [".las", ".csv"])
def test_a_cloud_in_degrees_is_written_at_a_fine_enough_scale(tmp_path, suffix):
    native = read_cloud(DATA_REAL / "als" / "epsg_4326.las", units="native")
    out = write_cloud(native, tmp_path / f"deg{suffix}")
    back = read_cloud(out, units="native")
    # 1e-7 degrees is the file's own resolution: nothing is lost (0.001 degrees would move points by ~100 m)
    np.testing.assert_allclose(back.xyz[:, :2], native.xyz[:, :2], rtol=0, atol=0.51e-7)
    if suffix == ".las":
        assert back.units.angular


AUTZEN_WKT = ('COMPD_CS["m + ftUS",PROJCS["NAD83 / Oregon LCC (m)",GEOGCS["NAD83",UNIT["degree",0.0174532925199433]],'
              'UNIT["metre",1]],VERT_CS["NAVD88 height (ftUS)",UNIT["US survey foot",0.304800609601219]]]')


@pytest.mark.parametrize("keys, bit, expected, conflict", [
    ({1024: (0, 1, 1), 3076: (0, 1, 9001)}, True, ("metre", "US survey foot"), None),  # keys state no Z: no conflict
    ({1024: (0, 1, 1), 3076: (0, 1, 9001), 4099: (0, 1, 9001)}, True, ("metre", "US survey foot"), "Z in metre"),
    ({1024: (0, 1, 1), 3076: (0, 1, 9001), 4099: (0, 1, 9001)}, False, ("metre", "metre"), "used the GeoKeys"),
    ({1024: (0, 1, 1), 3076: (0, 1, 32767), 3077: (34736, 1, 0)}, True, ("metre", "US survey foot"), "X/Y in US survey foot"),
])
def test_decision_rule_compares_only_stated_units(keys, bit, expected, conflict):
    from labkit.core.units import decide_units

    u = decide_units(AUTZEN_WKT, keys, doubles=(US_FT,), wkt_bit=bit, las14=True)
    assert (u.horizontal, u.vertical) == expected
    assert (u.conflict is None) if conflict is None else (conflict in u.conflict)
