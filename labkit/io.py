"""Reading and writing point-cloud files (seed 003, step 1: laspy -> numpy -> CSV).

Formats
-------
- LAS / LAZ 1.0-1.4, every point format, via laspy (LAZ through lazrs).
  Coordinates are ``X * scale + offset`` as float64; every other dimension
  (classification, intensity, return_number, number_of_returns, gps_time,
  point_source_id, colours, flags, extra bytes, ...) becomes an attribute under
  laspy's name. The CRS is kept as text: the WKT of the WKT VLR, or
  ``"EPSG:code"`` from the GeoTIFF keys (no pyproj needed).
- ASCII ``.xyz .txt .csv .asc``: comma, semicolon or whitespace separated, with
  or without a header line. With a header, x/y/z are found by name and other
  columns become attributes (common spellings such as ``Classification``,
  ``Intensity``, ``GpsTime``, ``//X`` are mapped to laspy's names); without a
  header the first three columns are x, y, z and further ones are kept as
  ``column_3``, ``column_4``, ...
- NumPy ``.npy`` (an (n, >=3) array or a structured array with x, y, z fields)
  and ``.npz`` (``xyz`` or ``x``, ``y``, ``z`` plus one array per attribute).
- PLY ``.ply`` (reading): ASCII and binary little/big endian; the ``vertex``
  element's x, y, z plus every scalar property as an attribute.

Units
-----
The units of a LAS/LAZ file are read from its CRS (WKT and GeoTIFF keys, see
``labkit._units`` for the parser and the rule when they contradict each
other). By default (``units="m"``) coordinates in feet (US survey foot
1200/3937 m, international foot 0.3048 m; horizontal and vertical may differ)
are converted to metres, and a file in longitude/latitude degrees is refused
with :class:`labkit.cloud.UnitsError` before any point is read. With
``units="native"`` the coordinates stay as stored and the cloud records its
units, so metric steps refuse it later (:meth:`PointCloud.require_metric`).
Either way ``cloud.units`` says what the file states, whether the
coordinates were converted, and any conflict between WKT and GeoKeys. Writing
a converted cloud to LAS/LAZ/NPZ stores it in its file's units again (the CRS
is written with it), so a file never holds metres under a CRS in feet.

Large files
-----------
Files are read in chunks; a box, polygon or class filter is applied to each
chunk, so only the kept points are ever held in memory. LAZ is decompressed
(and compressed) on all cores by lazrs (``parallel=True``); with a selection of
``attributes`` from a LAS 1.4 file (point formats 6-10) only the layers of
those attributes are decompressed. Without a filter, each chunk's coordinates
``X * scale + offset`` are computed straight into the one preallocated array
the cloud then keeps (no concatenation, no second copy): reading needs the
memory of the cloud plus one chunk. :func:`read_clouds` reads the part of many
files (a folder, a glob) that an area needs: the LAS headers are read first and
files whose extent misses the area are skipped without decompressing a point.
Writing quantizes and writes one chunk at a time. ``progress=True`` reports the
chunks (see :mod:`labkit.progress`). Files are written atomically: into a
temporary file in the destination folder, renamed over the destination only
when complete.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import struct
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import regions
from ._report import ReportMixin, fmt
from .cloud import PointCloud, Units, UnitsError
from ._atomic import atomic_path
from ._checks import check_precision, choice
from .errors import CloudFileError, EmptyRegionError, LabkitError
from .progress import progress_steps

__all__ = ["read_cloud", "read_clouds", "write_cloud", "cloud_info", "CloudInfo", "cloud_files", "files_in_box",
           "LAS_SUFFIXES", "ASCII_SUFFIXES"]

LAS_SUFFIXES = (".las", ".laz")
ASCII_SUFFIXES = (".xyz", ".txt", ".csv", ".asc")
NUMPY_SUFFIXES = (".npy", ".npz")
PLY_SUFFIXES = (".ply",)
UNIT_CHOICES = ("m", "native")
SCAN_ANGLE_STEP = 0.006  # degrees per unit of the LAS 1.4 scan_angle field
DEFAULT_CHUNK = 1_000_000
_INT32_MAX = 2**31 - 1

# laspy dtypes of the standard dimensions that can arrive as text or npz columns
_STANDARD_DTYPES = {
    "intensity": np.uint16,
    "return_number": np.uint8,
    "number_of_returns": np.uint8,
    "classification": np.uint8,
    "scan_direction_flag": np.uint8,
    "edge_of_flight_line": np.uint8,
    "synthetic": np.uint8,
    "key_point": np.uint8,
    "withheld": np.uint8,
    "overlap": np.uint8,
    "scanner_channel": np.uint8,
    "scan_angle_rank": np.int8,
    "scan_angle": np.int16,
    "user_data": np.uint8,
    "point_source_id": np.uint16,
    "gps_time": np.float64,
    "red": np.uint16,
    "green": np.uint16,
    "blue": np.uint16,
    "nir": np.uint16,
}
# spellings found in ASCII headers (CloudCompare, LAStools, PDAL) -> laspy name
_ALIASES = {
    "class": "classification",
    "classification": "classification",
    "intensity": "intensity",
    "returnnumber": "return_number",
    "numberofreturns": "number_of_returns",
    "gpstime": "gps_time",
    "pointsourceid": "point_source_id",
    "userdata": "user_data",
    "scanangle": "scan_angle",
    "scananglerank": "scan_angle_rank",
    "scanchannel": "scanner_channel",
    "scannerchannel": "scanner_channel",
    "scandirectionflag": "scan_direction_flag",
    "edgeofflightline": "edge_of_flight_line",
    "keypoint": "key_point",
    "scalarintensity": "intensity",
    "scalarclassification": "classification",
    "r": "red",
    "g": "green",
    "b": "blue",
}


# ============================================================================ filter
@dataclass(frozen=True)
class _Filter:
    """The spatial and class filter applied to every chunk while reading."""

    box: np.ndarray | None = None
    rings: list | None = None
    classes: np.ndarray | None = None

    @classmethod
    def build(cls, bbox, polygon, classes) -> "_Filter":
        return cls(
            box=None if bbox is None else regions.as_bbox(bbox),
            rings=None if polygon is None else regions.as_rings(polygon),
            classes=None if classes is None else regions.as_classes(classes),
        )

    @property
    def active(self) -> bool:
        return self.box is not None or self.rings is not None or self.classes is not None

    def describe(self) -> str:
        parts = []
        if self.box is not None:
            parts.append(f"box {self.box.ravel().tolist()}")
        if self.rings is not None:
            parts.append(f"polygon with {sum(len(r) for r in self.rings)} vertices")
        if self.classes is not None:
            parts.append(f"classes {self.classes.tolist()}")
        return " and ".join(parts) or "no filter"

    def xy_bounds(self) -> np.ndarray | None:
        """[[xmin, ymin], [xmax, ymax]] of the spatial filter, for a quick header test."""
        boxes = []
        if self.box is not None:
            boxes.append(self.box[:, :2])
        if self.rings is not None:
            v = np.vstack(self.rings)
            boxes.append(np.array([v.min(axis=0), v.max(axis=0)]))
        if not boxes:
            return None
        return np.array([np.max([b[0] for b in boxes], axis=0), np.min([b[1] for b in boxes], axis=0)])

    def mask(self, xyz: np.ndarray, classification) -> np.ndarray | None:
        """Boolean mask of kept points, or None when nothing is filtered."""
        if not self.active:
            return None
        keep = np.ones(len(xyz), dtype=bool)
        if self.classes is not None:
            keep &= regions.class_mask(classification, self.classes)
        if self.box is not None:
            keep &= regions.box_mask(xyz, self.box)
        if self.rings is not None and keep.any():
            idx = np.flatnonzero(keep)
            keep[idx] = regions.polygon_mask(xyz[idx], self.rings)
        return keep


# ============================================================================ gathering chunks
class _Gather:
    """Collects the kept part of each chunk; preallocates when the final size is known.

    With a known capacity the chunks are written into one array (the memory of
    the cloud plus one chunk, no concatenation); :meth:`slot` hands out the rows
    a chunk of known size fills, so coordinates can be computed straight into them.
    """

    def __init__(self, capacity: int | None):
        self.capacity, self.n = capacity, 0
        self.xyz_parts, self.attr_parts = [], {}
        self.xyz, self.attrs = None, None

    def _allocate(self, attrs: dict) -> None:
        if self.xyz is None:
            self.xyz = np.empty((self.capacity, 3))
        if self.attrs is None:
            self.attrs = {k: np.empty(self.capacity, dtype=v.dtype) for k, v in attrs.items()}

    def slot(self, m: int) -> np.ndarray | None:
        """Rows ``n .. n+m`` of the preallocated coordinates (None without a capacity)."""
        if self.capacity is None or self.n + m > self.capacity:
            return None
        if self.xyz is None:
            self.xyz = np.empty((self.capacity, 3))
        return self.xyz[self.n : self.n + m]

    def add(self, xyz: np.ndarray, attrs: dict) -> None:
        m = len(xyz)
        if self.capacity is not None and self.n + m <= self.capacity:
            self._allocate(attrs)
            dest = self.xyz[self.n : self.n + m]
            if not np.shares_memory(dest, xyz):
                dest[:] = xyz
            for k, v in attrs.items():
                self.attrs[k][self.n : self.n + m] = v
        else:
            if self.capacity is not None:  # more points than announced: fall back to gathering parts
                self._spill()
            self.xyz_parts.append(xyz)
            for k, v in attrs.items():
                self.attr_parts.setdefault(k, []).append(v)
        self.n += m

    def _spill(self) -> None:
        if self.xyz is not None:
            self.xyz_parts.append(self.xyz[: self.n])
            for k, v in (self.attrs or {}).items():
                self.attr_parts.setdefault(k, []).append(v[: self.n])
        self.capacity, self.xyz, self.attrs = None, None, None

    def result(self) -> tuple[np.ndarray, dict]:
        if self.capacity is not None and self.xyz is not None:
            xyz, attrs = self.xyz[: self.n], {k: v[: self.n] for k, v in (self.attrs or {}).items()}
            if self.n < 0.9 * self.capacity:  # much was filtered out: give the unused rows back
                xyz, attrs = xyz.copy(), {k: v.copy() for k, v in attrs.items()}
            return xyz, attrs
        xyz = np.concatenate(self.xyz_parts) if self.xyz_parts else np.empty((0, 3))
        self.xyz_parts = []
        attrs = {}
        for k in list(self.attr_parts):
            attrs[k] = np.concatenate(self.attr_parts.pop(k))
        return xyz, attrs


# ============================================================================ reading
def read_cloud(
    path,
    *,
    bbox=None,
    polygon=None,
    classes=None,
    attributes=None,
    chunk_size: int = DEFAULT_CHUNK,
    progress=False,
    units: str = "m",
    parallel: bool = True,
) -> PointCloud:
    """Read a LAS/LAZ, ASCII, NumPy or PLY point-cloud file into a :class:`PointCloud`.

    Parameters
    ----------
    path : str or Path
        ``.las .laz .xyz .txt .csv .asc .npy .npz .ply``.
    bbox : sequence, optional
        Keep points inside ``(xmin, ymin, xmax, ymax)`` or
        ``(xmin, ymin, zmin, xmax, ymax, zmax)`` (see :func:`labkit.regions.crop_box`),
        in the units of the returned cloud (metres by default).
    polygon : array_like (m, 2) or list of rings, optional
        Keep points inside this polygon in xy (even-odd rule), same units as ``bbox``.
    classes : int or sequence of int, optional
        Keep points of these ASPRS classes (needs a classification attribute).
    attributes : str or sequence of str, optional
        Attribute(s) to keep (default: all); a single name may be given as a
        string. A name the file does not have raises. Reading fewer saves memory.
    chunk_size : int
        Points (or text lines) per chunk. The filters act on each chunk, so the
        memory needed is one chunk plus the kept points.
    progress : bool, "bar", "lines" or callable
        Report the chunks read (see :mod:`labkit.progress`): ``True`` shows a
        bar (terminal, notebook) or plain lines on stderr; default silent.
    units : {"m", "native"}
        ``"m"`` (default): coordinates whose CRS states feet are converted to
        metres (per axis: X/Y and Z may differ), and a file in longitude/latitude
        degrees raises :class:`labkit.cloud.UnitsError`. ``"native"``: keep the
        stored values; the cloud records its units and metric steps refuse it.
        Files without a stated unit (no CRS, text, NumPy, PLY) are read as they are.
    parallel : bool
        Decompress LAZ on all cores (lazrs); ``False`` uses one core.

    Returns
    -------
    PointCloud
        Named after the file stem; ``crs`` from the LAS header when present;
        ``units`` (:class:`labkit.cloud.Units`) says what the file states and
        whether the coordinates were converted.

    Raises
    ------
    CloudFileError
        Missing, unreadable, truncated or corrupt file, unsupported suffix.
    EmptyRegionError
        The filters keep no point.
    UnitsError
        ``units="m"`` and the file is in degrees (or in a unit with no metre factor).
    """
    path = _existing(path)
    flt = _Filter.build(bbox, polygon, classes)
    chunk_size = _positive_int(chunk_size, "chunk_size")
    choice(units, UNIT_CHOICES, "units")
    keep = _attribute_names(attributes)
    suffix = path.suffix.lower()
    try:
        if suffix in LAS_SUFFIXES:
            xyz, attrs, crs, found = _read_las(path, flt, keep, chunk_size, progress, units, parallel)
        elif suffix in ASCII_SUFFIXES:
            xyz, attrs, crs = _read_ascii(path, flt, keep, chunk_size, progress)
            found = Units()
        elif suffix in NUMPY_SUFFIXES:
            xyz, attrs, crs, found = _read_numpy(path, flt, keep, chunk_size, units)
        elif suffix in PLY_SUFFIXES:
            xyz, attrs, crs = _read_ply(path, flt, keep, chunk_size)
            found = Units()
        else:
            raise CloudFileError(_unsupported(path))
    except (LabkitError, MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # laspy, lazrs, numpy and OS errors of a bad file
        raise CloudFileError(f"cannot read {path}: {type(exc).__name__}: {exc}") from exc
    if len(xyz) == 0:
        if flt.active:
            raise EmptyRegionError(f"{flt.describe()} keeps none of the points of {path}")
        raise EmptyRegionError(f"{path} contains no points")
    if not np.isfinite(xyz).all():
        bad = int((~np.isfinite(xyz)).any(axis=1).sum())
        raise CloudFileError(f"{path} has {bad} point(s) with NaN or infinite coordinates")
    missing = set() if keep is None else keep - set(attrs)
    if missing and missing <= _SCAN_ANGLE_NAMES and set(attrs) & _SCAN_ANGLE_NAMES:
        missing = set()  # a text scan-angle column, read under the name its values need
    if missing:
        raise LabkitError(f"{path} has no attribute {', '.join(sorted(missing))}")
    return PointCloud._adopt(xyz, attrs, crs=crs, name=path.stem, units=found)  # no copy of the fresh arrays


def _positive_int(value, name: str) -> int:
    """A whole number >= 1 (bool, fractions and text refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise LabkitError(f"{name} must be a whole number >= 1, got {value!r}")
    if not np.isfinite(value) or value != int(value) or value < 1:
        raise LabkitError(f"{name} must be a whole number >= 1, got {value!r}")
    return int(value)


def _attribute_names(attributes) -> set | None:
    """The attribute selection as a set of names; a bare string is one name."""
    if attributes is None:
        return None
    if isinstance(attributes, str):
        return {attributes}
    try:
        names = list(attributes)
    except TypeError:
        raise LabkitError(f"attributes must be a name or a sequence of names, got {attributes!r}") from None
    bad = [a for a in names if not isinstance(a, str)]
    if bad:
        raise LabkitError(f"attributes must be names (str), got {bad[0]!r}")
    return set(names)


def _existing(path) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise CloudFileError(f"a point-cloud file path (str or Path) is needed, got {type(path).__name__}")
    if isinstance(path, str) and not path.strip():
        raise CloudFileError("a point-cloud file path is needed, got an empty string")
    path = Path(path)
    if not path.exists():
        raise CloudFileError(f"point-cloud file not found: {path}")
    if not path.is_file():
        raise CloudFileError(f"not a file: {path}")
    if not os.access(path, os.R_OK):
        raise CloudFileError(f"no permission to read {path}")
    return path


def _unsupported(path: Path) -> str:
    known = " ".join(LAS_SUFFIXES + ASCII_SUFFIXES + NUMPY_SUFFIXES + PLY_SUFFIXES)
    return f"unsupported point-cloud format {path.suffix!r} of {path}; known suffixes: {known}"


def _needs_class(flt: _Filter, names, path: Path) -> None:
    if flt.classes is not None and "classification" not in names:
        raise CloudFileError(f"{path} has no classification, so it cannot be filtered by class")


# ---------------------------------------------------------------------------- LAS / LAZ
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


def _read_las(path: Path, flt: _Filter, keep, chunk_size: int, progress, units: str, parallel: bool = True):
    import laspy

    _check_las_header(path)
    with laspy.open(str(path), laz_backend=laz_backend(parallel),
                    decompression_selection=_decompression_selection(keep, flt)) as reader:
        header = reader.header
        total = int(header.point_count)
        found, crs = las_units(header)
        found, factors = _to_metres(found, units, path)
        names = [d for d in header.point_format.dimension_names if d not in ("X", "Y", "Z")]
        names = [d for d in names if keep is None or d in keep]
        _needs_class(flt, header.point_format.dimension_names, path)
        _check_overlap(flt, header, path, factors)
        every = not flt.active  # no filter: each point is kept, coordinates go straight into the cloud
        gather = _Gather(_plausible_count(header, path) if every or _holds_header(flt, header, factors) else None)
        scales, offsets = np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, dtype=np.float64)
        seen = 0
        with progress_steps(progress, total, f"reading {path.name}", "pts") as step:
            for points in reader.chunk_iterator(chunk_size):
                m = len(points)
                seen += m
                xyz = gather.slot(m) if every else None
                xyz = _las_xyz(points, scales, offsets, factors, np.empty((m, 3)) if xyz is None else xyz)
                cls = np.asarray(points["classification"]) if flt.classes is not None else None
                mask = flt.mask(xyz, cls)
                sel = slice(None) if mask is None else mask
                gather.add(xyz if mask is None else xyz[sel], {d: np.asarray(points[d])[sel] for d in names})
                step(m)
        if seen != total:
            raise CloudFileError(f"{path} is truncated: the header announces {total} points, the file holds {seen}")
        xyz, attrs = gather.result()
        return xyz, attrs, crs, found


