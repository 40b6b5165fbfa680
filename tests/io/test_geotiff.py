"""GeoTIFF deliverables (labkit.io.geotiff): a CRS PROJ only half knows is written without noise on stderr."""

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")

from labkit.change.m3c2 import m3c2  # noqa: E402
from labkit.io.geotiff import change_geotiff, geotiff_crs  # noqa: E402


def _result():
    g = np.arange(0.0, 4.0, 0.2)
    plane = np.c_[np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)]
    return m3c2(plane, plane + [0, 0, 0.1], [[2.0, 2.0, 0.0]], normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)


def test_unknown_vertical_part_is_a_warning_not_a_proj_line(tmp_path, capfd):
    """EPSG:2903+5103 (Oregon ft + NAVD88 ft, as in Autzen): PROJ knows no EPSG:5103; GDAL said so on stderr."""
    result = _result()
    capfd.readouterr()
    with pytest.warns(UserWarning, match="vertical part of EPSG:2903\\+5103 .* gets EPSG:2903"):
        path = change_geotiff(result, tmp_path / "c.tif", crs="EPSG:2903+5103")
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 2903
        assert np.isclose(ds.read(1)[np.isfinite(ds.read(1))], 0.1, atol=1e-3).all()


def test_a_crs_nobody_knows_is_one_clear_error(capfd):
    from labkit import LabkitError

    with pytest.raises(LabkitError, match="cannot write a GeoTIFF in the CRS 'EPSG:999999'"):
        geotiff_crs("EPSG:999999")
    assert capfd.readouterr().err == ""
