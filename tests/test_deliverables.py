"""From files to deliverables on real epochs: registration file, change with parameters from the data, GeoTIFFs.

Each written file is checked against the numbers it was made from: the GeoTIFF cells against the
core points of the LAS written beside it (binned here independently), its CRS against the input's
(pyproj), its bounds against the input's own coordinates (metres, or US survey feet).
"""

import re
from pathlib import Path

import numpy as np
import pytest

from labkit import load_registration, save_registration
from labkit.cli.main import main
from labkit.io.geotiff import STATUS_CODES
from labkit.io import read_cloud, write_cloud

pyproj = pytest.importorskip("pyproj")
rasterio = pytest.importorskip("rasterio")

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
pytestmark = pytest.mark.skipif(not (REAL / "epochs" / "autzen-bmx-2010.las").exists(), reason="data/real not shipped")


def _halves(name, folder):
    """Two epochs of one ground: the even and the odd points of a shipped ALS file, in its own units and CRS."""
    cloud = read_cloud(REAL / "als" / name, units="native")
    i = np.arange(len(cloud))
    stem = Path(name).stem
    return (write_cloud(cloud.subset(i % 2 == 0), folder / f"{stem}_a.las"),
            write_cloud(cloud.subset(i % 2 == 1), folder / f"{stem}_b.las"))


def _pixel(transform, x, y):
    """Column and row of the cell holding (x, y), from a north-up transform."""
    return (np.floor((np.asarray(x) - transform.c) / transform.a).astype(int),
            np.floor((np.asarray(y) - transform.f) / transform.e).astype(int))


def _check_change_geotiff(tif, las_path, source, capsys_out):
    """CRS, bounds and every cell of the change GeoTIFF against the input and the written core points."""
    native = read_cloud(source, units="native")
    with rasterio.open(tif) as ds:
        assert pyproj.CRS.from_wkt(ds.crs.to_wkt()).equals(pyproj.CRS.from_user_input(native.crs))
        lo, hi = native.xyz.min(axis=0), native.xyz.max(axis=0)  # the data in the file's own units
        b = ds.bounds
        assert b.left <= lo[0] and b.bottom <= lo[1] and b.right >= hi[0] and b.top >= hi[1]
        assert b.right - b.left < (hi[0] - lo[0]) + 2.01 * ds.res[0]  # and not much more
        assert ds.descriptions[0] == "distance (m)" and ds.tags()["VALUE_UNIT"] == "metre"
        bands = ds.read().astype(np.float64)
        transform = ds.transform
    cores = read_cloud(las_path, units="native")  # core points written in the file's units
    assert cores.crs == native.crs
    # bin the cores independently: the cell of each core from the raster's transform
    col, row = _pixel(transform, cores.xyz[:, 0], cores.xyz[:, 1])
    d, lod, sig = cores["distance"], cores["lod"], cores["significant"].astype(float)
    checked = 0
    for (r, c) in set(zip(row.tolist(), col.tolist())):
        here = (row == r) & (col == c) & np.isfinite(d)
        if here.any():
            assert bands[0, r, c] == pytest.approx(d[here].mean(), rel=1e-5, abs=1e-6)
            assert bands[1, r, c] == pytest.approx(lod[here].mean(), rel=1e-5, abs=1e-6)
            assert bands[2, r, c] == pytest.approx(sig[here].mean(), abs=1e-6)
            checked += 1
    assert checked > 10 and np.isfinite(bands[0]).sum() == checked  # no value without a core