def laz_backend(parallel: bool = True):
    """laspy's LAZ backends to try: lazrs on all cores first when ``parallel``, else lazrs on one."""
    from laspy import LazBackend

    if parallel:
        return (LazBackend.LazrsParallel, LazBackend.Lazrs, LazBackend.Laszip)
    return (LazBackend.Lazrs, LazBackend.Laszip, LazBackend.LazrsParallel)


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


def _decompression_selection(keep, flt: _Filter):
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


def _holds_header(flt: _Filter, header, factors) -> bool:
    """The box filter holds the file's whole header extent (so most points will be kept)."""
    if flt.box is None or flt.rings is not None or header.point_count == 0:
        return False
    f = np.ones(3) if factors is None else factors
    lo, hi = np.asarray(header.mins) * f, np.asarray(header.maxs) * f
    box = np.asarray(flt.box)
    d = box.shape[1]
    return bool((box[0] <= lo[:d]).all() and (box[1] >= hi[:d]).all())


def _to_metres(found: Units, units: str, path: Path):
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
        return total
    return total if needed <= 50 * size else None


def _check_overlap(flt: _Filter, header, path: Path, factors=None) -> None:
    """Fail early when the filter's area misses the header's bounding box."""
    area = flt.xy_bounds()
    if area is None or header.point_count == 0:
        return
    f = np.ones(2) if factors is None else factors[:2]
    lo, hi = np.asarray(header.mins)[:2] * f, np.asarray(header.maxs)[:2] * f
    if (area[0] > hi).any() or (area[1] < lo).any() or (area[0] > area[1]).any():
        raise EmptyRegionError(
            f"{flt.describe()} lies outside the extent of {path} "
            f"(x {lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f})"
        )


