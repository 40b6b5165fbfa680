"""Many files: expanding folders and globs, choosing files by their LAS headers, reading them as one cloud."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..core import masks
from ..cloud import PointCloud
from ..core.units import UnitsError
from ..core.errors import CloudFileError, EmptyRegionError
from .common import DEFAULT_CHUNK, LAS_SUFFIXES, existing_file
from .filter import ReadFilter
from .las import CloudInfo, cloud_info, to_metres
from .read import read_cloud


def cloud_files(paths) -> list[Path]:
    """The point-cloud files named by ``paths``: a file, a folder (its LAS/LAZ files), a glob, or a list of these.

    Sorted by name within each entry, without duplicates. Raises
    :class:`CloudFileError` when an entry names no file.

    Examples
    --------
    >>> from labkit.io import cloud_files
    >>> from labkit.synthetic import tile_row
    >>> folder = tile_row(3)  # t0.laz, t1.laz, t2.laz
    >>> [p.name for p in cloud_files(folder)]
    ['t0.laz', 't1.laz', 't2.laz']
    >>> [p.name for p in cloud_files(str(folder / "t[12].laz"))]
    ['t1.laz', 't2.laz']
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
    return [existing_file(entry)]


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

    Examples
    --------
    >>> from labkit.io import files_in_box
    >>> from labkit.synthetic import tile_row
    >>> folder = tile_row(3)  # three 10 m tiles in a row along x
    >>> [p.name for p in files_in_box(folder, (12, 0, 25, 5))]
    ['t1.laz', 't2.laz']
    """
    box = masks.as_bbox(bbox)
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

    Examples
    --------
    >>> from labkit.io import read_clouds
    >>> from labkit.synthetic import tile_row
    >>> folder = tile_row(3)  # three 10 m tiles in a row along x, a point every metre
    >>> part = read_clouds(folder, bbox=(8, -1, 12, 1))
    >>> part.xyz[:, 0].tolist(), part.name
    ([8.0, 9.0, 10.0, 11.0, 12.0], 't0+1 files')
    """
    files = cloud_files(paths)
    flt = ReadFilter.build(bbox, polygon, classes)
    area = flt.xy_bounds()
    box = None if area is None else area
    if flt.box is not None and flt.box.shape[1] == 3 and flt.rings is None:
        box = flt.box  # the z range can rule out a file too
    factors = (lambda info: header_factors(info, units)) if units == "m" else None
    hits = [p for p in files if _header_meets(p, box, factors)]
    by_header = bool(hits)
    if not hits:  # before "empty" is said, the points themselves are asked: a header's bounds may be wrong
        hits = files
    clouds = []
    for path in hits:
        try:
            clouds.append(read_cloud(path, bbox=bbox, polygon=polygon, classes=classes, attributes=attributes,
                                     chunk_size=chunk_size, progress=progress, units=units, parallel=parallel))
        except EmptyRegionError:
            if not flt.active:
                raise
    if not clouds:
        where = "whose extent it meets" if by_header else "(no header extent meets it; the points were read)"
        raise EmptyRegionError(f"{flt.describe()} keeps no point of the {len(hits)} file(s) {where}")
    label = name or (clouds[0].name if len(clouds) == 1 else f"{clouds[0].name}+{len(clouds) - 1} files")
    return _merge(clouds, label)


def header_factors(info: "CloudInfo", units: str) -> np.ndarray:
    """Metres per stored unit of a header (ones when nothing is converted)."""
    try:
        _, factors = to_metres(info.units, units, info.path)
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
    return PointCloud.concatenate(clouds, name=name, crs=first.crs, units=first.units)
