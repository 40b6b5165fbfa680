"""LAS / LAZ reading, the units and CRS of a LAS header (via ``labkit.core.units``) and the header summary."""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..core.report import ReportMixin, fmt
from ..core.units import decide_units, parse_wkt
from ..core.units import Units, UnitsError
from ..core.errors import CloudFileError, EmptyRegionError, LabkitError
from ..core.arrays import extent, rows
from ..core.progress import progress_steps
from .chunks import ChunkCollector
from .common import LAS_SUFFIXES, existing_file, require_classification
from .filter import ReadFilter
from .las_layout import LasLayout


def _check_las_header(path: Path) -> None:
    """Sanity checks on the fixed LAS header before laspy parses it.

    A corrupt header can announce billions of VLRs, which laspy would try to
    read one by one; these checks reject such files at once.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(179)
    if len(head) < 179 or head[:4] != b"LASF":
        raise CloudFileError(f"{path} is not a LAS/LAZ file (no 'LASF' signature or header too short)")
    major, minor = head[24], head[25]
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    fmt_id = head[104] & 0x3F
    problems = []
    if major != 1 or minor > 4:
        problems.append(f"LAS version {major}.{minor} (known: 1.0-1.4)")
    if not 227 <= header_size <= offset <= size:
        problems.append(f"header size {header_size} / point data offset {offset} do not fit a file of {size} bytes")
    elif n_vlrs * 54 > offset - header_size:
        problems.append(f"{n_vlrs} VLRs announced, room for at most {(offset - header_size) // 54}")
    if fmt_id > 10:
        problems.append(f"point format {fmt_id} (known: 0-10)")
    scales = np.array(struct.unpack_from("<3d", head, 131))
    offsets = np.array(struct.unpack_from("<3d", head, 155))
    if not (np.isfinite(scales).all() and (scales != 0).all()):
        problems.append(f"scale factors {scales.tolist()} (each must be a finite number other than 0)")
    if not np.isfinite(offsets).all():
        problems.append(f"offsets {offsets.tolist()} are not finite")
    if problems:
        raise CloudFileError(f"{path} has a corrupt or unsupported LAS header: " + "; ".join(problems))


def read_las(path: Path, flt: ReadFilter, keep, chunk_size: int, progress, units: str, parallel: bool = True):
    import laspy

    _check_las_header(path)
    with laspy.open(str(path), laz_backend=laz_backend(parallel),
                    decompression_selection=_decompression_selection(keep, flt)) as reader:
        header = reader.header
        total = int(header.point_count)
        found, crs = las_units(header)
        found, factors = to_metres(found, units, path)
        names = [d for d in header.point_format.dimension_names if d not in ("X", "Y", "Z")]
        names = [d for d in names if keep is None or d in keep]
        require_classification(flt, header.point_format.dimension_names, path)
        if header.are_points_compressed:  # with or without a filter: a wrong count is found before decoding
            _check_chunk_table(path, header, path.stat().st_size)
        every = not flt.active  # no filter: each point is kept, coordinates go straight into the cloud
        gather = ChunkCollector(_plausible_count(header, path) if every or _holds_header(flt, header, factors) else None)
        scales, offsets = np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, dtype=np.float64)
        seen, lo, hi = 0, np.full(3, np.inf), np.full(3, -np.inf)
        with progress_steps(progress, total, f"reading {path.name}", "pts") as step:
            for points in reader.chunk_iterator(chunk_size):
                m = len(points)
                seen += m
                xyz = gather.slot(m) if every else None
                xyz = _las_xyz(points, scales, offsets, factors, np.empty((m, 3)) if xyz is None else xyz)
                cls = np.asarray(points["classification"]) if flt.classes is not None else None
                mask = flt.mask(xyz, cls)
                if mask is not None and m:  # the extent of the points themselves (header bounds may be wrong)
                    lo_m, hi_m = extent(xyz)
                    lo, hi = np.minimum(lo, lo_m), np.maximum(hi, hi_m)
                sel = slice(None) if mask is None else mask
                gather.add(xyz if mask is None else rows(xyz, mask), {d: np.asarray(points[d])[sel] for d in names})
                step(m)
        if seen != total:
            raise CloudFileError(f"{path} is truncated: the header announces {total} points, the file holds {seen}")
        xyz, attrs = gather.result()
        if len(xyz) == 0 and seen and flt.classes is None and (flt.box is not None or flt.rings is not None):
            raise EmptyRegionError(f"{flt.describe()} lies outside the extent of the points of {path} "
                                   f"(x {lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f})")
        return xyz, attrs, crs, found, LasLayout.of(header, crs)


def laz_backend(parallel: bool = True):
    """laspy's LAZ backends to try: lazrs on all cores first when ``parallel``, else lazrs on one.

    Examples
    --------
    >>> from labkit.io import laz_backend
    >>> [b.name for b in laz_backend()][:2]
    ['LazrsParallel', 'Lazrs']
    >>> [b.name for b in laz_backend(parallel=False)][0]
    'Lazrs'
    """
    from laspy import LazBackend

    order = ((LazBackend.LazrsParallel, LazBackend.Lazrs, LazBackend.Laszip) if parallel
             else (LazBackend.Lazrs, LazBackend.Laszip, LazBackend.LazrsParallel))
    # only installed backends: a corrupt file is then reported by lazrs, not as "Laszip is not available"
    return tuple(b for b in order if b.is_available()) or order


def _las_xyz(points, scales, offsets, factors, out: np.ndarray) -> np.ndarray:
    """``X * scale + offset`` (then the unit factors) computed into ``out``, one column at a time.

    The same float64 operations as laspy's ``points.x``, without its temporary
    arrays and without stacking three columns into a new array.
    """
    for j, dim in enumerate("XYZ"):
        col = out[:, j]
        np.multiply(np.asarray(points[dim]), scales[j], out=col)
        col += offsets[j]
    if factors is not None:
        out *= factors  # file units -> metres, per axis
    return out


# Layers of a LAZ 1.4 file (point formats 6-10) that hold each dimension; a
# read that keeps few attributes decompresses only their layers.
_LAYERS = {
    "return_number": "XY_RETURNS_CHANNEL", "number_of_returns": "XY_RETURNS_CHANNEL",
    "scanner_channel": "XY_RETURNS_CHANNEL", "classification": "CLASSIFICATION",
    "synthetic": "FLAGS", "key_point": "FLAGS", "withheld": "FLAGS", "overlap": "FLAGS",
    "scan_direction_flag": "FLAGS", "edge_of_flight_line": "FLAGS", "classification_flags": "FLAGS",
    "intensity": "INTENSITY", "scan_angle": "SCAN_ANGLE", "scan_angle_rank": "SCAN_ANGLE",
    "user_data": "USER_DATA", "point_source_id": "POINT_SOURCE_ID", "gps_time": "GPS_TIME",
    "red": "RGB", "green": "RGB", "blue": "RGB", "nir": "NIR",
}


def _decompression_selection(keep, flt: ReadFilter):
    """The LAZ layers a read needs: all of them unless ``attributes`` names a few standard ones."""
    from laspy import DecompressionSelection

    if keep is None:
        return DecompressionSelection.all()
    wanted = set(keep) | ({"classification"} if flt.classes is not None else set())
    if not wanted <= set(_LAYERS):  # extra bytes, wave packets, unknown names: decompress everything
        return DecompressionSelection.all()
    sel = DecompressionSelection.XY_RETURNS_CHANNEL | DecompressionSelection.Z
    for name in wanted:
        sel |= DecompressionSelection[_LAYERS[name]]
    return sel


def _holds_header(flt: ReadFilter, header, factors) -> bool:
    """The box filter holds the file's whole header extent (so most points will be kept)."""
    if flt.box is None or flt.rings is not None or header.point_count == 0:
        return False
    f = np.ones(3) if factors is None else factors
    lo, hi = np.asarray(header.mins) * f, np.asarray(header.maxs) * f
    box = np.asarray(flt.box)
    d = box.shape[1]
    return bool((box[0] <= lo[:d]).all() and (box[1] >= hi[:d]).all())