def _las_crs_records(header):
    """(WKT text or None, GeoKey dict or None, GeoDoubleParams) of a LAS header.

    The WKT is the LASF_Projection 2112 record, or the OGR WKT that libLAS wrote
    as ``liblas`` 2112. GeoKeys map key id -> (location, count, value).
    """
    from laspy.vlrs.known import GeoDoubleParamsVlr, GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    from ._units import parse_wkt

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
    when the governing one names nothing. See ``labkit._units`` for the parser.
    """
    from ._units import decide_units

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


# ---------------------------------------------------------------------------- ASCII
def _read_ascii(path: Path, flt: _Filter, keep, chunk_size: int, progress: bool):
    size = path.stat().st_size
    with open(path, encoding="utf-8", errors="strict") as f:
        first, skipped = _first_line(f, path)
        delimiter = "," if "," in first else ";" if ";" in first else None
        tokens = [t.strip() for t in (first.split(delimiter) if delimiter else first.split())]
        header = not all(_is_number(t) for t in tokens)
        columns = _column_names(tokens, header, path)
        ix = [columns.index(c) for c in ("x", "y", "z")]
        extra = [(i, c) for i, c in enumerate(columns) if c not in ("x", "y", "z") and _wanted(c, keep)]
        _needs_class(flt, columns, path)
        lines = f if header else itertools.chain([first], f)
        gather, row = _Gather(None), skipped
        with progress_steps(progress, size, f"reading {path.name}", "B") as step:
            step(len(first.encode()) + 1 if header else 0)
            while True:
                block = list(itertools.islice(lines, chunk_size))
                if not block:
                    break
                data = _parse_block(block, delimiter, len(columns), path, row)
                row += len(block)
                xyz = data[:, ix]
                cls = data[:, columns.index("classification")] if flt.classes is not None else None
                mask = flt.mask(xyz, cls)
                sel = slice(None) if mask is None else mask
                gather.add(xyz[sel], {c: data[sel, i] for i, c in extra})
                step(sum(len(s) for s in block))
    xyz, attrs = gather.result()
    return xyz, _text_columns(attrs, path), None


def _first_line(f, path: Path) -> tuple[str, int]:
    """The first non-blank line (header or data) and the number of lines consumed."""
    for count, line in enumerate(f, start=1):
        if line.strip():
            return line.strip(), count - (0 if _looks_header(line) else 1)
    raise CloudFileError(f"{path} is empty (no lines with data)")


def _looks_header(line: str) -> bool:
    tokens = re.split(r"[,;\s]+", line.strip())
    return not all(_is_number(t) for t in tokens if t)


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _column_names(tokens: list[str], header: bool, path: Path) -> list[str]:
    if not header:
        if len(tokens) < 3:
            raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {len(tokens)}")
        return ["x", "y", "z"] + [f"column_{i}" for i in range(3, len(tokens))]
    names = [_canonical(t) for t in tokens]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise CloudFileError(f"{path}: the header line names no column {', '.join(missing)} (found {tokens})")
    if len(set(names)) != len(names):
        raise CloudFileError(f"{path}: the header line repeats a column name ({tokens})")
    return names


def _canonical(token: str) -> str:
    """Header spelling -> laspy-style name ('//X' -> 'x', 'GpsTime' -> 'gps_time')."""
    word = token.strip().lstrip("/#").strip().strip('"').strip("'")
    squeezed = re.sub(r"[^0-9a-z]", "", word.lower())
    if squeezed in ("x", "y", "z"):
        return squeezed
    if squeezed in _ALIASES:
        return _ALIASES[squeezed]
    return re.sub(r"[^0-9a-z]+", "_", word.lower()).strip("_") or "column"


def _parse_block(block: list[str], delimiter, ncol: int, path: Path, row: int) -> np.ndarray:
    try:
        data = np.loadtxt(block, delimiter=delimiter, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        raise CloudFileError(f"{path}: cannot parse lines {row + 1}-{row + len(block)}: {exc}") from None
    if data.shape[1] != ncol:
        raise CloudFileError(f"{path}: expected {ncol} columns near line {row + 1}, found {data.shape[1]}")
    return data


def _text_columns(attrs: dict, path: Path) -> dict:
    """Typed text columns; a scan-angle column in fractional degrees (PDAL's
    ``ScanAngleRank`` of LAS 1.4 data) becomes ``scan_angle`` in 0.006-degree units."""
    out = {}
    for name, values in attrs.items():
        if name == "scan_angle_rank" and "scan_angle" not in attrs and _fractional_degrees(values):
            steps = np.rint(values / SCAN_ANGLE_STEP)
            if np.abs(steps * SCAN_ANGLE_STEP - values).max() <= 1e-6 * max(1.0, np.abs(values).max()):
                out["scan_angle"] = steps.astype(np.int16)  # LAS 1.4 units of 0.006 degrees, exact
            else:
                out["scan_angle_degrees"] = values  # finer than the LAS field: kept as degrees
            continue
        out[name] = _text_dtype(name, values, path)
    return out


_SCAN_ANGLE_NAMES = {"scan_angle_rank", "scan_angle", "scan_angle_degrees"}  # one text column, three names


def _wanted(column: str, keep) -> bool:
    """Is a text column asked for? A scan-angle column answers to each name it may be read under."""
    if keep is None or column in keep:
        return True
    return column == "scan_angle_rank" and bool(keep & _SCAN_ANGLE_NAMES)


def _fractional_degrees(values: np.ndarray) -> bool:
    """Finite angles within +-180 degrees that are not all whole numbers."""
    return bool(values.size and np.isfinite(values).all() and np.abs(values).max() <= 180.0
                and not np.array_equal(values, np.round(values)))


def _text_dtype(name: str, values: np.ndarray, path: Path) -> np.ndarray:
    """Known dimensions get laspy's dtype, other integral columns int64, the rest float64."""
    finite = np.isfinite(values).all()
    integral = finite and np.array_equal(values, np.round(values))
    target = _STANDARD_DTYPES.get(name)
    if target is not None and np.issubdtype(target, np.integer):
        info = np.iinfo(target)
        if not integral or (values.size and (values.min() < info.min or values.max() > info.max)):
            raise CloudFileError(f"{path}: column {name!r} must hold integers in {info.min}..{info.max}")
        return values.astype(target)
    if target is None and integral and values.size and np.abs(values).max() < 2**53:
        return values.astype(np.int64)
    return values


