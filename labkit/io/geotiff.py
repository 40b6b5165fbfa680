"""GeoTIFF deliverables through rasterio: the M3C2 change map and the tile shift field (notebooks 08 and 10).

Each raster is georeferenced in the input's CRS and in the input's own coordinate
units: a cloud read from a file in US survey feet (``read_cloud`` converts to metres)
gives a raster whose transform and bounds are in US survey feet again, so it lies on
the file in a GIS. The band *values* are lengths in metres (distances, levels of
detection, shifts and their standard deviations); each band's description names its
quantity and unit, and the tag ``VALUE_UNIT`` says ``metre``. Cells without a value
hold NaN (the nodata value).

Files are written to a temporary name and renamed when complete (``labkit.core.atomic``).
The CRS text a cloud carries (WKT or ``EPSG:n[+m]``) becomes a rasterio CRS in one
place, :func:`geotiff_crs`; a raster of an input without a CRS has none and carries the tag
``CRS_NOTE`` ("no CRS in the input: coordinates in an unknown frame").
"""

from __future__ import annotations

import re
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_path
from ..core.crs import NO_CRS
from ..core.errors import LabkitError
from . import LAS_SUFFIXES, cloud_files, cloud_info

__all__ = ["change_geotiff", "geotiff_crs", "shift_field_geotiff"]

CHANGE_BANDS = ("distance", "lod", "significant")
SHIFT_BANDS = ("dx", "dy", "dz", "std_dx", "std_dy", "std_dz", "status")
STATUS_CODES = {"ok": 1, "undetermined": 2, "not converged": 3, "too few points": 4, "failed": 5}


def geotiff_crs(crs):
    """A rasterio CRS from a cloud's CRS text (WKT, ``EPSG:n`` or ``EPSG:n+m``); None without a CRS.

    A compound ``EPSG:n+m`` whose vertical part PROJ does not know keeps its horizontal
    part (with a warning): the raster's georeferencing is horizontal anyway.

    Parameters
    ----------
    crs : str or None
        ``PointCloud.crs``.

    Returns
    -------
    rasterio.crs.CRS or None

    References
    ----------
    .. [1] Notebook 03, section 2 (the CRS of a LAS file: WKT and GeoTIFF keys).
    .. [2] OGC (2019): OGC GeoTIFF Standard 1.1, OGC 19-008r4.

    Examples
    --------
    >>> from labkit.io.geotiff import geotiff_crs
    >>> geotiff_crs("EPSG:25832").to_epsg(), geotiff_crs(None)
    (25832, None)
    """
    import rasterio
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    if not crs:
        return None
    try:
        # inside an Env, GDAL's messages (PROJ's "crs not found") go to rasterio's logger, not to stderr;
        # a CRS it cannot read raises CRSError, which says so
        with rasterio.Env():
            return CRS.from_user_input(crs)
    except CRSError as exc:
        m = re.fullmatch(r"\s*EPSG:(\d+)\+\d+\s*", str(crs), flags=re.IGNORECASE)
        if m is None:
            raise LabkitError(f"cannot write a GeoTIFF in the CRS {str(crs)[:80]!r}: {exc}") from None
    warnings.warn(f"the vertical part of {crs} is not a CRS PROJ knows; the GeoTIFF gets EPSG:{m.group(1)}",
                  stacklevel=2)
    return CRS.from_epsg(int(m.group(1)))