def to_metres(found: Units, units: str, path: Path):
    """(units recorded on the cloud, per-axis factors to apply or None) for ``units='m'|'native'``."""
    if units == "native" or not found.known:
        return found, None
    if found.angular:
        raise UnitsError(
            f"{path} is in {found.angle_text} ({found.describe()}); labkit's metric steps "
            "need projected coordinates: reproject it (e.g. to UTM) first, or read it with units='native' "
            "for non-metric use"
        )
    factors = found.factors
    if factors is None:
        raise UnitsError(f"{path}: cannot convert {found.label(native=True)} to metres ({found.describe()}); "
                         "read it with units='native'")
    if np.all(factors == 1.0):
        return found, None
    return replace(found, converted=True), factors


def _plausible_count(header, path: Path) -> int | None:
    """The header's point count if the file can hold it (for preallocation), else None.

    An uncompressed file shorter than its header promises is truncated. For
    LAZ the count is trusted only up to a generous compression ratio; beyond
    that, chunks are gathered without preallocating.
    """
    total = int(header.point_count)
    needed = total * header.point_format.size
    size = path.stat().st_size
    if not header.are_points_compressed:
        if header.offset_to_point_data + needed > size:
            raise CloudFileError(
                f"{path} is truncated or corrupt: the header announces {total} points "
                f"({header.offset_to_point_data + needed} bytes), the file has {size} bytes"
            )
        held = (_end_of_points(header, size) - header.offset_to_point_data) // header.point_format.size
        if held > total:
            raise CloudFileError(
                f"{path}: the header counts {total} points but the file holds {held} point records; "
                "the header is wrong (rewrite the file with a tool that updates it, e.g. las2las or PDAL)"
            )
        return total
    return total if needed <= 50 * size else None