# ---------------------------------------------------------------------------- PLY
def _read_ply(path: Path, flt: _Filter, keep, chunk_size: int):
    """Vertex x, y, z and scalar properties of an ASCII or binary PLY file (see ``labkit._ply``)."""
    from ._ply import ply_vertex_blocks

    names, fmt, blocks = ply_vertex_blocks(path, chunk_size)
    columns = [_canonical(n) for n in names]
    if len(set(columns)) != len(columns):
        raise CloudFileError(f"{path}: the PLY vertex element repeats a property ({names})")
    missing = [c for c in "xyz" if c not in columns]
    if missing:
        raise CloudFileError(f"{path}: the PLY vertex element has no property {', '.join(missing)}")
    ix = [columns.index(c) for c in "xyz"]
    extra = [(i, c) for i, c in enumerate(columns) if c not in "xyz" and _wanted(c, keep)]
    _needs_class(flt, columns, path)
    gather = _Gather(None)
    for block in blocks:  # one array per property
        xyz = np.column_stack([block[i].astype(np.float64) for i in ix])
        cls = block[columns.index("classification")] if flt.classes is not None else None
        mask = flt.mask(xyz, cls)
        sel = slice(None) if mask is None else mask
        gather.add(xyz[sel], {c: block[i][sel] for i, c in extra})
    xyz, attrs = gather.result()
    if fmt == "ascii":  # text: typed like the columns of an ASCII file
        attrs = _text_columns(attrs, path)
    return xyz, attrs, None