def change_geotiff(result, path, *, crs=None, units=None, cell=None, extent=None):
    """Write the M3C2 change map as a 3-band GeoTIFF: distance (m), LoD (m), share of significant cores.

    Core points are binned in square cells; a cell holds the mean distance and the mean
    level of detection of its cores and the share of its cores whose change is significant
    (1: all, 0: none); NaN where no core has a distance.

    Parameters
    ----------
    result : M3C2Result
        From :func:`labkit.m3c2` (core points in the cloud's metric coordinates).
    path : str or Path
        The ``.tif`` to write (atomically).
    crs : str, optional
        The input cloud's ``crs``.
    units : labkit.core.units.Units, optional
        The input cloud's ``units``: with converted feet the raster is written in feet.
    cell : float, optional
        Cell size in m (default: the cylinder radius, the default core spacing).
    extent : array_like (n, 2) or (n, 3), optional
        Points (or their bounding corners) the raster must cover, e.g. the reference cloud;
        default: the core points.

    Returns
    -------
    Path

    References
    ----------
    .. [1] Notebook 10, eqs. 3, 5 and 7 (distance, level of detection, significance).
    .. [2] D. Lague, N. Brodu, J. Leroux (2013): Accurate 3D comparison of complex topography with
       terrestrial laser scanner: application to the Rangitikei canyon (N-Z). ISPRS Journal of
       Photogrammetry and Remote Sensing 82, 10-26.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> import rasterio
    >>> from labkit.change.m3c2 import m3c2
    >>> from labkit.io.geotiff import change_geotiff
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 4, (2000, 2))
    >>> a, b = np.c_[xy, rng.normal(0, 0.01, 2000)], np.c_[xy, 0.1 + rng.normal(0, 0.01, 2000)]
    >>> result = m3c2(a, b, 1.0, normal_radius=1.0, cylinder_radius=0.5, max_depth=1.0)
    >>> path = change_geotiff(result, Path(tempfile.mkdtemp()) / "change.tif", crs="EPSG:25832")
    >>> with rasterio.open(path) as ds:
    ...     print(ds.count, ds.crs.to_epsg(), round(float(np.nanmedian(ds.read(1))), 2), ds.descriptions[0])
    3 25832 0.1 distance (m)
    """
    xy = np.asarray(result.corepoints, dtype=np.float64)[:, :2]
    ok = np.isfinite(result.distance)
    cell = float(result.cylinder_radius if cell is None else cell)
    values = np.c_[result.distance, result.lod, result.significant.astype(np.float64)]
    cover = xy if extent is None else np.asarray(extent, dtype=np.float64)[:, :2]
    cover = np.array([np.vstack([cover, xy]).min(axis=0), np.vstack([cover, xy]).max(axis=0)])
    grid = _bin_mean(xy[ok], values[ok], cell, cover)
    descriptions = ("distance (m)", "level of detection (m)", "share of significant cores (1)")
    return _write(path, grid, descriptions, CHANGE_BANDS, crs, units, "M3C2 change (labkit)")


def shift_field_geotiff(field, path, sources=None, *, crs=None, units=None):
    """Write a tile shift field as a GeoTIFF at tile resolution: dx, dy, dz, their std (m) and status.

    One pixel per tile of the regular grid: the shift at the tile's centroid (eq. 1 of
    notebook 08), NaN for a component the tile's data do not determine, and its standard
    deviations (inf: not determined; NaN: not registered); ``status`` codes the tile's status:
    1 ok, 2 undetermined, 3 not converged, 4 too few points, 5 failed (0 any other).

    Parameters
    ----------
    field : ShiftField
        From :func:`labkit.register_tiles`.
    path : str or Path
        The ``.tif`` to write (atomically).
    sources : str, Path or list, optional
        The source files, folders or globs of ``labkit tiles``: the CRS and units are read
        from the first LAS/LAZ header among them (unless ``crs``/``units`` are given).
    crs : str, optional
    units : labkit.core.units.Units, optional

    Returns
    -------
    Path

    References
    ----------
    .. [1] Notebook 08, eqs. 1-2 (the shift of a tile and its covariance).
    .. [2] OGC (2019): OGC GeoTIFF Standard 1.1, OGC 19-008r4.

    Examples
    --------
    >>> import tempfile
    >>> import numpy as np
    >>> import rasterio
    >>> from labkit.io.geotiff import shift_field_geotiff
    >>> from labkit.tiles import ShiftField, Tile, TileShift
    >>> tiles = tuple(TileShift(Tile(0, c, (100.0 * c, 0.0, 100.0 * c + 100, 100.0)), np.array([0.01 * c, 0, 0]),
    ...                         np.eye(3) * 1e-6, np.ones(3, bool), 900, 950, 800, 1.0, True, 0.1, "ok")
    ...               for c in range(2))
    >>> path = shift_field_geotiff(ShiftField(tiles, 100.0), f"{tempfile.mkdtemp()}/shift.tif", crs="EPSG:25832")
    >>> with rasterio.open(path) as ds:
    ...     print(ds.shape, ds.read(1).tolist(), ds.read(4)[0, 0], ds.bounds.right)
    (1, 2) [[0.0, 0.009999999776482582]] 0.001 200.0
    """
    if (crs is None or units is None) and sources is not None:
        found_crs, found_units = _crs_of(sources)
        crs = found_crs if crs is None else crs
        units = found_units if units is None else units
    if len(field) == 0:
        raise LabkitError("the shift field has no tiles: no GeoTIFF to write")
    size = float(field.size)
    bounds = np.array([t.tile.bounds for t in field.tiles], dtype=np.float64)
    x0, y1 = bounds[:, 0].min(), bounds[:, 3].max()
    ncol = int(round((bounds[:, 2].max() - x0) / size))
    nrow = int(round((y1 - bounds[:, 1].min()) / size))
    data = np.full((len(SHIFT_BANDS), nrow, ncol), np.nan)
    col = np.round((bounds[:, 0] - x0) / size).astype(int)
    row = np.round((y1 - bounds[:, 3]) / size).astype(int)
    shifts = field.determined_translations  # NaN: a component the tile's data do not determine
    registered = np.isfinite(field.translations).all(axis=1)
    std = np.where(np.isnan(shifts) & registered[:, None], np.inf, field.std)
    data[0:3, row, col] = shifts.T
    data[3:6, row, col] = np.where(registered[:, None], std, np.nan).T
    names = [getattr(t, "verdict", t.status) for t in field.tiles]
    data[6, row, col] = [STATUS_CODES.get(n, 0) for n in names]
    codes = ", ".join(f"{v} {k}" for k, v in STATUS_CODES.items())
    descriptions = ("dx (m)", "dy (m)", "dz (m)", "std dx (m, inf: not determined)", "std dy (m, inf: not determined)",
                    "std dz (m, inf: not determined)", f"status ({codes}, 0 other)")
    return _write(path, (data, x0, y1, size), descriptions, SHIFT_BANDS, crs, units, "tile shift field (labkit)")