def _end_of_points(header, size: int) -> int:
    """Byte where the point records end: the first EVLR or waveform record after them, else the end of the file."""
    ends = [int(getattr(header, name, 0) or 0) for name in ("start_of_first_evlr",
                                                             "start_of_waveform_data_packet_record")]
    ends = [e for e in ends if header.offset_to_point_data < e <= size]
    return min(ends) if ends else size


def _check_chunk_table(path: Path, header, size: int) -> None:
    """A LAZ file begins its points with the offset of its chunk table, written last: past the end = truncated."""
    with open(path, "rb") as f:
        f.seek(header.offset_to_point_data)
        raw = f.read(8)
    if len(raw) < 8:
        raise CloudFileError(f"{path} is a truncated LAZ file: it ends before its compressed points begin")
    table = struct.unpack("<q", raw)[0]
    if table != -1 and not header.offset_to_point_data < table <= size - 8:
        raise CloudFileError(
            f"{path} is a truncated or corrupt LAZ file: its chunk table should start at byte {table}, "
            f"the file has {size} bytes"
        )
    held = _laz_points_held(path, header) if table != -1 else None
    if held is None:
        return
    count, (least, most) = int(header.point_count), held
    exact = f"holds {least}" if least == most else f"holds at least {least}"
    if count < least:
        raise CloudFileError(
            f"{path}: the header counts {count} points but the file {exact} (its LAZ chunk table); the header "
            "is wrong (rewrite the file with a tool that updates it)"
        )
    if count > most:
        raise CloudFileError(
            f"{path} is truncated or its header is wrong: the header counts {count} points but the file "
            + (f"holds {most}" if least == most else f"has room for at most {most}") + " (its LAZ chunk table)"
        )