# ---------------------------------------------------------------------------- NumPy
def _read_numpy(path: Path, flt: _Filter, keep, chunk_size: int, units: str):
    from ._units import units_from_crs_text

    if path.suffix.lower() == ".npy":
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        xyz, attrs = _split_npy(arr, path)
        crs = None
    else:
        with np.load(path, allow_pickle=False) as z:
            xyz, attrs, crs = _split_npz(z, path)
    check_precision(xyz, f"the coordinates in {path.name}")
    found = units_from_crs_text(crs)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if "units" in z.files:
                found = _units_from_json(str(z["units"]), path)
    found, factors = _to_metres(found, units, path)
    attrs = {k: v for k, v in attrs.items() if keep is None or k in keep}
    _needs_class(flt, attrs, path)
    gather = _Gather(None)
    for start in range(0, len(xyz), chunk_size):
        part = np.array(xyz[start : start + chunk_size], dtype=np.float64)
        if factors is not None:
            part *= factors
        cls = np.asarray(attrs["classification"][start : start + chunk_size]) if flt.classes is not None else None
        mask = flt.mask(part, cls)
        sel = slice(None) if mask is None else mask
        gather.add(part[sel], {k: np.asarray(v[start : start + chunk_size])[sel] for k, v in attrs.items()})
    out_xyz, out_attrs = gather.result()
    return out_xyz, out_attrs, crs, found


def _split_npy(arr: np.ndarray, path: Path):
    if arr.dtype.names:
        names = {n.lower(): n for n in arr.dtype.names}
        if not all(c in names for c in "xyz"):
            raise CloudFileError(f"{path}: a structured array needs fields x, y, z (has {arr.dtype.names})")
        xyz = np.column_stack([arr[names[c]] for c in "xyz"])
        attrs = {_canonical(n): arr[n] for n in arr.dtype.names if n.lower() not in "xyz"}
        return xyz, attrs
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise CloudFileError(f"{path}: expected a numeric (n, 3+) array, got shape {arr.shape} of {arr.dtype}")
    return arr[:, :3], {f"column_{i}": arr[:, i] for i in range(3, arr.shape[1])}


