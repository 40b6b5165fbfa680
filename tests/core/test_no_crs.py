"""An input without a CRS: the results and the files written from them say so (crs=None and a note),
not only a warning."""

import numpy as np
import pytest
import rasterio

from labkit import PointCloud, load_registration, m3c2, read_cloud, save_registration, write_cloud
from labkit.core.crs import NO_CRS
from labkit.io.geotiff import change_geotiff
from labkit.transforms import make_transform


def _epochs(tmp_path, crs):
    """Two LAS files of a plane 5 cm apart in UTM-sized coordinates, written with or without a CRS."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 6, (3000, 2)) + [500_000.0, 5_400_000.0]
    paths = []
    for name, dz in (("a", 0.0), ("b", 0.05)):
        xyz = np.c_[xy, 100.0 + dz + rng.normal(0, 0.005, len(xy))]
        paths.append(write_cloud(PointCloud(xyz, crs=crs), tmp_path / f"{name}.las"))
    return [read_cloud(p) for p in paths]


def _change(tmp_path, crs):
    ref, cmp_ = _epochs(tmp_path, crs)
    result = m3c2(ref, cmp_, ref.xyz[::300], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    tif = change_geotiff(result, tmp_path / "change.tif", crs=ref.crs, units=ref.units, extent=ref.bounds)
    with rasterio.open(tif) as ds:
        return ref, result, ds.crs, ds.tags()


def test_change_without_crs_carries_the_note(tmp_path):
    ref, result, tif_crs, tags = _change(tmp_path, None)
    assert ref.crs is None and result.crs is None
    assert NO_CRS in result.summary()
    assert np.nanmedian(result.distance) == pytest.approx(0.05, abs=0.005)  # the change itself is unaffected
    assert tif_crs is None and tags["CRS_NOTE"] == NO_CRS


def test_change_with_crs_names_it(tmp_path):
    ref, result, tif_crs, tags = _change(tmp_path, "EPSG:25832")
    assert result.crs == ref.crs == "EPSG:25832"
    assert "EPSG:25832" in result.summary() and NO_CRS not in result.summary()
    assert tif_crs.to_epsg() == 25832 and "CRS_NOTE" not in tags


@pytest.mark.parametrize("crs", [None, "EPSG:25832"])
def test_registration_file_states_its_crs(tmp_path, crs):
    path = save_registration(tmp_path / "r.json", matrix=make_transform(np.eye(3), [0.1, 0.0, 0.0]),
                             covariance=np.diag([4e-6, 4e-6, np.inf]), parameter_names=("tx", "ty", "tz"),
                             crs=crs, method="icp")
    back = load_registration(path)
    assert back.crs == crs
    text = back.summary()
    assert (NO_CRS in text) == (crs is None)
    assert "tz not determined" in text and "tx 2.0 mm" in text