def _laz_points_held(path: Path, header) -> tuple[int, int] | None:
    """(fewest, most) points the LAZ chunk table allows; None without a readable table.

    Variable-size chunks record their counts, and so does every chunk of a layered LAZ
    1.4 file (point formats 6-10: a 32-bit count after the chunk's raw first point), so
    both bounds are the count. Fixed-size chunks of point formats 0-5 record none: all
    but the last chunk are full, the last one holds 1 to ``chunk_size`` points.
    """
    import lazrs

    vlr = next((v for v in header.vlrs if getattr(v, "record_id", None) == 22204), None)
    if vlr is None:
        return None
    try:
        laz = lazrs.LazVlr(vlr.record_data)
        with open(path, "rb") as f:
            f.seek(header.offset_to_point_data)
            chunks = lazrs.read_chunk_table(f, laz)
            if not chunks or laz.uses_variable_size_chunks():
                n = int(sum(c[0] for c in chunks))
                return (n, n) if chunks else None
            full = (len(chunks) - 1) * int(laz.chunk_size())
            if header.point_format.id < 6:
                return full + 1, full + int(laz.chunk_size())
            # the last chunk: after the table's offset (8 bytes), the earlier chunks and its raw first point
            f.seek(header.offset_to_point_data + 8 + sum(int(c[1]) for c in chunks[:-1]) + header.point_format.size)
            last = struct.unpack("<I", f.read(4))[0]
    except Exception:  # noqa: BLE001 - an unreadable table is reported by the decompressor itself
        return None
    if not 1 <= last <= int(laz.chunk_size()):
        return None  # not a count: left to the decompressor
    return full + last, full + last


def _las_crs_records(header):
    """(WKT text or None, GeoKey dict or None, GeoDoubleParams) of a LAS header.

    The WKT is the LASF_Projection 2112 record, or the OGR WKT that libLAS wrote
    as ``liblas`` 2112. GeoKeys map key id -> (location, count, value).
    """
    from laspy.vlrs.known import GeoDoubleParamsVlr, GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    wkt, keys, doubles = None, None, ()
    for rec in list(header.vlrs) + list(header.evlrs or []):
        text = None
        if isinstance(rec, WktCoordinateSystemVlr):
            text = rec.string
        elif getattr(rec, "record_id", None) == 2112 and isinstance(getattr(rec, "record_data", None), bytes):
            text = rec.record_data.decode("utf-8", errors="replace")
        if text is not None:
            text = text.strip().rstrip("\x00").strip()
            if wkt is None and text and parse_wkt(text) is not None:
                wkt = text
        if isinstance(rec, GeoKeyDirectoryVlr) and keys is None:
            keys = {k.id: (k.tiff_tag_location, k.count, k.value_offset) for k in rec.geo_keys if k.id}
        if isinstance(rec, GeoDoubleParamsVlr):
            doubles = tuple(float(getattr(d, "value", d)) for d in rec.doubles)
    return wkt, keys or None, doubles


def _epsg_text(keys) -> str | None:
    """``EPSG:h[+v]`` from ProjectedCSType / GeographicType (+ VerticalCSType) GeoKeys."""
    if not keys:
        return None
    direct = {k: v[2] for k, v in keys.items() if v[0] == 0}
    horizontal = direct.get(3072) or direct.get(2048)
    if horizontal is None or not 1024 <= horizontal <= 32766:
        return None
    vertical = direct.get(4096)
    if vertical is not None and 1024 <= vertical <= 32766:
        return f"EPSG:{horizontal}+{vertical}"
    return f"EPSG:{horizontal}"


def las_units(header) -> tuple[Units, str | None]:
    """Units of a LAS header's coordinates and its CRS text (from the governing record).

    The WKT governs a LAS 1.4 file with the global-encoding WKT bit set, the
    GeoTIFF keys every other file (LAS specification); the other record is used
    when the governing one names nothing. See ``labkit.core.units`` for the parser.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import laspy
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.io import las_units, write_cloud
    >>> path = write_cloud(PointCloud(np.zeros((1, 3)), crs="EPSG:25832"), Path(tempfile.mkdtemp()) / "a.las")
    >>> with laspy.open(path) as reader:
    ...     units, crs = las_units(reader.header)
    >>> units.horizontal, crs
    ('metre', 'EPSG:25832')
    """
    wkt, keys, doubles = _las_crs_records(header)
    las14 = (header.version.major, header.version.minor) >= (1, 4)
    wkt_bit = bool(header.global_encoding.wkt) if las14 else False
    found = decide_units(wkt, keys, doubles, wkt_bit=wkt_bit, las14=las14)
    epsg = _epsg_text(keys)
    if found.source == "GeoKeys":
        crs = epsg or wkt
    elif found.source == "WKT":
        crs = wkt
    else:
        crs = wkt if wkt and (las14 and wkt_bit or epsg is None) else epsg
    return found, crs


