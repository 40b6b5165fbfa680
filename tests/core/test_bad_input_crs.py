"""Coordinate reference systems (labkit.core.units, labkit.core.crs and the two-cloud entry points): units from EPSG codes,
WKT and GeoKeys alike through pyproj; geographic CRS recognised; two inputs in different CRS refused everywhere with
an error naming both; a CRS on one side only noted."""

import warnings

import laspy
import numpy as np
import pyproj
import pytest

import labkit
from labkit.core.crs import same_crs
from labkit.core.units import units_from_crs_text, units_from_wkt
from labkit.change.m3c2 import m3c2
from labkit.cli.main import main
from labkit.cloud import PointCloud
from labkit.core.units import UnitsError
from labkit.core.errors import CrsMismatchError, CrsNote
from labkit.io import read_cloud

US_FT, FT = 1200.0 / 3937.0, 0.3048  # metres per US survey foot / international foot (definitions)

# EPSG code -> unit of X/Y as its EPSG name says ("(ftUS)", "(ft)", UTM/Lambert grids in metres, lon/lat)
CODES = {
    2277: "US survey foot", 2903: "US survey foot", 2263: "US survey foot", 6539: "US survey foot",
    2994: "foot",
    32632: "metre", 25832: "metre", 27700: "metre", 2154: "metre", 3857: "metre", 26912: "metre",
    32104: "metre", 2180: "metre", 31467: "metre",
    4326: "degree", 4258: "degree", 4979: "degree",
}
FACTOR = {"US survey foot": US_FT, "foot": FT, "metre": 1.0}


@pytest.mark.parametrize("code", sorted(CODES))
def test_units_of_an_epsg_code(code):
    u = units_from_crs_text(f"EPSG:{code}")
    assert u.horizontal == CODES[code]
    if CODES[code] == "degree":
        assert u.angular and u.horizontal_to_metre is None
    else:
        assert u.horizontal_to_metre == FACTOR[CODES[code]]
        assert u.vertical == CODES[code]  # not stated: taken equal to X/Y (with a note)
        assert "taken equal" in u.note


@pytest.mark.parametrize("code", sorted(CODES))
@pytest.mark.parametrize("version", ["WKT1_GDAL", "WKT2_2019", "WKT1_ESRI"])
def test_the_same_crs_as_wkt_has_the_same_units(code, version):
    try:
        wkt = pyproj.CRS.from_epsg(code).to_wkt(version)
    except pyproj.exceptions.CRSError:
        pytest.skip(f"WKT {version} cannot express EPSG:{code}")
    h, _ = units_from_wkt(wkt)
    assert h[0] == CODES[code]
    assert PointCloud(np.zeros((1, 3)), crs=wkt).units.horizontal == CODES[code]


@pytest.mark.parametrize("text, h, v", [
    ("EPSG:2277+6360", "US survey foot", "US survey foot"),  # Texas Central ftUS + NAVD88 height (ftUS)
    ("EPSG:25832+5783", "metre", "metre"),  # ETRS89 / UTM 32N + DHHN92
    ("EPSG:6318+5703", "degree", "metre"),  # NAD83(2011) lon/lat + NAVD88 height (m)
    ("EPSG:32104+6360", "metre", "US survey foot"),  # Nebraska (m) + NAVD88 height (ftUS), as the Autzen epochs
])
def test_compound_epsg_codes(text, h, v):
    u = units_from_crs_text(text)
    assert (u.horizontal, u.vertical) == (h, v)


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:4258", "EPSG:4979", pyproj.CRS.from_epsg(4326).to_wkt(),
                                 pyproj.CRS.from_epsg(4258).to_wkt("WKT1_GDAL")])
def test_geographic_crs_recognised_and_refused_by_metric_steps(crs):
    cloud = PointCloud(np.random.default_rng(0).uniform(0, 1, (50, 3)), crs=crs)
    assert cloud.units.angular
    with pytest.raises(UnitsError, match="longitude/latitude"):
        cloud.require_metric()
    with pytest.raises(UnitsError, match="longitude/latitude"):
        labkit.local_pca(cloud)


@pytest.mark.parametrize("crs", ["EPSG:2277", pyproj.CRS.from_epsg(2277).to_wkt()])
def test_us_feet_given_as_code_or_wkt_alike(crs):
    """A cloud in US survey feet (by code or WKT) is refused by metric steps in both spellings."""
    cloud = PointCloud(np.random.default_rng(0).uniform(0, 1, (50, 3)), crs=crs)
    assert cloud.units.horizontal_to_metre == US_FT
    with pytest.raises(UnitsError, match="ftUS"):
        cloud.require_metric()


# ---------------------------------------------------------------------------- two clouds, two CRS
def _surface(n=600, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 20, (n, 2))
    return np.c_[xy, 0.4 * np.sin(xy[:, 0] / 2) + 0.3 * np.cos(xy[:, 1] / 3)]