def _split_npz(z, path: Path):
    keys = set(z.files)
    if "xyz" in keys:
        xyz = z["xyz"]
        used = {"xyz"}
    elif {"x", "y", "z"} <= keys:
        xyz = np.column_stack([z[c] for c in "xyz"])
        used = {"x", "y", "z"}
    else:
        raise CloudFileError(f"{path}: an .npz cloud needs an 'xyz' array or 'x', 'y', 'z' arrays (has {sorted(keys)})")
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"{path}: 'xyz' must have shape (n, 3), got {xyz.shape}")
    crs = str(z["crs"]) if "crs" in keys and z["crs"].size else None
    attrs = {}
    for k in sorted(keys - used - {"crs", "name", "units"}):
        v = z[k]
        if v.ndim != 1 or len(v) != len(xyz):
            raise CloudFileError(f"{path}: array {k!r} has shape {v.shape}, expected ({len(xyz)},)")
        attrs[k] = v
    return xyz, attrs, crs


# ============================================================================ many files
def cloud_files(paths) -> list[Path]:
    """The point-cloud files named by ``paths``: a file, a folder (its LAS/LAZ files), a glob, or a list of these.

    Sorted by name within each entry, without duplicates. Raises
    :class:`CloudFileError` when an entry names no file.
    """
    entries = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not entries:
        raise CloudFileError("no point-cloud files given")
    out, seen = [], set()
    for entry in entries:
        if not isinstance(entry, (str, os.PathLike)):
            raise CloudFileError(f"a file, folder or glob pattern (str or Path) is needed, got {type(entry).__name__}")
        found = _expand(Path(entry))
        if not found:
            raise CloudFileError(f"no point-cloud file matches {entry}")
        for f in found:
            if f.resolve() not in seen:
                seen.add(f.resolve())
                out.append(f)
    return out


def _expand(entry: Path) -> list[Path]:
    if entry.is_dir():
        return sorted(p for p in entry.iterdir() if p.is_file() and p.suffix.lower() in LAS_SUFFIXES)
    if any(ch in str(entry) for ch in "*?["):
        anchor = Path(entry.anchor) if entry.is_absolute() else Path(".")
        pattern = str(entry.relative_to(anchor)) if entry.is_absolute() else str(entry)
        return sorted(p for p in anchor.glob(pattern) if p.is_file())
    return [_existing(entry)]


def files_in_box(paths, bbox) -> list[Path]:
    """The LAS/LAZ files whose header extent meets ``bbox`` (no point is read).

    Parameters
    ----------
    paths : file, folder, glob or list of these
        See :func:`cloud_files`.
    bbox : sequence
        ``(xmin, ymin, xmax, ymax)`` or ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in
        the files' stored units (a box in metres against files in feet would miss).

    Returns
    -------
    list of Path
        In the order of :func:`cloud_files`; other formats (no header bounds) are always kept.
    """
    box = regions.as_bbox(bbox)
    return [p for p in cloud_files(paths) if _header_meets(p, box, None)]


def _header_meets(path: Path, box: np.ndarray | None, factors_for) -> bool:
    """True unless a LAS/LAZ header proves that the file lies outside the box."""
    if box is None or path.suffix.lower() not in LAS_SUFFIXES:
        return True
    info = cloud_info(path)
    if info.point_count == 0:
        return False
    f = np.ones(3)
    if factors_for is not None:
        f = factors_for(info)
    lo, hi = info.mins * f, info.maxs * f
    d = box.shape[1]
    return bool((box[0] <= hi[:d]).all() and (box[1] >= lo[:d]).all())


def read_clouds(paths, *, bbox=None, polygon=None, classes=None, attributes=None,
                chunk_size: int = DEFAULT_CHUNK, progress=False, units: str = "m",
                parallel: bool = True, name: str | None = None) -> PointCloud:
    """Read the part of many files that a box or polygon needs, as one cloud (e.g. a tile and its buffer).

    The LAS/LAZ headers are read first: files whose extent misses the area are
    skipped without reading a point; the others are read chunk by chunk with the
    filter applied to every chunk (see :func:`read_cloud`), so only the kept
    points are held.

    Parameters
    ----------
    paths : file, folder, glob or list of these
        See :func:`cloud_files`.
    bbox, polygon, classes, attributes, chunk_size, progress, units, parallel
        As in :func:`read_cloud`; ``bbox`` and ``polygon`` in the cloud's units (metres by default).
    name : str, optional
        Name of the merged cloud (default: the single file's stem, else ``"<first>+<k> files"``).

    Returns
    -------
    PointCloud
        The kept points of all files; attributes are those every read file has
        (or exactly ``attributes``).

    Raises
    ------
    CloudFileError
        No file, a bad file, or files whose CRS or units differ.
    EmptyRegionError
        No file meets the area, or the filters keep no point.
    """
    files = cloud_files(paths)
    flt = _Filter.build(bbox, polygon, classes)
    area = flt.xy_bounds()
    box = None if area is None else area
    if flt.box is not None and flt.box.shape[1] == 3 and flt.rings is None:
        box = flt.box  # the z range can rule out a file too
    factors = (lambda info: _header_factors(info, units)) if units == "m" else None
    hits = [p for p in files if _header_meets(p, box, factors)]
    if not hits:
        raise EmptyRegionError(f"{flt.describe()} meets none of the {len(files)} file(s) (by their header extents)")
    clouds = []
    for path in hits:
        try:
            clouds.append(read_cloud(path, bbox=bbox, polygon=polygon, classes=classes, attributes=attributes,
                                     chunk_size=chunk_size, progress=progress, units=units, parallel=parallel))
        except EmptyRegionError:
            if not flt.active:
                raise
    if not clouds:
        raise EmptyRegionError(f"{flt.describe()} keeps no point of the {len(hits)} file(s) whose extent it meets")
    label = name or (clouds[0].name if len(clouds) == 1 else f"{clouds[0].name}+{len(clouds) - 1} files")
    return _merge(clouds, label)


def _header_factors(info: "CloudInfo", units: str) -> np.ndarray:
    """Metres per stored unit of a header (ones when nothing is converted)."""
    try:
        _, factors = _to_metres(info.units, units, info.path)
    except UnitsError:
        return np.ones(3)  # read_cloud raises the proper error when the file is read
    return np.ones(3) if factors is None else factors


