"""``write_cloud``: a cloud to LAS/LAZ, ASCII or ``.npz``, atomically."""

from __future__ import annotations

import contextlib
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..core.atomic import atomic_path
from ..core.checks import count
from ..cloud import PointCloud
from ..core.errors import CloudFileError, LabkitError
from .ascii import write_ascii
from .common import ASCII_SUFFIXES, DEFAULT_CHUNK, LAS_SUFFIXES, unsupported_format
from .las_write import transform_las, write_las
from .npy import write_npz


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
        Default: the scale of the LAS file the cloud was read from (so nothing is
        rounded away), else 0.001 (rounding error at most 0.5 mm); for a cloud in
        degrees 1e-7 degrees for x, y (about 1 cm). ``None`` picks, per
        axis, the coarsest decimal grid the coordinates already lie on (so a
        cloud read from a LAS file is written back without rounding), and 0.0001 m
        when they lie on none.
    point_format : int, optional
        LAS point format. A cloud read from LAS/LAZ is written by default in its
        file's layout: LAS version, point format, extra-bytes types, VLRs (CRS),
        offsets where the coordinates still fit them. Otherwise the smallest of 0-3 (LAS 1.2) that holds
        the attributes, or 6-8 (LAS 1.4) when values need it (classes > 31,
        more than 7 returns, nir, scan_angle, overlap, scanner_channel).
    chunk_size : int
        Points written per chunk (LAS/LAZ and text); only one chunk of LAS
        integers is held at a time.
    progress : bool, "bar", "lines" or callable
        Report the chunks written (see :mod:`labkit.core.progress`); default silent.
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

    References
    ----------
    .. [1] Notebook 03, section 8 (CSV export) and eqs. 1-3 (the LAS scale and
       offset); the registration study, step 1.
    .. [2] ASPRS (2019): LAS Specification 1.4 - R15.

    Examples
    --------
    >>> import tempfile
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.io import read_cloud, write_cloud
    >>> cloud = PointCloud(np.array([[600000.0, 5400000.0, 300.0], [600001.5, 5400002.25, 301.0]]),
    ...                {"intensity": np.array([10, 20], dtype=np.uint16)}, crs="EPSG:25832")
    >>> path = write_cloud(cloud, f"{tempfile.mkdtemp()}/two.laz")
    >>> back = read_cloud(path)
    >>> back.xyz.tolist(), back["intensity"].tolist(), back.crs
    ([[600000.0, 5400000.0, 300.0], [600001.5, 5400002.25, 301.0]], [10, 20], 'EPSG:25832')
    """
    if not isinstance(cloud, PointCloud):
        raise LabkitError(f"write_cloud needs a PointCloud, got {type(cloud).__name__}")
    if not isinstance(path, (str, os.PathLike)) or (isinstance(path, str) and not path.strip()):
        raise CloudFileError(f"write_cloud needs a file path (str or Path), got {path!r}")
    chunk_size = count(chunk_size, "chunk_size")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LAS_SUFFIXES + ASCII_SUFFIXES + (".npz",):
        raise CloudFileError(unsupported_format(path) + " (writing: .las .laz .csv .txt .xyz .asc .npz)")
    if not path.parent.is_dir():
        raise CloudFileError(f"cannot write {path}: folder {path.parent} does not exist")
    if suffix in LAS_SUFFIXES + (".npz",):
        cloud = _in_file_units(cloud)
    if scale is DEFAULT_SCALE and cloud.layout is not None:  # the scale of the file it was read from
        scale = cloud.layout.scales
        if suffix not in LAS_SUFFIXES + (".npz",) and cloud.units.converted and cloud.units.factors is not None:
            scale = scale * cloud.units.factors  # text holds metres: the file's resolution in metres
    elif scale is DEFAULT_SCALE and cloud.units.angular:  # 0.001 degrees would be about 100 m
        scale = (ANGULAR_SCALE, ANGULAR_SCALE, DEFAULT_SCALE)
    scales = _choose_scale(cloud.xyz, scale)
    with _atomic(path) as tmp:
        if suffix in LAS_SUFFIXES:
            write_las(cloud, tmp, suffix == ".laz", scales, point_format, chunk_size, progress, parallel, path.name)
        elif suffix == ".npz":
            write_npz(cloud, tmp)
        else:
            write_ascii(cloud, tmp, "," if suffix == ".csv" else " ", scales, chunk_size, progress, path.name)
    return path


def _in_file_units(cloud: PointCloud) -> PointCloud:
    """The cloud in its CRS's own units (undoes the conversion to metres made on reading)."""
    u = cloud.units
    if not (u.converted and cloud.crs and u.factors is not None):
        return cloud
    return PointCloud(cloud.xyz / u.factors, cloud.attributes, crs=cloud.crs, name=cloud.name,
                      units=replace(u, converted=False), layout=cloud.layout)


