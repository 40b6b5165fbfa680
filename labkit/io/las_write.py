"""LAS / LAZ writing: scales and offsets, point formats, extra bytes, range checks, the CRS records."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..core.units import Units
from ..core.errors import LabkitError
from ..core.arrays import extent
from ..core.progress import progress_steps
from .common import INT32_MAX, STANDARD_DTYPES
from .las import _las_xyz, las_units, laz_backend, to_metres
from .las_layout import LasLayout


def _las_offsets(xyz: np.ndarray, scales=None) -> np.ndarray:
    """Offsets at whole kilometres below the data (UTM-friendly, exact in binary).

    Where that leaves too little int32 range at a fine scale (e.g. 1e-7 degrees),
    the offset is the whole unit below the data instead.
    """
    if len(xyz) == 0:
        return np.zeros(3)
    lo, hi = extent(xyz)
    offsets = np.floor(lo / 1000.0) * 1000.0
    if scales is not None:
        tight = (hi - offsets) / np.asarray(scales) > 0.9 * INT32_MAX
        offsets[tight] = np.floor(lo[tight])
    return offsets


def _auto_format(attrs: dict) -> int:
    big = lambda k, m: k in attrs and attrs[k].size and attrs[k].max() > m  # noqa: E731
    new = {"nir", "scan_angle", "overlap", "scanner_channel"} & set(attrs)
    if new or big("classification", 31) or big("return_number", 7) or big("number_of_returns", 7):
        return 8 if "nir" in attrs else 7 if "red" in attrs else 6
    return {(False, False): 0, (True, False): 1, (False, True): 2, (True, True): 3}[("gps_time" in attrs, "red" in attrs)]


def write_las(cloud, tmp: Path, compress: bool, scales, point_format, chunk_size: int, progress=False,
               parallel: bool = True, label: str = "") -> None:
    import laspy

    layout = cloud.layout
    keep_layout = layout is not None and (point_format is None or int(point_format) == layout.point_format)
    attrs = _las_attributes(cloud.attributes, layout.point_format if keep_layout else point_format)
    if keep_layout and layout.fits(attrs, STANDARD_DTYPES):  # the file it came from: only coordinates change
        header = layout.header_for(attrs, cloud.crs, scales)
        fmt_id = layout.point_format
        offsets = layout.offsets_for(cloud.xyz, scales)
        header.offsets = _las_offsets(cloud.xyz, scales) if offsets is None else offsets
        if cloud.crs != layout.crs:
            _add_crs(header, cloud.crs, cloud.units)
    else:
        fmt_id = _auto_format(attrs) if point_format is None else int(point_format)
        if fmt_id not in range(11):
            raise LabkitError(f"point_format must be 0..10, got {point_format!r}")
        version = "1.2" if fmt_id <= 3 else "1.3" if fmt_id <= 5 else "1.4"
        header = laspy.LasHeader(version=version, point_format=fmt_id)
        header.scales, header.offsets = scales, _las_offsets(cloud.xyz, scales)
        header.generating_software = "labkit"
        _add_crs(header, cloud.crs, cloud.units)
    standard = set(header.point_format.standard_dimension_names)
    have = set(header.point_format.dimension_names)
    _check_extra_names([n for n in attrs if n not in have])
    for name, values in attrs.items():
        if name in standard:
            _check_fits(name, values, header.point_format.dimension_by_name(name), fmt_id)
        elif name not in have:
            header.add_extra_dim(laspy.ExtraBytesParams(name=name[:32], type=_extra_dtype(name, values)))
    standard = have | {n[:32] for n in attrs}
    _check_int32_range(cloud.xyz, header.offsets, header.scales)
    backend = laz_backend(parallel) if compress else None
    with laspy.open(str(tmp), mode="w", header=header, do_compress=compress, laz_backend=backend) as writer, \
            progress_steps(progress, len(cloud), f"writing {label or tmp.name}", "pts") as step:
        for start in range(0, max(len(cloud), 1), chunk_size):
            sl = slice(start, start + chunk_size)
            ints = _quantize(cloud.xyz[sl], header.offsets, header.scales)  # one chunk at a time
            rec = laspy.ScaleAwarePointRecord.zeros(len(ints), header=header)
            rec.X, rec.Y, rec.Z = ints[:, 0], ints[:, 1], ints[:, 2]
            for name, values in attrs.items():
                _assign(rec, name[:32], values[sl], name in standard)
            writer.write_points(rec)
            step(len(ints))


def _las_attributes(attrs: dict, point_format) -> dict:
    """Attributes to write; scan angles converted between the two LAS conventions."""
    out = dict(attrs)
    fmt_new = point_format is not None and int(point_format) >= 6
    if "scan_angle_rank" in out and "scan_angle" not in out and (fmt_new or _auto_format(out) >= 6):
        out["scan_angle"] = np.round(out.pop("scan_angle_rank").astype(np.float64) / 0.006).astype(np.int16)  # 0.006 deg units
    return out


def _check_extra_names(names: list) -> None:
    """LAS extra-bytes names hold 32 characters: two names may not share them."""
    seen = {}
    for name in names:
        if not name.isascii():
            raise LabkitError(f"attribute {name!r}: LAS extra-bytes names must be ASCII")
        short = name[:32]
        if short in seen:
            raise LabkitError(
                f"attributes {seen[short]!r} and {name!r} share their first 32 characters ({short!r}), "
                "the length of a LAS extra-bytes name: rename one of them"
            )
        seen[short] = name


def _check_fits(name: str, values: np.ndarray, dim, fmt_id: int) -> None:
    """Raise when an integer LAS field cannot hold the values (they would wrap around)."""
    values = np.asarray(values)
    if values.size == 0 or values.dtype.kind not in "biuf":
        return
    if dim.kind.name == "BitField":
        lo, hi = 0, 2**dim.num_bits - 1
    elif dim.kind.name in ("SignedInteger", "UnsignedInteger"):
        info = np.iinfo(dim.dtype)
        lo, hi = int(info.min), int(info.max)
    else:
        return
    if values.dtype.kind in "biu":
        info = np.iinfo(values.dtype) if values.dtype.kind != "b" else None
        if info is None or (info.min >= lo and info.max <= hi):
            return  # the dtype cannot hold a value outside the field: no pass over the data
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        raise LabkitError(f"attribute {name!r} holds NaN or infinite values; the LAS field takes integers {lo}..{hi}")
    vmin, vmax = values.min(), values.max()
    if vmin < lo or vmax > hi:
        raise LabkitError(
            f"attribute {name!r} holds values {vmin}..{vmax}, outside the range {lo}..{hi} of its LAS field "
            f"(point format {fmt_id}); they would wrap around: fix or rescale the values"
        )


def _extra_dtype(name: str, values: np.ndarray):
    values = np.asarray(values)
    if values.ndim != 1 or values.dtype.kind not in "biuf":
        raise LabkitError(f"attribute {name!r} ({values.dtype}, shape {values.shape}) cannot be stored as LAS extra bytes")
    return np.uint8 if values.dtype.kind == "b" else values.dtype


def _assign(rec, name: str, values: np.ndarray, standard: bool) -> None:
    values = np.asarray(values)
    if values.dtype.kind == "b":
        values = values.astype(np.uint8)
    if standard:
        target = np.asarray(rec[name]).dtype
        if target.kind in "iu" and values.dtype.kind == "f":
            if not np.array_equal(values, np.round(values)):
                raise LabkitError(f"attribute {name!r} must hold whole numbers for the LAS dimension of type {target}")
    try:
        rec[name] = values
    except OverflowError as exc:
        raise LabkitError(f"attribute {name!r} does not fit the chosen LAS point format: {exc}") from None


def _check_int32_range(xyz: np.ndarray, offsets, scales) -> None:
    """Raise if the LAS integers ``round((x - offset) / scale)`` would leave the int32 range."""
    if len(xyz) == 0:
        return
    lo, hi = extent(xyz)
    q = np.rint((np.vstack([lo, hi]) - np.asarray(offsets)) / np.asarray(scales))
    if np.abs(q).max() > INT32_MAX:
        raise LabkitError(
            f"the coordinates span {np.max(hi - lo):.1f} m, too much for LAS integers at "
            f"scale {np.asarray(scales).tolist()}; choose a coarser scale"
        )


def _quantize(xyz: np.ndarray, offsets, scales) -> np.ndarray:
    """LAS integers ``round((x - offset) / scale)`` of a chunk (range checked by :func:`_check_int32_range`)."""
    q = xyz - np.asarray(offsets)
    q /= np.asarray(scales)
    np.rint(q, out=q)
    return q.astype(np.int32)


_EPSG_UNIT_CODES = {"metre": 9001, "foot": 9002, "US survey foot": 9003}


def _add_crs(header, crs: str | None, units: Units | None = None) -> None:
    """Store the CRS text: WKT as a WKT VLR, ``EPSG:h[+v]`` as GeoTIFF keys (with the unit keys)."""
    if not crs:
        return
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr

    m = re.fullmatch(r"\s*EPSG:(\d+)(?:\+(\d+))?\s*", crs, flags=re.IGNORECASE)
    if m is None:
        header.vlrs.append(WktCoordinateSystemVlr(crs))
        if header.version.minor >= 4:
            header.global_encoding.wkt = True
        return
    code, vertical = int(m.group(1)), m.group(2)
    geographic = 4000 <= code < 5000  # EPSG's geographic 2D/3D block (4326, 4258, 4979, ...)
    keys = [(1024, 2 if geographic else 1), (1025, 1), (2048 if geographic else 3072, code)]
    if vertical:
        keys.append((4096, int(vertical)))
    if units is not None and not geographic and units.horizontal in _EPSG_UNIT_CODES:
        keys.append((3076, _EPSG_UNIT_CODES[units.horizontal]))  # ProjLinearUnitsGeoKey
    if units is not None and units.vertical in _EPSG_UNIT_CODES:
        keys.append((4099, _EPSG_UNIT_CODES[units.vertical]))  # VerticalUnitsGeoKey
    keys.sort()
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys = [GeoKeyEntryStruct(k, 0, 1, v) for k, v in keys]
    vlr.geo_keys_header.number_of_keys = len(keys)
    header.vlrs.append(vlr)


def transform_las(source, path, transform, *, units: str = "m", chunk_size: int = 1_000_000, progress=False,
                  parallel: bool = True):
    """Write the LAS/LAZ file ``source`` moved by ``transform`` to ``path``, chunk by chunk (None: not possible).

    The file ``write_cloud(read_cloud(source).with_xyz(transform(xyz)), path)`` writes - same
    header (version, point format, VLRs, scales, offsets), the same points with only X, Y, Z
    changed - without holding the cloud: each chunk's coordinates are read as ``read_cloud``
    reads them (in metres for ``units='m'``), moved by ``transform`` (a callable on (m, 3)
    arrays), put back into the file's units and quantized as ``write_cloud`` does. Returns None
    (and leaves nothing at ``path``) when the moved points do not fit the file's offsets
    (``write_cloud`` would then choose new ones): the caller writes the cloud instead.
    """
    import laspy

    source, path = Path(source), Path(path)
    backend = laz_backend(parallel)
    with laspy.open(str(source), laz_backend=backend) as reader:
        found, crs = las_units(reader.header)
        found, factors = to_metres(found, units, source)
        layout = LasLayout.of(reader.header, crs)
        names = {d: None for d in reader.header.point_format.dimension_names if d not in ("X", "Y", "Z")}
        header = layout.header_for(names, crs, layout.scales)
        header.offsets = layout.offsets
        scales, offsets = layout.scales, layout.offsets
        compress = path.suffix.lower() == ".laz"
        with laspy.open(str(path), mode="w", header=header, do_compress=compress,
                        laz_backend=backend if compress else None) as writer, \
                progress_steps(progress, int(reader.header.point_count), f"writing {path.name}", "pts") as step:
            for points in reader.chunk_iterator(chunk_size):
                xyz = transform(_las_xyz(points, scales, offsets, factors, np.empty((len(points), 3))))
                if factors is not None:
                    xyz = xyz / factors  # back to the file's units (write_cloud's _in_file_units)
                if len(xyz) and layout.offsets_for(xyz, scales) is None:
                    return None  # beyond the int32 range of the file's offsets
                ints = _quantize(xyz, offsets, scales)
                points.X, points.Y, points.Z = ints[:, 0], ints[:, 1], ints[:, 2]
                writer.write_points(points)
                step(len(points))
    return path