# ---------------------------------------------------------------------------- header summary
@dataclass(frozen=True, eq=False, repr=False)
class CloudInfo(ReportMixin):
    """What a LAS/LAZ header says, read without loading the points.

    Examples
    --------
    >>> from labkit.io import cloud_info
    >>> from labkit.synthetic import tile_row
    >>> info = cloud_info(tile_row(1) / "t0.laz")
    >>> info.point_count, info.mins.tolist(), info.compressed
    (10, [0.0, 0.0, 0.0], True)
    """

    path: Path
    version: str
    point_format: int
    point_count: int
    mins: np.ndarray
    maxs: np.ndarray
    scales: np.ndarray
    offsets: np.ndarray
    dimensions: tuple
    crs: str | None
    compressed: bool
    units: Units = Units()

    def _report(self):
        crs = self.crs if self.crs is None or len(self.crs) < 60 else self.crs[:57] + "..."
        rows = [
            ("file", str(self.path.name)),
            ("LAS version / point format", f"{self.version} / {self.point_format}" + (" (LAZ)" if self.compressed else "")),
            ("points", f"{self.point_count:,}"),
            ("min", _with_units(self.mins, 3, self.units)),
            ("max", _with_units(self.maxs, 3, self.units)),
            ("scale", _with_units(self.scales, _scale_digits(self.scales), self.units)),
            ("offset", _with_units(self.offsets, 3, self.units)),
            ("units", self.units.describe()),
            ("CRS", str(crs)),
            ("dimensions", ", ".join(self.dimensions)),
        ]
        return "Point-cloud file", [("", rows)]


def _scale_digits(scales) -> int:
    """Decimals that show the finest scale factor (at least 6)."""
    finest = np.abs(np.asarray(scales, dtype=float)).min()
    return int(max(6, np.ceil(-np.log10(finest)) + 1)) if finest > 0 else 6


def _with_units(values, digits: int, units: Units) -> str:
    """``[x, y, z] m`` or ``[x, y] m, z ftUS``: the file's units, never 'm' when they are not metres."""
    if not units.known:
        return fmt(values, digits) + " (units not stated)"
    h, _, v = (label if label != "?" else "(unit not stated)" for label in units.axis_labels(native=True))
    hd = digits + 4 if units.angular and digits < 8 else digits  # 1e-7 degrees is about 1 cm
    if h == v and hd == digits:
        return fmt(values, digits, h)
    return f"{fmt(values[:2], hd, h)}, {fmt(values[2], digits, v)}"


def cloud_info(path) -> CloudInfo:
    """Header of a LAS/LAZ file (count, bounds, scale, offset, CRS, dimensions) without reading points.

    Examples
    --------
    >>> from labkit.io import cloud_info
    >>> from labkit.synthetic import tile_row
    >>> info = cloud_info(tile_row(2, suffix=".las") / "t1.las")
    >>> info.point_count, info.maxs.tolist(), info.version
    (10, [19.0, 0.0, 0.0], '1.2')
    """
    path = existing_file(path)
    if path.suffix.lower() not in LAS_SUFFIXES:
        raise CloudFileError(f"cloud_info reads LAS/LAZ headers only, not {path}")
    import laspy

    _check_las_header(path)
    try:
        with laspy.open(str(path)) as reader:
            h = reader.header
            found, crs = las_units(h)
            return CloudInfo(
                path=path,
                version=f"{h.version.major}.{h.version.minor}",
                point_format=int(h.point_format.id),
                point_count=int(h.point_count),
                mins=np.asarray(h.mins, dtype=float),
                maxs=np.asarray(h.maxs, dtype=float),
                scales=np.asarray(h.scales, dtype=float),
                offsets=np.asarray(h.offsets, dtype=float),
                dimensions=tuple(h.point_format.dimension_names),
                crs=crs,
                compressed=bool(h.are_points_compressed),
                units=found,
            )
    except LabkitError:
        raise
    except Exception as exc:
        raise CloudFileError(f"cannot read the header of {path}: {type(exc).__name__}: {exc}") from exc
