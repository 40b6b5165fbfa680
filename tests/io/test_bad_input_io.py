"""File cases: every bad or unusual file input gets a right answer or one clear LabkitError.

Each case states its exact outcome: an error type with a message fragment, or the value read.
Files are built with laspy or plain bytes, never with the labkit writer under test.
"""

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from labkit import regions  # noqa: E402
from labkit.cloud import PointCloud  # noqa: E402
from labkit.core.units import UnitsError  # noqa: E402
from labkit.core.errors import CloudFileError, LabkitError  # noqa: E402
from labkit.io import read_cloud, write_cloud  # noqa: E402

DATA_REAL = Path(__file__).resolve().parents[2] / "data" / "real"


def _cloud(n=5, **attrs):
    xyz = np.column_stack([np.arange(n) * 1.0, np.arange(n) * 2.0, np.zeros(n)]) + [500_000.0, 5_600_000.0, 100.0]
    return PointCloud(xyz, attrs, name="c")


# ============================================================================ write_cloud: values that do not fit
WRITE_CASES = [
    # (id, attributes, write keyword arguments, error fragment)
    ("intensity -5", {"intensity": np.array([1, -5, 3, 4, 5])}, {}, "'intensity' holds values -5..5, outside the range 0..65535"),
    ("intensity 70000", {"intensity": np.array([1, 70000, 3, 4, 5])}, {}, "outside the range 0..65535"),
    ("classification 300", {"classification": np.array([1, 300, 2, 2, 2])}, {}, "'classification' holds values 1..300, outside the range 0..255"),
    ("classification 40 in format 1", {"classification": np.full(5, 40)}, {"point_format": 1}, "outside the range 0..31"),
    ("classification -1", {"classification": np.array([-1, 2, 2, 2, 2])}, {}, "outside the range 0..31"),
    ("return_number 9 in format 3", {"return_number": np.full(5, 9), "gps_time": np.zeros(5), "red": np.zeros(5, np.uint16)},
     {"point_format": 3}, "'return_number' holds values 9..9, outside the range 0..7"),
    ("return_number 16 in format 6", {"return_number": np.full(5, 16)}, {"point_format": 6}, "outside the range 0..15"),
    ("user_data 256", {"user_data": np.full(5, 256)}, {}, "'user_data' holds values 256..256, outside the range 0..255"),
    ("point_source_id -1", {"point_source_id": np.full(5, -1)}, {}, "outside the range 0..65535"),
    ("scan_angle_rank 200", {"scan_angle_rank": np.full(5, 200)}, {}, "outside the range -128..127"),
    ("red 65536", {"red": np.full(5, 65536), "green": np.zeros(5), "blue": np.zeros(5)}, {}, "'red' holds values 65536..65536"),
    ("intensity NaN", {"intensity": np.array([1.0, np.nan, 3, 4, 5])}, {}, "'intensity' holds NaN or infinite values"),
    ("intensity 3.5", {"intensity": np.array([1.0, 3.5, 3, 4, 5])}, {}, "must hold whole numbers"),
    ("32-character names", {"a" * 32 + "_first": np.arange(5.0), "a" * 32 + "_second": np.arange(5.0)}, {},
     "share their first 32 characters"),
    ("non-ASCII name", {"höhe": np.arange(5.0)}, {}, "must be ASCII"),
    ("string attribute", {"label": np.array(list("abcde"))}, {}, "cannot be stored as LAS extra bytes"),
    ("scale 'abc'", {}, {"scale": "abc"}, "scale must be a positive number"),
    ("scale 0", {}, {"scale": 0.0}, "scale must be a positive number"),
    ("scale -0.01", {}, {"scale": -0.01}, "scale must be a positive number"),
    ("scale nan", {}, {"scale": float("nan")}, "scale must be a positive number"),
    ("scale of 2 values", {}, {"scale": [0.01, 0.01]}, "scale must be a positive number"),
    ("scale True", {}, {"scale": True}, "scale must be a positive number"),
    ("scale too fine", {}, {"scale": 1e-9}, "choose a coarser scale"),
    ("chunk_size 0", {}, {"chunk_size": 0}, "chunk_size must be a whole number >= 1, got 0"),
    ("chunk_size -3", {}, {"chunk_size": -3}, "chunk_size must be a whole number >= 1"),
    ("chunk_size 2.5", {}, {"chunk_size": 2.5}, "chunk_size must be a whole number >= 1, got 2.5"),
    ("chunk_size '10'", {}, {"chunk_size": "10"}, "chunk_size must be a whole number >= 1"),
    ("chunk_size None", {}, {"chunk_size": None}, "chunk_size must be a whole number >= 1"),
    ("point_format 11", {}, {"point_format": 11}, "point_format must be 0..10"),
]


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("attrs, kwargs, fragment", [c[1:] for c in WRITE_CASES], ids=[c[0] for c in WRITE_CASES])
def test_write_refuses_values_that_do_not_fit(tmp_path, suffix, attrs, kwargs, fragment):
    out = tmp_path / f"out{suffix}"
    out.write_bytes(b"previous content")
    with pytest.raises(LabkitError) as err:
        write_cloud(_cloud(**attrs), out, **kwargs)
    assert fragment in str(err.value)
    assert out.read_bytes() == b"previous content"  # atomic: the old file stays, no temporary is left
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


