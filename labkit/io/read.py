"""``read_cloud``: one file of any supported format into a :class:`~labkit.cloud.PointCloud`."""

from __future__ import annotations

import numpy as np

from ..core.checks import choice, count
from ..cloud import PointCloud
from ..core.units import Units
from ..core.errors import CloudFileError, EmptyRegionError, LabkitError
from .ascii import SCAN_ANGLE_NAMES, read_ascii
from .common import (
    ASCII_SUFFIXES, DEFAULT_CHUNK, LAS_SUFFIXES, NUMPY_SUFFIXES, PLY_SUFFIXES, UNIT_CHOICES,
    attribute_names, existing_file, unsupported_format,
)
from .filter import ReadFilter
from .las import read_las
from .npy import read_numpy
from .ply import read_ply


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
        Report the chunks read (see :mod:`labkit.core.progress`): ``True`` shows a
        bar (terminal, notebook) or plain lines on stderr; default silent.
    units : {"m", "native"}
        ``"m"`` (default): coordinates whose CRS states feet are converted to
        metres (per axis: X/Y and Z may differ), and a file in longitude/latitude
        degrees raises :class:`labkit.core.units.UnitsError`. ``"native"``: keep the
        stored values; the cloud records its units and metric steps refuse it.
        Files without a stated unit (no CRS, text, NumPy, PLY) are read as they are.
    parallel : bool
        Decompress LAZ on all cores (lazrs); ``False`` uses one core.

    Returns
    -------
    PointCloud
        Named after the file stem; ``crs`` from the LAS header when present;
        ``units`` (:class:`labkit.core.units.Units`) says what the file states and
        whether the coordinates were converted.

    Raises
    ------
    CloudFileError
        Missing, unreadable, truncated or corrupt file, unsupported suffix; a LAS/LAZ file
        whose header counts other points than the file holds (with or without filters).
        A LAZ file records how many points each chunk holds for point formats 6-10 and
        variable-size chunks, so a wrong count there is always found. For point formats
        0-5 with fixed-size chunks (50,000 points) the last chunk's count is recorded
        nowhere: a header that counts fewer points than the last chunk holds (by less than
        one chunk) cannot be told from a right one, and the header's count is read.
    EmptyRegionError
        The filters keep no point.
    UnitsError
        ``units="m"`` and the file is in degrees (or in a unit with no metre factor).

    References
    ----------
    .. [1] Notebook 03, section 2, eqs. 1-3 (LAS scaled integer coordinates); the registration study, step 1
       (laspy to NumPy).
    .. [2] ASPRS (2019): LAS Specification 1.4 - R15. American Society for Photogrammetry and Remote
       Sensing.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from labkit.io import read_cloud
    >>> path = Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = path.write_text("x,y,z,classification\\n0,0,0,2\\n1,0,0,6\\n5,5,1,2\\n")
    >>> cloud = read_cloud(path)
    >>> len(cloud), cloud["classification"].tolist()
    (3, [2, 6, 2])
    >>> read_cloud(path, bbox=(0, 0, 2, 2), classes=2).xyz.tolist()
    [[0.0, 0.0, 0.0]]
    """
    path = existing_file(path)
    flt = ReadFilter.build(bbox, polygon, classes)
    chunk_size = count(chunk_size, "chunk_size")
    choice(units, UNIT_CHOICES, "units")
    keep = attribute_names(attributes)
    suffix = path.suffix.lower()
    layout = None
    try:
        if suffix in LAS_SUFFIXES:
            xyz, attrs, crs, found, layout = read_las(path, flt, keep, chunk_size, progress, units, parallel)
        elif suffix in ASCII_SUFFIXES:
            xyz, attrs, crs = read_ascii(path, flt, keep, chunk_size, progress)
            found = Units()
        elif suffix in NUMPY_SUFFIXES:
            xyz, attrs, crs, found = read_numpy(path, flt, keep, chunk_size, units)
        elif suffix in PLY_SUFFIXES:
            xyz, attrs, crs = read_ply(path, flt, keep, chunk_size)
            found = Units()
        else:
            raise CloudFileError(unsupported_format(path))
    except (LabkitError, MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # laspy, lazrs, numpy and OS errors of a bad file
        if suffix == ".laz" and not isinstance(exc, OSError):
            raise CloudFileError(f"{path} is a truncated or corrupt LAZ file ({type(exc).__name__}: {exc})") from exc
        raise CloudFileError(f"cannot read {path}: {type(exc).__name__}: {exc}") from exc
    if len(xyz) == 0:
        if flt.active:
            raise EmptyRegionError(f"{flt.describe()} keeps none of the points of {path}")
        raise EmptyRegionError(f"{path} contains no points")
    if not np.isfinite(xyz).all():
        bad = int((~np.isfinite(xyz)).any(axis=1).sum())
        raise CloudFileError(f"{path} has {bad} point(s) with NaN or infinite coordinates")
    missing = set() if keep is None else keep - set(attrs)
    if missing and missing <= SCAN_ANGLE_NAMES and set(attrs) & SCAN_ANGLE_NAMES:
        missing = set()  # a text scan-angle column, read under the name its values need
    if missing:
        raise LabkitError(f"{path} has no attribute {', '.join(sorted(missing))}")
    return PointCloud._adopt(xyz, attrs, crs=crs, name=path.stem, units=found, layout=layout)  # no copy of the fresh arrays