ENTRIES = {
    "icp": lambda a, b: labkit.icp(a, b),
    "max_consensus": lambda a, b: labkit.max_consensus(a, b, extent=0.2),
    "cloud_to_cloud": lambda a, b: labkit.cloud_to_cloud(a, b),
    "point_to_plane_distance": lambda a, b: labkit.point_to_plane_distance(a, b),
    "m3c2": lambda a, b: m3c2(a, b, [[10.0, 10.0, 0.0]], normal_radius=2.0, cylinder_radius=1.0, max_depth=1.0),
    "register_tiles": lambda a, b: labkit.register_tiles(a, b, size=50.0, scheduler="serial", progress=False),
}
# ETRS89 zones 32/33; ETRS89 vs WGS 84 in one zone; ETRS89/UTM vs the German national grid (Gauss-Krueger)
PAIRS = [("EPSG:25832", "EPSG:25833"), ("EPSG:25832", "EPSG:32632"), ("EPSG:25832", "EPSG:31467")]


@pytest.mark.parametrize("a, b", PAIRS)
@pytest.mark.parametrize("entry", sorted(ENTRIES))
def test_two_crs_refused_naming_both(entry, a, b):
    xyz = _surface()
    src, tgt = PointCloud(xyz, crs=a), PointCloud(xyz + [0, 0, 0.01], crs=b)
    name_a, name_b = pyproj.CRS(a).name, pyproj.CRS(b).name
    with pytest.raises(CrsMismatchError) as info:
        ENTRIES[entry](src, tgt)
    assert name_a in str(info.value) and name_b in str(info.value)


@pytest.mark.slow
@pytest.mark.parametrize("entry", sorted(ENTRIES))
@pytest.mark.parametrize("side", ["source", "target"])
def test_a_crs_on_one_side_only_is_noted(entry, side):
    xyz = _surface()
    with_crs, without = PointCloud(xyz, crs="EPSG:25832"), PointCloud(xyz + [0, 0, 0.01])
    a, b = (with_crs, without) if side == "source" else (without, with_crs)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ENTRIES[entry](a, b)
    notes = [str(w.message) for w in caught if issubclass(w.category, CrsNote)]
    assert notes and "states no CRS" in notes[0] and "ETRS89 / UTM zone 32N" in notes[0]


@pytest.mark.parametrize("b", ["EPSG:25832", pyproj.CRS.from_epsg(25832).to_wkt(),
                               pyproj.CRS.from_epsg(25832).to_wkt("WKT1_GDAL"),
                               pyproj.CRS.from_epsg(25832).to_wkt("WKT1_ESRI"), "EPSG:25832+5783"])
def test_one_crs_in_other_spellings_is_accepted(b):
    assert same_crs("EPSG:25832", b)
    xyz = _surface()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even a note
        d = labkit.cloud_to_cloud(PointCloud(xyz, crs="EPSG:25832"), PointCloud(xyz, crs=b))
    assert np.all(d == 0)


def _las(path, code, shift=0.0):
    las = laspy.create(point_format=1, file_version="1.2")
    xyz = _surface() + [500_000.0, 5_400_000.0, 100.0 + shift]
    las.header.offsets, las.header.scales = [500_000.0, 5_400_000.0, 0.0], [0.001] * 3
    las.x, las.y, las.z = xyz.T
    if code is not None:
        las.header.add_crs(pyproj.CRS.from_epsg(code))
    las.write(str(path))
    return str(path)


@pytest.mark.parametrize("command", ["register", "change"])
def test_the_commands_refuse_two_crs(tmp_path, capsys, command):
    a, b = _las(tmp_path / "a.las", 25832), _las(tmp_path / "b.las", 25833, 0.01)
    argv = [command, a, b, "--out", str(tmp_path / "out")]
    if command == "change":
        argv += ["--normal-radius", "2", "--cylinder-radius", "1", "--max-depth", "1"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "UTM zone 32N" in err and "UTM zone 33N" in err
    assert not (tmp_path / "out").exists()


def test_register_notes_a_file_without_crs(tmp_path, capsys):
    a, b = _las(tmp_path / "a.las", 25832), _las(tmp_path / "b.las", None, 0.01)
    assert main(["register", a, b, "--out", str(tmp_path / "out"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "states no CRS" in err


def test_read_keeps_a_feet_epsg_code_and_converts(tmp_path):
    path = _las(tmp_path / "ft.las", 2277)
    raw = laspy.read(path)
    cloud = read_cloud(path)
    assert cloud.units.converted and cloud.units.horizontal == "US survey foot"
    np.testing.assert_allclose(cloud.xyz[:, 0], np.asarray(raw.x) * US_FT, rtol=1e-15)


@pytest.mark.parametrize("a, b", [("LOCAL_CS[\"site A\"]", "LOCAL_CS[\"site B\"]"), ("garbage", "EPSG:25832")])
def test_crs_that_pyproj_cannot_read_are_noted_not_taken_for_equal(a, b):
    xyz = _surface()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        labkit.cloud_to_cloud(PointCloud(xyz, crs=a), PointCloud(xyz, crs=b))
    notes = [str(w.message) for w in caught if issubclass(w.category, CrsNote)]
    assert notes and "cannot be compared" in notes[0]


def test_register_tiles_compares_the_crs_of_files(tmp_path):
    a, b = _las(tmp_path / "a.las", 25832), _las(tmp_path / "b.las", 32632)
    with pytest.raises(CrsMismatchError, match="ETRS89 / UTM zone 32N.*WGS 84 / UTM zone 32N"):
        labkit.register_tiles(a, b, size=50.0, scheduler="serial", progress=False)
