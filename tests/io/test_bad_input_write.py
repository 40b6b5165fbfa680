"""Data kept (labkit.io.write, labkit.io.las_layout, the register command): a cloud labkit moves or writes keeps
the LAS version, point format, every standard and extra dimension, the VLRs, offsets and the scale of its file;
only the coordinates change; a LAZ writer error is one CloudFileError and keeps the old file."""

import laspy
import pyproj
import numpy as np
import pytest

from labkit.cli.main import main
from labkit.cloud import PointCloud
from labkit.core.errors import CloudFileError
from labkit.io import read_cloud, write_cloud

ORIGIN = np.array([500_000.25, 5_400_000.5, 100.0])


def _las(path, version="1.3", point_format=1, scale=0.00025, n=3000, seed=0, crs=25832, extra=True, shift=(0, 0, 0)):
    """A LAS/LAZ file with random values in every dimension (and three kinds of extra bytes)."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales, header.offsets = [scale] * 3, ORIGIN
    if extra:
        header.add_extra_dim(laspy.ExtraBytesParams("deviation", "u2"))
        header.add_extra_dim(laspy.ExtraBytesParams("amplitude", "f4"))
        header.add_extra_dim(laspy.ExtraBytesParams("reflect", "i4", scales=np.array([0.01]), offsets=np.array([5.0])))
    las = laspy.LasData(header)
    # a gently curved surface with structure in x, y and z, so that ICP is determined in all three shifts
    xy = rng.uniform(0, 30, (n, 2))
    z = 0.3 * np.sin(xy[:, 0] / 3) + 0.2 * np.cos(xy[:, 1] / 2.5) + 0.02 * xy[:, 0]
    xyz = ORIGIN + np.c_[xy, z] + np.asarray(shift)
    las.x, las.y, las.z = xyz.T
    for dim in las.point_format.dimensions:
        if dim.name in ("X", "Y", "Z") or dim.name in las.point_format.extra_dimension_names:
            continue
        if dim.kind.name == "BitField":
            las[dim.name] = rng.integers(0, 2 ** dim.num_bits, n)
        elif dim.kind.name == "FloatingPoint":
            las[dim.name] = rng.uniform(0, 1e5, n)
        elif dim.kind.name in ("SignedInteger", "UnsignedInteger") and dim.num_elements == 1:
            info = np.iinfo(dim.dtype)
            las[dim.name] = rng.integers(max(info.min, -100), min(info.max, 30000), n)
    if "wavepacket_offset" in las.point_format.dimension_names:  # packets one after the other, as a scanner writes them
        las.wavepacket_size, las.wavepacket_index = np.full(n, 256), np.ones(n, dtype=np.uint8)
        las.wavepacket_offset = 60 + 256 * np.arange(n)
        las.scanner_channel = np.zeros(n, dtype=np.uint8)  # lazrs 0.6 mixes up wave packets across channels
    if extra:
        las.deviation = rng.integers(0, 1000, n)
        las.amplitude = rng.normal(size=n).astype("f4")
        las.reflect = np.round(rng.uniform(0, 10, n), 2)
    if crs is not None:
        las.header.add_crs(pyproj.CRS.from_epsg(crs))
    las.write(path)
    return path


def _same_except_xyz(a, b):
    assert (a.header.version.major, a.header.version.minor) == (b.header.version.major, b.header.version.minor)
    assert a.header.point_format.id == b.header.point_format.id
    assert list(a.point_format.dimension_names) == list(b.point_format.dimension_names)
    for dim in a.point_format.dimension_names:
        if dim not in ("X", "Y", "Z"):
            np.testing.assert_array_equal(np.asarray(a[dim]), np.asarray(b[dim]), err_msg=dim)
    assert [type(v).__name__ for v in a.header.vlrs] == [type(v).__name__ for v in b.header.vlrs]
    assert (np.asarray(b.header.scales) <= np.asarray(a.header.scales)).all()


def test_register_keeps_every_dimension_and_the_scale(tmp_path):
    """labkit register of a LAS 1.3 file with extra bytes at 0.25 mm: only the coordinates change."""
    src = _las(tmp_path / "src.las", shift=(0.05, -0.03, 0.02))
    tgt = _las(tmp_path / "tgt.las", seed=1)
    assert main(["register", str(src), str(tgt), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    a, b = laspy.read(src), laspy.read(tmp_path / "out" / "src_registered.las")
    _same_except_xyz(a, b)
    assert b.header.offsets.tolist() == a.header.offsets.tolist()
    # the coordinates: the input transformed by the printed 4x4, to within half the input's scale
    moved = b.xyz - a.xyz
    assert np.abs(moved.mean(axis=0) - [-0.05, 0.03, -0.02]).max() < 0.01  # ICP found the shift
    rest = moved - moved.mean(axis=0)  # a translation (dof default): the same shift for every point
    assert np.abs(rest).max() <= 0.5 * 0.00025 + 1e-9


@pytest.mark.parametrize("version, point_format", [
    ("1.1", 0), ("1.1", 1), ("1.2", 2), ("1.2", 3), ("1.3", 4), ("1.3", 5),
    ("1.4", 6), ("1.4", 7), ("1.4", 8), ("1.4", 9), ("1.4", 10),
])
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_write_back_keeps_the_layout(tmp_path, version, point_format, suffix):
    src = _las(tmp_path / f"in{suffix}", version=version, point_format=point_format, n=300)
    cloud = read_cloud(src)
    shift = np.array([0.123456789, -2.5, 0.0000625])
    out = write_cloud(cloud.with_xyz(cloud.xyz + shift), tmp_path / f"out{suffix}")
    a, b = laspy.read(src), laspy.read(out)
    _same_except_xyz(a, b)
    assert np.abs(b.xyz - (a.xyz + shift)).max() <= 0.5 * 0.00025 + 1e-9
    assert read_cloud(out).crs == cloud.crs
    assert pyproj.CRS(cloud.crs).to_epsg() == 25832


@pytest.mark.parametrize("scale", [0.01, 0.001, 0.00025, 1e-5])
def test_write_cloud_takes_the_input_scale_by_default(tmp_path, scale):
    src = _las(tmp_path / "in.las", scale=scale, n=200, extra=False)
    out = write_cloud(read_cloud(src), tmp_path / "out.las")
    a, b = laspy.read(src), laspy.read(out)
    np.testing.assert_array_equal(np.asarray(b.header.scales), [scale] * 3)
    np.testing.assert_array_equal(a.X, b.X)  # bit for bit: nothing rounded
    np.testing.assert_array_equal(a.Z, b.Z)


@pytest.mark.parametrize("change", ["drop_extra", "add_extra", "subset", "new_crs", "no_crs"])
def test_layout_follows_the_cloud(tmp_path, change):
    """Attributes dropped or added, points selected, another CRS: the file says what the cloud holds."""
    cloud = read_cloud(_las(tmp_path / "in.las", n=200))
    if change == "drop_extra":
        cloud = PointCloud(cloud.xyz, {k: v for k, v in cloud.attributes.items() if k != "deviation"},
                           crs=cloud.crs, layout=cloud.layout)
    elif change == "add_extra":
        cloud = cloud.with_attributes(height=np.arange(len(cloud), dtype=np.float32))
    elif change == "subset":
        cloud = cloud.subset(np.arange(len(cloud)) % 3 == 0)
    elif change == "new_crs":
        cloud = PointCloud(cloud.xyz, cloud.attributes, crs="EPSG:25833", layout=cloud.layout)
    else:
        cloud = PointCloud(cloud.xyz, cloud.attributes, crs=None, layout=cloud.layout)
    back = read_cloud(write_cloud(cloud, tmp_path / "out.las"))
    assert set(back.attributes) == set(cloud.attributes)
    for k in cloud.attributes:
        np.testing.assert_allclose(back[k], cloud[k], atol=0.006)
    assert back.crs == cloud.crs
    assert back.layout.version == "1.3" and back.layout.point_format == 1


def test_explicit_point_format_overrides_the_layout(tmp_path):
    cloud = read_cloud(_las(tmp_path / "in.las", n=100))
    b = laspy.read(write_cloud(cloud, tmp_path / "out.las", point_format=6))
    assert b.header.point_format.id == 6 and b.header.version.minor == 4
    np.testing.assert_array_equal(b.deviation, cloud["deviation"])


def test_feet_cloud_written_back_in_feet_at_its_scale(tmp_path):
    src = _las(tmp_path / "in.las", n=100, crs=2277, extra=False)  # NAD83 / Texas Central (ftUS)
    cloud = read_cloud(src)
    assert cloud.units.converted and cloud.units.horizontal == "US survey foot"
    out = write_cloud(cloud, tmp_path / "out.las")
    a, b = laspy.read(src), laspy.read(out)
    np.testing.assert_array_equal(a.X, b.X)
    np.testing.assert_array_equal(a.Y, b.Y)


@pytest.mark.parametrize("name", ["als/append-bug.laz", "als/fullwave.laz", "als/4_6_crop.las", "als/interesting.las",
                                  "als/file_with_both_wkt_and_geotiff_vlrs.las", "epochs/autzen-bmx-2010.las",
                                  "dim/pybathysfm_sample_sfm_epsg27700.laz", "tls/vegetation_1_3.las"])
def test_real_files_are_written_back_bit_for_bit(realdata, tmp_path, name):
    """Feet converted on reading and back on writing, RIEGL extra bytes, point format 10, WKT and GeoKeys:
    read_cloud then write_cloud gives every dimension, X/Y/Z integers included, and the VLRs back."""
    src = realdata / name
    cloud = read_cloud(src)
    out = write_cloud(cloud, tmp_path / src.name)
    a, b = laspy.read(src), laspy.read(out)
    _same_except_xyz(a, b)
    for dim in ("X", "Y", "Z"):
        np.testing.assert_array_equal(np.asarray(a[dim]), np.asarray(b[dim]))
    assert read_cloud(out).crs == cloud.crs


@pytest.mark.parametrize("error", ["LazrsError", "RuntimeError", "ValueError"])
def test_a_laz_writer_error_is_a_labkit_error_and_keeps_the_old_file(tmp_path, monkeypatch, error):
    """A full disk makes lazrs raise its own error (not an OSError): reported in one LabkitError."""
    path = write_cloud(PointCloud(np.zeros((5, 3))), tmp_path / "keep.laz")
    before = path.read_bytes()
    kind = type(error, (Exception,), {})

    def full(*args, **kwargs):
        raise kind("No space left on device (os error 28)")

    monkeypatch.setattr(laspy.LasWriter, "write_points", full)
    with pytest.raises(CloudFileError, match=f"{error}: No space left"):
        write_cloud(PointCloud(np.ones((7, 3))), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.laz"]