def _merge(clouds: list, name: str) -> PointCloud:
    """One cloud from several with the same CRS and units; the attributes all of them have."""
    first = clouds[0]
    for c in clouds[1:]:
        if c.crs != first.crs:
            raise CloudFileError(f"files {first.name!r} and {c.name!r} have different CRS ({first.crs!r} vs {c.crs!r})")
        if c.units.coordinates != first.units.coordinates:
            raise CloudFileError(f"files {first.name!r} and {c.name!r} hold coordinates in different units "
                                 f"({first.units.label()} vs {c.units.label()})")
    if len(clouds) == 1:
        return PointCloud._adopt(first.xyz, dict(first.attributes), crs=first.crs, name=name, units=first.units)
    common = [k for k in first.attributes if all(k in c.attributes for c in clouds[1:])]
    xyz = np.concatenate([c.xyz for c in clouds])
    attrs = {}
    for k in common:
        dtype = np.result_type(*(c.attributes[k].dtype for c in clouds))
        attrs[k] = np.concatenate([c.attributes[k].astype(dtype, copy=False) for c in clouds])
    return PointCloud._adopt(xyz, attrs, crs=first.crs, name=name, units=first.units)


# ============================================================================ header summary
@dataclass(frozen=True, eq=False, repr=False)
class CloudInfo(ReportMixin):
    """What a LAS/LAZ header says, read without loading the points."""

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
    """Header of a LAS/LAZ file (count, bounds, scale, offset, CRS, dimensions) without reading points."""
    path = _existing(path)
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


# ============================================================================ writing
DEFAULT_SCALE = 0.001  # metres (or the file's linear unit)
ANGULAR_SCALE = 1e-7  # degrees: about 1 cm on the ground


def write_cloud(cloud: PointCloud, path, *, scale=DEFAULT_SCALE, point_format: int | None = None,
                chunk_size: int = DEFAULT_CHUNK, progress=False, parallel: bool = True) -> Path:
    """Write a cloud to LAS/LAZ, ASCII (CSV/TXT/XYZ) or ``.npz``, atomically.

    Parameters
    ----------
    cloud : PointCloud
    path : str or Path
        The suffix picks the format: ``.las .laz .csv .txt .xyz .asc .npz``.
    scale : float, sequence of 3 floats or None
        Coordinate resolution in the file's units (metres, or the CRS's feet
        for a cloud converted from feet): LAS scale factors, decimals in text.
        Default 0.001 (rounding error at most 0.5 mm); for a cloud in degrees
        the default is 1e-7 degrees for x, y (about 1 cm). ``None`` picks, per
        axis, the coarsest decimal grid the coordinates already lie on (so a
        cloud read from a LAS file is written back without rounding), and 0.0001 m
        when they lie on none.
    point_format : int, optional
        LAS point format. By default the smallest of 0-3 (LAS 1.2) that holds
        the attributes, or 6-8 (LAS 1.4) when values need it (classes > 31,
        more than 7 returns, nir, scan_angle, overlap, scanner_channel).
    chunk_size : int
        Points written per chunk (LAS/LAZ and text); only one chunk of LAS
        integers is held at a time.
    progress : bool, "bar", "lines" or callable
        Report the chunks written (see :mod:`labkit.progress`); default silent.
    parallel : bool
        Compress LAZ on all cores (lazrs); ``False`` uses one core.

    Returns
    -------
    Path
        The written file.

    Notes
    -----
    LAS offsets are the data minimum rounded down to a multiple of 1000 m, so
    UTM coordinates keep the whole int32 range for the fraction. Attributes
    that are not dimensions of the point format become LAS extra bytes (names
    of at most 32 characters, unique within those 32). The CRS text is written
    as a WKT VLR (WKT) or GeoTIFF keys (``EPSG:code``, with the unit keys of
    ``cloud.units``). A cloud converted from feet on reading is written to
    LAS/LAZ/NPZ in its CRS's units again; text files get the coordinates as held.
    Integer attributes must fit their LAS field (e.g. intensity 0..65535,
    classification 0..31 in formats 0-5): values outside raise, they never wrap.
    """
    if not isinstance(cloud, PointCloud):
        raise LabkitError(f"write_cloud needs a PointCloud, got {type(cloud).__name__}")
    if not isinstance(path, (str, os.PathLike)) or (isinstance(path, str) and not path.strip()):
        raise CloudFileError(f"write_cloud needs a file path (str or Path), got {path!r}")
    chunk_size = _positive_int(chunk_size, "chunk_size")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LAS_SUFFIXES + ASCII_SUFFIXES + (".npz",):
        raise CloudFileError(_unsupported(path) + " (writing: .las .laz .csv .txt .xyz .asc .npz)")
    if not path.parent.is_dir():
        raise CloudFileError(f"cannot write {path}: folder {path.parent} does not exist")
    if suffix in LAS_SUFFIXES + (".npz",):
        cloud = _in_file_units(cloud)
    if scale is DEFAULT_SCALE and cloud.units.angular:  # 0.001 degrees would be about 100 m
        scale = (ANGULAR_SCALE, ANGULAR_SCALE, DEFAULT_SCALE)
    scales = _choose_scale(cloud.xyz, scale)
    with _atomic(path) as tmp:
        if suffix in LAS_SUFFIXES:
            _write_las(cloud, tmp, suffix == ".laz", scales, point_format, chunk_size, progress, parallel, path.name)
        elif suffix == ".npz":
            _write_npz(cloud, tmp)
        else:
            _write_ascii(cloud, tmp, "," if suffix == ".csv" else " ", scales, chunk_size, progress, path.name)
    return path


def _in_file_units(cloud: PointCloud) -> PointCloud:
    """The cloud in its CRS's own units (undoes the conversion to metres made on reading)."""
    u = cloud.units
    if not (u.converted and cloud.crs and u.factors is not None):
        return cloud
    return PointCloud(cloud.xyz / u.factors, cloud.attributes, crs=cloud.crs, name=cloud.name,
                      units=replace(u, converted=False))


