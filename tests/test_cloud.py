"""PointCloud construction (labkit.cloud): the CRS, the attributes and the name are checked; a wrong type gives a
LabkitError, never a raw TypeError or a silently dropped imaginary part."""

import numpy as np
import pyproj
import pytest

from labkit.cloud import PointCloud
from labkit.core.errors import LabkitError

XYZ = np.zeros((2, 3))


@pytest.mark.parametrize("crs, expected", [
    (4326, "EPSG:4326"), (25832, "EPSG:25832"), (np.int64(2154), "EPSG:2154"), ("EPSG:32632", "EPSG:32632"),
    ("  EPSG:32632 ", "EPSG:32632"), ("", None), (None, None), (pyproj.CRS.from_epsg(25833), "EPSG:25833"),
])
def test_crs_forms_accepted(crs, expected):
    assert PointCloud(XYZ, crs=crs).crs == expected


def test_a_pyproj_crs_without_code_is_kept_as_wkt():
    custom = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=9.5 +k=1 +x_0=500000 +y_0=0 +ellps=GRS80 +units=m")
    cloud = PointCloud(XYZ, crs=custom)
    assert cloud.crs.startswith(("PROJCRS", "PROJCS")) and cloud.units.horizontal == "metre"


@pytest.mark.parametrize("crs, fragment", [
    (4326.0, "got float"), (-5, "not an EPSG code"), (12, "not an EPSG code"), (True, "got bool"),
    (["EPSG:4326"], "got list"), ({"epsg": 4326}, "got dict"), (b"EPSG:4326", "got bytes"),
])
def test_crs_of_a_wrong_type_refused(crs, fragment):
    with pytest.raises(LabkitError, match=fragment):
        PointCloud(XYZ, crs=crs)


@pytest.mark.parametrize("attributes, fragment", [
    ([1, 2], "must be a dict"), ((("a", [1, 2]),), "must be a dict"), ("intensity", "must be a dict"),
    (np.array([1, 2]), "must be a dict"), ({1: [1, 2]}, "non-empty str"), ({"": [1, 2]}, "non-empty str"),
    ({"a": [1, 2, 3]}, "expected one per point"), ({"a": np.array([1j, 2j])}, "complex"),
])
def test_attributes_of_a_wrong_form_refused(attributes, fragment):
    with pytest.raises(LabkitError, match=fragment):
        PointCloud(XYZ, attributes)


@pytest.mark.parametrize("name", [3, 1.5, ["a"], b"name"])
def test_name_must_be_text(name):
    with pytest.raises(LabkitError, match="name must be a str"):
        PointCloud(XYZ, name=name)


@pytest.mark.parametrize("xyz", [np.zeros((2, 3), dtype=complex), [[0j, 0, 0]], np.array([[1 + 1e-30j, 0, 0]])])
def test_complex_coordinates_refused(xyz):
    with pytest.raises(LabkitError, match="complex"):
        PointCloud(xyz)