@pytest.mark.parametrize("values, dtype", [
    (np.array([0, 65535, 7, 8, 9]), np.uint16),  # the whole uint16 range, from int64
    (np.array([0.0, 65535.0, 7, 8, 9]), np.uint16),  # whole floats are fine
])
def test_write_keeps_values_at_the_limits(tmp_path, values, dtype):
    path = write_cloud(_cloud(intensity=values), tmp_path / "ok.las")
    got = np.asarray(laspy.read(str(path)).intensity)
    np.testing.assert_array_equal(got, values.astype(dtype))


@pytest.mark.parametrize("path, fragment", [
    (None, "needs a file path (str or Path), got None"),
    ("", "needs a file path (str or Path), got ''"),
    (42, "needs a file path (str or Path), got 42"),
])
def test_write_bad_paths(path, fragment):
    with pytest.raises(CloudFileError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        write_cloud(_cloud(), path)


def test_write_needs_a_point_cloud(tmp_path):
    with pytest.raises(LabkitError, match="needs a PointCloud, got ndarray"):
        write_cloud(np.zeros((3, 3)), tmp_path / "a.las")


@pytest.mark.parametrize("name", ["units", "crs", "x"])
def test_npz_reserved_attribute_names(tmp_path, name):
    with pytest.raises(LabkitError, match=f"attribute name\\(s\\) \\['{name}'\\] are reserved"):
        write_cloud(_cloud(**{name: np.arange(5.0)}), tmp_path / "a.npz")
    assert list(tmp_path.iterdir()) == []


def test_write_unknown_suffix_and_missing_folder(tmp_path):
    with pytest.raises(CloudFileError, match="unsupported point-cloud format '.foo'"):
        write_cloud(_cloud(), tmp_path / "a.foo")
    with pytest.raises(CloudFileError, match="does not exist"):
        write_cloud(_cloud(), tmp_path / "nope" / "a.las")


# ============================================================================ read_cloud: paths and arguments
@pytest.mark.parametrize("path, error, fragment", [
    (None, CloudFileError, "file path (str or Path) is needed, got NoneType"),
    ("", CloudFileError, "got an empty string"),
    (3.5, CloudFileError, "got float"),
    ("/no/such/file.las", CloudFileError, "point-cloud file not found"),
])
def test_read_bad_paths(path, error, fragment):
    with pytest.raises(error) as err:
        read_cloud(path)
    assert fragment in str(err.value)


@pytest.fixture
def small_las(tmp_path):
    las = laspy.create(point_format=3, file_version="1.2")
    las.x, las.y, las.z = np.arange(10.0), np.arange(10.0) * 2, np.zeros(10)
    las.intensity = np.arange(10, dtype=np.uint16) * 100
    las.classification = np.full(10, 2, np.uint8)
    path = tmp_path / "small.las"
    las.write(str(path))
    return path


@pytest.mark.parametrize("kwargs, fragment", [
    ({"chunk_size": 0}, "chunk_size must be a whole number >= 1, got 0"),
    ({"chunk_size": 2.5}, "chunk_size must be a whole number >= 1, got 2.5"),
    ({"chunk_size": "x"}, "chunk_size must be a whole number >= 1, got 'x'"),
    ({"chunk_size": True}, "chunk_size must be a whole number >= 1, got True"),
    ({"attributes": ["nope"]}, "has no attribute nope"),
    ({"attributes": 5}, "attributes must be a name or a sequence of names, got 5"),
    ({"attributes": [1, 2]}, "attributes must be names (str), got 1"),
    ({"units": "feet"}, "units must be one of 'm', 'native'; got 'feet'"),
])
def test_read_bad_arguments(small_las, kwargs, fragment):
    with pytest.raises(LabkitError) as err:
        read_cloud(small_las, **kwargs)
    assert fragment in str(err.value)


def test_attributes_as_one_name(small_las):
    cloud = read_cloud(small_las, attributes="intensity")
    assert list(cloud.attributes) == ["intensity"]
    np.testing.assert_array_equal(cloud["intensity"], np.arange(10) * 100)


def test_whole_float_chunk_size_is_accepted(small_las):
    assert len(read_cloud(small_las, chunk_size=3.0)) == 10


# ============================================================================ corrupt LAS headers
def _patched(small_las, offset, fmt, values):
    raw = bytearray(small_las.read_bytes())
    struct.pack_into(fmt, raw, offset, *values)
    small_las.write_bytes(bytes(raw))
    return small_las


@pytest.mark.parametrize("offset, fmt, values, fragment", [
    (131, "<3d", (0.0, 0.01, 0.01), "scale factors [0.0, 0.01, 0.01]"),
    (131, "<3d", (0.01, 0.01, 0.0), "each must be a finite number other than 0"),
    (131, "<3d", (float("nan"), 0.01, 0.01), "scale factors [nan"),
    (131, "<3d", (float("inf"), 0.01, 0.01), "scale factors [inf"),
    (155, "<3d", (float("inf"), 0.0, 0.0), "offsets [inf, 0.0, 0.0] are not finite"),
    (24, "<BB", (2, 0), "LAS version 2.0"),
    (104, "<B", (12,), "point format 12"),
    (100, "<I", (10**6,), "VLRs announced"),
])
def test_corrupt_las_headers(small_las, offset, fmt, values, fragment):
    path = _patched(small_las, offset, fmt, values)
    with pytest.raises(CloudFileError) as err:
        read_cloud(path)
    assert fragment in str(err.value) and str(path) in str(err.value)


# ============================================================================ text files
def test_real_pdal_csv_with_fractional_scan_angles():
    """PDAL writes LAS 1.4 scan angles as degrees (-15.996): read as scan_angle in 0.006-degree units,
    equal to the field stored in the LAS file the CSV was exported from."""
    csv = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-largersample.txt", units="native")
    las = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-2010.las", units="native")
    assert len(csv) == 103 and csv["scan_angle"].dtype == np.int16
    from scipy.spatial import cKDTree

    d, idx = cKDTree(las.xyz).query(csv.xyz)
    same = d < 1e-6  # cores taken from the 2010 epoch
    assert same.sum() > 50
    np.testing.assert_array_equal(csv["scan_angle"][same], las["scan_angle"][idx[same]])
    np.testing.assert_array_equal(csv["intensity"][same], las["intensity"][idx[same]])
    assert csv["scanner_channel"].dtype == np.uint8 and "edge_of_flight_line" in csv


@pytest.mark.parametrize("asked", ["scan_angle_rank", "scan_angle", ["scan_angle", "intensity"]])
def test_pdal_scan_angle_answers_to_its_names(asked):
    cloud = read_cloud(DATA_REAL / "epochs" / "autzen-bmx-largersample.txt", attributes=asked, units="native")
    assert "scan_angle" in cloud and set(cloud.attributes) <= {"scan_angle", "intensity"}
    assert cloud["scan_angle"].min() == -2666  # -15.996 degrees


@pytest.mark.parametrize("column, values, name, expected", [
    ("ScanAngleRank", ["-15.996", "-15.000", "3.000"], "scan_angle", np.array([-2666, -2500, 500], np.int16)),
    ("ScanAngleRank", ["-15", "2", "3"], "scan_angle_rank", np.array([-15, 2, 3], np.int8)),
    ("ScanAngleRank", ["1.0001", "2", "3"], "scan_angle_degrees", np.array([1.0001, 2.0, 3.0])),
    ("Intensity", ["1", "65535", "0"], "intensity", np.array([1, 65535, 0], np.uint16)),
    ("Deviation", ["-15.996", "2", "3"], "deviation", np.array([-15.996, 2.0, 3.0])),
    ("Reflectance", ["-3", "2", "3"], "reflectance", np.array([-3, 2, 3], np.int64)),
])
def test_text_columns_are_read_right(tmp_path, column, values, name, expected):
    path = tmp_path / "t.csv"
    rows = [f"{i}.5,{i}.25,1.0,{v}" for i, v in enumerate(values)]
    path.write_text(f'"X","Y","Z","{column}"\n' + "\n".join(rows) + "\n")
    got = read_cloud(path)[name]
    assert got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("column, value, fragment", [
    ("Intensity", "-1", "column 'intensity' must hold integers in 0..65535"),
    ("Classification", "2.5", "column 'classification' must hold integers in 0..255"),
    ("ScanAngleRank", "400", "column 'scan_angle_rank' must hold integers in -128..127"),
])
def test_text_columns_that_do_not_fit(tmp_path, column, value, fragment):
    path = tmp_path / "t.csv"
    path.write_text(f"x,y,z,{column}\n0,0,0,1\n1,1,1,{value}\n")
    with pytest.raises(CloudFileError, match=fragment):
        read_cloud(path)


# ============================================================================ PLY
_PLY_HEAD = "ply\nformat {fmt} 1.0\nelement vertex {n}\n{props}end_header\n"
_XYZ = "property float x\nproperty float y\nproperty float z\n"


@pytest.mark.parametrize("content, fragment", [
    (b"plx\nformat ascii 1.0\n", "is not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\n" + _XYZ.encode(), "has no 'end_header' line"),
    (b"ply\nformat bogus 1.0\nend_header\n", "unknown PLY format 'bogus'"),
    (b"ply\nelement vertex 1\n" + _XYZ.encode() + b"end_header\n0 0 0\n", "has no 'format' line"),
    (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n",
     "has no 'vertex' element"),
    (_PLY_HEAD.format(fmt="ascii", n=1, props="property float x\nproperty float y\n").encode() + b"0 0\n",
     "has no property z"),
    (_PLY_HEAD.format(fmt="ascii", n=3, props=_XYZ).encode() + b"0 0 0\n1 1 1\n", "is truncated: the PLY header announces 3 vertices, the file holds 2"),
    (_PLY_HEAD.format(fmt="binary_little_endian", n=3, props=_XYZ).encode() + b"\x00" * 30,
     "is truncated: the PLY header announces 3 vertices"),
    (_PLY_HEAD.format(fmt="ascii", n=1, props=_XYZ + "property list uchar int idx\n").encode() + b"0 0 0 1 5\n",
     "list properties in the PLY vertex element are not supported"),
    (_PLY_HEAD.format(fmt="ascii", n=1, props=_XYZ + "property quad w\n").encode() + b"0 0 0 1\n",
     "cannot read the PLY property line"),
    (_PLY_HEAD.format(fmt="ascii", n=2, props=_XYZ).encode() + b"0 0 0\n1 1\n", "cannot parse lines 1-2"),
    (_PLY_HEAD.format(fmt="ascii", n=1, props=_XYZ + "property float X\n").encode() + b"0 0 0 1\n",
     "repeats a property"),
])
def test_bad_ply_files(tmp_path, content, fragment):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(CloudFileError) as err:
        read_cloud(path)
    assert fragment in str(err.value)


def test_ply_with_an_element_before_the_vertices(tmp_path):
    head = ("ply\nformat binary_little_endian 1.0\nelement camera 1\nproperty float cx\nproperty float cy\n"
            "element vertex 2\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nend_header\n")
    cam = np.array([7.0, 8.0], "<f4").tobytes()
    rec = np.array([(1.0, 2.0, 3.0, 200), (4.0, 5.0, 6.0, 17)], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1")])
    path = tmp_path / "cam.ply"
    path.write_bytes(head.encode() + cam + rec.tobytes())
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud["red"], [200, 17])


# ============================================================================ units: degrees and feet
def test_degrees_refused_on_reading_by_default():
    with pytest.raises(UnitsError, match="is in degrees of longitude/latitude.*reproject it"):
        read_cloud(DATA_REAL / "als" / "epsg_4326.las")


@pytest.mark.parametrize("step", ["normals", "icp", "ransac_sphere", "cloud_to_cloud", "local_noise"])
@pytest.mark.parametrize("file, fragment", [
    ("als/epsg_4326.las", "degrees of longitude/latitude"),
    ("als/interesting.las", "has coordinates in ft"),
    ("epochs/autzen-bmx-2010.las", "has coordinates in m (x, y), ftUS (z)"),
])
def test_metric_steps_refuse_clouds_in_degrees_or_native_feet(step, file, fragment):
    import labkit
    from labkit.features import normals

    cloud = read_cloud(DATA_REAL / file, units="native")
    calls = {
        "normals": lambda: normals(cloud, k=8),
        "icp": lambda: labkit.icp(cloud, cloud),
        "ransac_sphere": lambda: labkit.ransac_sphere(cloud, 0.05, rng=1),
        "cloud_to_cloud": lambda: labkit.cloud_to_cloud(cloud, cloud),
        "local_noise": lambda: labkit.local_noise(cloud, k=8),
    }
    with pytest.raises(UnitsError) as err:
        calls[step]()
    assert fragment in str(err.value)


def test_a_cloud_made_with_a_geographic_crs_is_refused_too():
    from labkit.features import normals

    cloud = PointCloud(np.random.default_rng(0).uniform(0, 1, (50, 3)), crs="EPSG:4326")
    with pytest.raises(UnitsError, match="degrees"):
        normals(cloud, k=8)
    normals(cloud.xyz, k=8)  # a bare array carries no units: the caller's responsibility


def test_feet_converted_by_default_then_metric_steps_accept(tmp_path):
    from labkit.features import normals

    cloud = read_cloud(DATA_REAL / "als" / "4_6_crop_every24.las")
    assert cloud.units.converted and cloud.units.is_metric
    assert normals(cloud, k=8).shape == (len(cloud), 3)


def test_merge_refuses_mixed_units():
    a = read_cloud(DATA_REAL / "als" / "interesting.las")
    b = read_cloud(DATA_REAL / "als" / "interesting.las", units="native")
    with pytest.raises(LabkitError, match=r"cannot merge clouds in different units: \['ft', 'm'\]"):
        regions.merge(a, b)


def test_copy_of_a_read_only_file_reads(tmp_path):
    """The shipped real files are stored read-only in some checkouts: reading never needs write access."""
    src = tmp_path / "ro.las"
    shutil.copy(DATA_REAL / "als" / "interesting.las", src)
    src.chmod(0o444)
    assert len(read_cloud(src)) == 1065


@pytest.mark.parametrize("keys, error, fragment", [
    ([(1024, 1), (3076, 9099)], UnitsError, "cannot convert unit code 9099 to metres"),
    ([(1024, 2), (2054, 9104)], UnitsError, "is in longitude/latitude (angle unit code 9104)"),
    ([(1024, 1), (3076, 9001), (4099, 9099)], UnitsError, "cannot convert m (x, y), unit code 9099 (z) to metres"),
])
def test_stated_but_unknown_units_are_never_taken_for_metres(tmp_path, keys, error, fragment):
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct

    las = laspy.create(point_format=1, file_version="1.2")
    las.x, las.y, las.z = [1.0, 2.0], [3.0, 4.0], [5.0, 6.0]
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys = [GeoKeyEntryStruct(k, 0, 1, v) for k, v in keys]
    vlr.geo_keys_header.number_of_keys = len(keys)
    las.header.vlrs.append(vlr)
    path = tmp_path / "odd.las"
    las.write(str(path))
    with pytest.raises(error) as err:
        read_cloud(path)
    assert fragment in str(err.value)
    native = read_cloud(path, units="native")
    with pytest.raises(UnitsError):
        native.require_metric()