def test_autzen_register_then_change_with_defaults_writes_geotiff(tmp_path, capsys):
    a, b = str(REAL / "epochs" / "autzen-bmx-2010.las"), str(REAL / "epochs" / "autzen-bmx-2023.las")
    assert main(["register", b, a, "--out", str(tmp_path / "R"), "--quiet"]) == 0
    reg = load_registration(tmp_path / "R" / "registration.json")
    assert dict(reg.inputs) == {"source": str(Path(b).resolve()), "target": str(Path(a).resolve())}
    assert reg.crs == read_cloud(b).crs
    capsys.readouterr()
    out = tmp_path / "C"
    assert main(["change", a, b, "--registration", str(tmp_path / "R" / "registration.json"),
                 "--held-shift-std", "0.1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    radius = re.search(r"cylinder radius (\d+\.\d+) m: the median distance to the 30th", text)
    assert radius and re.search(r"normal radius \d+\.\d+ m", text) and re.search(r"max depth \d+\.\d+ m", text)
    assert re.search(r"distance median\s+[+-]\d+\.\d+ (mm|m)\b", text)
    # Autzen's NN spacing is about 1.1 m: about 30 points lie within 3-4.5 m
    assert 2.5 < float(radius.group(1)) < 5.0
    counts = re.search(r"points per cylinder median\s+(\d+) / (\d+)", text)
    assert 20 <= int(counts.group(1)) <= 45  # the rule's promise: about 30 reference points per cylinder
    stem = "autzen-bmx-2010_autzen-bmx-2023_m3c2"
    _check_change_geotiff(out / f"{stem}.tif", out / f"{stem}.las", a, text)


@pytest.mark.slow
def test_feet_halves_register_and_change(tmp_path, capsys):
    """A file in US survey feet: the GeoTIFF's transform and bounds in feet, its CRS the file's."""
    a, b = _halves("file_with_both_wkt_and_geotiff_vlrs_every25.las", tmp_path)
    assert main(["register", str(a), str(b), "--out", str(tmp_path / "R"), "--quiet"]) == 0
    assert main(["change", str(a), str(b), "--registration", str(tmp_path / "R" / "registration.json"),
                 "--out", str(tmp_path / "C")]) == 0
    text = capsys.readouterr().out
    assert "used inverted" in text and "cylinder radius" in text
    _check_change_geotiff(tmp_path / "C" / f"{a.stem}_{b.stem}_m3c2.tif", tmp_path / "C" / f"{a.stem}_{b.stem}_m3c2.las",
                          a, text)
    with rasterio.open(tmp_path / "C" / f"{a.stem}_{b.stem}_m3c2.tif") as ds:
        assert ds.tags()["COORDINATE_UNIT"] == "US survey foot" and ds.bounds.left > 2.4e6  # feet, not metres
    # a registration file made in another CRS: said on stderr, not silently applied
    other = save_registration(tmp_path / "other.json", matrix=np.eye(4), covariance=np.eye(3) * 1e-6,
                              parameter_names=("tx", "ty", "tz"), crs=read_cloud(REAL / "epochs" /
                                                                                  "autzen-bmx-2010.las").crs)
    assert main(["change", str(a), str(b), "--registration", str(other), "--out", str(tmp_path / "C2")]) == 0
    assert "made in another CRS" in capsys.readouterr().err


def _check_shift_geotiff(out, source, size):
    """Every tile of the CSV at its pixel of the GeoTIFF: shifts, std and status; CRS and cell in file units."""
    import csv

    native = read_cloud(source, units="native")
    f = native.units.horizontal_to_metre
    rows = list(csv.DictReader(open(out / "shift_field.csv")))
    with rasterio.open(out / "shift_field.tif") as ds:
        assert pyproj.CRS.from_wkt(ds.crs.to_wkt()).equals(pyproj.CRS.from_user_input(native.crs))
        bands, transform = ds.read().astype(np.float64), ds.transform
        assert transform.a == pytest.approx(size / f)  # the tile edge in the file's units
    assert sum(r["status"] == "ok" for r in rows) >= 2
    for r in rows:
        cx = (float(r["xmin"]) + float(r["xmax"])) / 2 / f
        cy = (float(r["ymin"]) + float(r["ymax"])) / 2 / f
        col, row = (int(v) for v in _pixel(transform, cx, cy))
        assert bands[6, row, col] == STATUS_CODES[r["status"]]
        for band, key in enumerate(("dx", "dy", "dz")):
            value = bands[band, row, col]
            if np.isfinite(value):  # a determined component: the CSV's number and its std
                assert value == pytest.approx(float(r[key]), rel=1e-5, abs=1e-7)
                assert bands[band + 3, row, col] == pytest.approx(float(r["s" + key[1]]), rel=1e-5, abs=1e-7)
        if r["status"] == "ok":
            assert np.isfinite(bands[:6, row, col]).all()
        if r["status"] in ("too few points", "failed"):
            assert np.isnan(bands[:6, row, col]).all()


def test_tiles_geotiff_on_metric_halves(tmp_path):
    a, b = _halves("faceraster_numerical_imprecision.laz", tmp_path)
    out = tmp_path / "T"
    assert main(["tiles", str(a), "--target", str(b), "--size", "10", "--scheduler", "threads", "--out", str(out),
                 "--quiet"]) in (0, 1, 4)
    with rasterio.open(out / "shift_field.tif") as ds:
        assert ds.crs.to_epsg() == 2154 and ds.count == 7 and ds.shape == (2, 3)
    _check_shift_geotiff(out, a, 10.0)