@contextlib.contextmanager
def _atomic(path: Path):
    """Write through a temporary file next to ``path`` (see ``labkit.core.atomic``); OS errors as CloudFileError."""
    try:
        with atomic_path(path) as tmp:
            yield tmp
    except OSError as exc:
        raise CloudFileError(f"cannot write {path}: {exc}") from exc
    except LabkitError:
        raise
    except Exception as exc:  # the LAZ compressor's errors (e.g. LazrsError on a full disk)
        raise CloudFileError(f"cannot write {path}: {type(exc).__name__}: {exc}") from exc


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


def write_moved(source, path, transform, *, chunk_size: int = DEFAULT_CHUNK, progress=False,
                parallel: bool = True) -> Path | None:
    """The LAS/LAZ file ``source`` moved by ``transform``, written to ``path`` chunk by chunk, atomically.

    The same file as ``write_cloud(read_cloud(source).with_xyz(transform(cloud.xyz)), path)``
    (the file's layout, attributes and scales, only X, Y, Z changed) without holding the cloud
    or its attributes in memory: ``labkit register`` writes the moved source this way.
    ``transform`` maps (m, 3) coordinates in metres (as :func:`labkit.io.read_cloud` reads them).
    Returns None, and writes nothing, when the moved points leave the int32 range of the
    file's offsets (write the cloud with :func:`write_cloud` then: it chooses new offsets).

    References
    ----------
    .. [1] Notebook 03, eqs. 1-3 (LAS scale and offset).
    .. [2] ASPRS (2019): LAS Specification 1.4 - R15.

    Examples
    --------
    A tile of the synthetic survey (its intensities kept) lifted by 20 cm:

    >>> import tempfile
    >>> from labkit.io import read_cloud
    >>> from labkit.io.write import write_moved
    >>> from labkit.synthetic import tile_row
    >>> src = tile_row(1) / "t0.laz"
    >>> out = write_moved(src, f"{tempfile.mkdtemp()}/moved.laz", lambda xyz: xyz + [0.0, 0.0, 0.2])
    >>> before, after = read_cloud(src), read_cloud(out)
    >>> (after.xyz - before.xyz).round(3).max(axis=0).tolist(), sorted(after.attributes) == sorted(before.attributes)
    ([0.0, 0.0, 0.2], True)
    """
    source, path = Path(source), Path(path)
    if source.suffix.lower() not in LAS_SUFFIXES or path.suffix.lower() not in LAS_SUFFIXES:
        raise LabkitError(f"write_moved copies a LAS/LAZ file into a LAS/LAZ file, not {source.name} -> {path.name}")
    if not path.parent.is_dir():
        raise CloudFileError(f"cannot write {path}: folder {path.parent} does not exist")
    try:
        with _atomic(path) as tmp:
            if transform_las(source, tmp, transform, chunk_size=count(chunk_size, "chunk_size"), progress=progress,
                             parallel=parallel) is None:
                raise _DoesNotFit
    except _DoesNotFit:
        return None
    return path


class _DoesNotFit(LabkitError):
    """The moved points leave the range of the file's offsets (nothing is written)."""