@contextlib.contextmanager
def _atomic(path: Path):
    """Write through a temporary file next to ``path`` (see ``labkit._atomic``); OS errors as CloudFileError."""
    try:
        with atomic_path(path) as tmp:
            yield tmp
    except OSError as exc:
        raise CloudFileError(f"cannot write {path}: {exc}") from exc


def _choose_scale(xyz: np.ndarray, scale) -> np.ndarray:
    """Per-axis coordinate resolution (m)."""
    if scale is None:
        return np.array([_grid_step(xyz[:, j]) for j in range(3)])
    try:
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy() if np.ndim(scale) <= 1 else None
    except (TypeError, ValueError):
        s = None
    if isinstance(scale, (bool, np.bool_, str, bytes)):
        s = None
    if s is None or s.shape != (3,) or not np.isfinite(s).all() or (s <= 0).any():
        raise LabkitError(f"scale must be a positive number, three positive numbers or None, got {scale!r}")
    return s


def _grid_step(values: np.ndarray) -> float:
    """The coarsest step 10^-k (k = 0..4) on which all values lie, else 1e-4."""
    if values.size == 0:
        return 0.001
    base = np.floor(values.min())
    for k in range(5):
        q = (values - base) * 10.0**k
        if np.abs(q - np.rint(q)).max() < 1e-3:
            return 10.0**-k
    return 1e-4


def _las_offsets(xyz: np.ndarray, scales=None) -> np.ndarray:
    """Offsets at whole kilometres below the data (UTM-friendly, exact in binary).

    Where that leaves too little int32 range at a fine scale (e.g. 1e-7 degrees),
    the offset is the whole unit below the data instead.
    """
    if len(xyz) == 0:
        return np.zeros(3)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    offsets = np.floor(lo / 1000.0) * 1000.0
    if scales is not None:
        tight = (hi - offsets) / np.asarray(scales) > 0.9 * _INT32_MAX
        offsets[tight] = np.floor(lo[tight])
    return offsets


def _auto_format(attrs: dict) -> int:
    big = lambda k, m: k in attrs and attrs[k].size and attrs[k].max() > m  # noqa: E731
    new = {"nir", "scan_angle", "overlap", "scanner_channel"} & set(attrs)
    if new or big("classification", 31) or big("return_number", 7) or big("number_of_returns", 7):
        return 8 if "nir" in attrs else 7 if "red" in attrs else 6
    return {(False, False): 0, (True, False): 1, (False, True): 2, (True, True): 3}[("gps_time" in attrs, "red" in attrs)]


def _write_las(cloud, tmp: Path, compress: bool, scales, point_format, chunk_size: int, progress=False,
               parallel: bool = True, label: str = "") -> None:
    import laspy

    attrs = _las_attributes(cloud.attributes, point_format)
    fmt_id = _auto_format(attrs) if point_format is None else int(point_format)
    if fmt_id not in range(11):
        raise LabkitError(f"point_format must be 0..10, got {point_format!r}")
    version = "1.2" if fmt_id <= 3 else "1.3" if fmt_id <= 5 else "1.4"
    header = laspy.LasHeader(version=version, point_format=fmt_id)
    header.scales, header.offsets = scales, _las_offsets(cloud.xyz, scales)
    header.generating_software = "labkit"
    standard = set(header.point_format.dimension_names)
    _check_extra_names([n for n in attrs if n not in standard])
    for name, values in attrs.items():
        if name in standard:
            _check_fits(name, values, header.point_format.dimension_by_name(name), fmt_id)
        else:
            header.add_extra_dim(laspy.ExtraBytesParams(name=name[:32], type=_extra_dtype(name, values)))
    _add_crs(header, cloud.crs, cloud.units)
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
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    q = np.rint((np.vstack([lo, hi]) - np.asarray(offsets)) / np.asarray(scales))
    if np.abs(q).max() > _INT32_MAX:
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


def _units_from_json(text: str, path: Path) -> Units:
    import json

    try:
        fields = json.loads(text)
        return Units(**{k: v for k, v in fields.items() if k != "converted"})
    except (ValueError, TypeError) as exc:
        raise CloudFileError(f"{path}: unreadable 'units' entry: {exc}") from None


def _write_npz(cloud: PointCloud, tmp: Path) -> None:
    import dataclasses
    import json

    reserved = sorted({"xyz", "x", "y", "z", "crs", "name", "units"} & set(cloud.attributes))
    if reserved:
        raise LabkitError(f"attribute name(s) {reserved} are reserved in an .npz cloud file: rename them")
    arrays = {"xyz": cloud.xyz, **cloud.attributes}
    if cloud.crs:
        arrays["crs"] = np.array(cloud.crs)
    if cloud.units.known:
        arrays["units"] = np.array(json.dumps(dataclasses.asdict(cloud.units)))
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def _write_ascii(cloud: PointCloud, tmp: Path, delimiter: str, scales: np.ndarray, chunk_size: int,
                 progress=False, label: str = "") -> None:
    names = list(cloud.attributes)
    decimals = [max(0, int(np.ceil(-np.log10(s) - 1e-9))) for s in scales]
    fmts = [f"%.{d}f" for d in decimals]
    for name in names:
        kind = cloud[name].dtype.kind
        if kind not in "biuf" or cloud[name].ndim != 1:
            raise LabkitError(f"attribute {name!r} ({cloud[name].dtype}) cannot be written as a text column")
        fmts.append("%d" if kind in "biu" else "%.15g")
    with open(tmp, "w", encoding="utf-8", newline="\n") as f, \
            progress_steps(progress, len(cloud), f"writing {label or tmp.name}", "pts") as step:
        f.write(delimiter.join(["x", "y", "z"] + names) + "\n")
        for start in range(0, len(cloud), chunk_size):
            sl = slice(start, start + chunk_size)
            cols = [cloud.xyz[sl, j] for j in range(3)] + [cloud[n][sl] for n in names]
            table = np.empty((len(cols[0]), len(cols)), dtype=object)
            for j, col in enumerate(cols):
                table[:, j] = col
            np.savetxt(f, table, fmt=fmts, delimiter=delimiter)
            step(len(table))