# --------------------------------------------------------------------------- private steps
def _bin_mean(xy, values, cell, extent_xy):
    """Mean of ``values`` per square cell (no Python loop): (bands, rows, cols) array, x0, y_top, cell."""
    if not (np.isfinite(cell) and cell > 0):
        raise LabkitError(f"cell size must be a positive length, got {cell!r}")
    lo, hi = extent_xy.min(axis=0), extent_xy.max(axis=0)
    x0, y1 = np.floor(lo[0] / cell) * cell, np.ceil(hi[1] / cell) * cell
    if y1 <= hi[1]:
        y1 += cell
    ncol = int(np.floor((hi[0] - x0) / cell)) + 1
    nrow = int(np.floor((y1 - lo[1]) / cell)) + 1
    if ncol * nrow > 50_000_000:
        raise LabkitError(f"a {nrow} x {ncol} raster is too large: give a larger cell size")
    col = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
    row = np.floor((y1 - xy[:, 1]) / cell).astype(np.int64)
    flat = row * ncol + col
    n = np.bincount(flat, minlength=nrow * ncol).astype(np.float64)
    out = np.full((values.shape[1], nrow * ncol), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        for b in range(values.shape[1]):  # a loop over bands, not points
            v = values[:, b]
            fin = np.isfinite(v)
            s = np.bincount(flat[fin], weights=v[fin], minlength=nrow * ncol)
            k = np.bincount(flat[fin], minlength=nrow * ncol)
            inf = np.bincount(flat[~fin & (v > 0)], minlength=nrow * ncol) > 0
            out[b] = np.where(k > 0, s / np.maximum(k, 1), np.nan)
            out[b, inf] = np.inf  # an infinite LoD stays infinite
    out[:, n == 0] = np.nan
    return out.reshape(values.shape[1], nrow, ncol), x0, y1, cell


def _write(path, grid, descriptions, names, crs, units, title):
    """Write bands (metric frame) to a GeoTIFF in the file's CRS and coordinate units."""
    import rasterio
    from affine import Affine

    data, x0, y1, cell = grid
    f = 1.0
    if units is not None and getattr(units, "converted", False) and units.horizontal_to_metre:
        f = float(units.horizontal_to_metre)  # metres per file unit: back to the file's units
    unit_name = "unknown (taken as metre)" if units is None or not units.known else units.horizontal
    profile = dict(driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0], dtype="float32",
                   nodata=np.nan, crs=geotiff_crs(crs), transform=Affine(cell / f, 0.0, x0 / f, 0.0, -cell / f, y1 / f),
                   compress="deflate")
    path = Path(path)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as ds:
            ds.write(data.astype(np.float32))
            ds.update_tags(TITLE=title, VALUE_UNIT="metre", COORDINATE_UNIT=unit_name)
            if not crs:  # a GeoTIFF without a CRS says so (tag CRS_NOTE), not only the warning of the run
                ds.update_tags(CRS_NOTE=NO_CRS)
            for i, (d, n) in enumerate(zip(descriptions, names), start=1):
                ds.set_band_description(i, d)
                ds.update_tags(i, NAME=n)
    return path


def _crs_of(sources):
    """CRS text and Units of the first LAS/LAZ file among ``sources`` (files, folders, globs); else (None, None)."""
    for p in cloud_files(sources if isinstance(sources, (list, tuple)) else [sources]):
        if Path(p).suffix.lower() in LAS_SUFFIXES:
            info = cloud_info(p)  # the tiles are read with units="m": feet converted to metres
            return info.crs, replace(info.units, converted=info.units.horizontal_to_metre is not None)
    return None, None
