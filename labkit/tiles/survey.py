"""The survey of one epoch: LAS/LAZ files with their header extents (read per tile), or points in memory."""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.checks import as_points
from ..core.arrays import extent, rows
from ..core.errors import CloudFileError, EmptyRegionError, LabkitError
from ..io import LAS_SUFFIXES, cloud_files, cloud_info, read_cloud
from ..io.many import header_factors
from ..regions import merge
from .grid import Tile


@dataclass(frozen=True, eq=False)
class _Files:
    """LAS/LAZ files with their header extents (xmin, ymin, xmax, ymax)."""

    paths: tuple
    extents: np.ndarray
    classes: tuple | None = None

    def bounds(self) -> np.ndarray:
        return np.r_[self.extents[:, :2].min(axis=0), self.extents[:, 2:].max(axis=0)]

    def for_tile(self, tile: Tile) -> "_Files":
        x0, y0, x1, y1 = tile.read_bounds
        e = self.extents
        hit = (e[:, 0] <= x1) & (e[:, 2] >= x0) & (e[:, 1] <= y1) & (e[:, 3] >= y0)
        return _Files(tuple(p for p, h in zip(self.paths, hit) if h), e[hit], self.classes)

    def load(self, tile: Tile):
        """The tile's points from each file (whole files kept in this process's cache, see :class:`_FileCache`)."""
        parts = [c.subset(tile.contains(c.xyz)) for c in (_FILES.get(p, self.classes) for p in self.paths)]
        return _concat([c for c in parts if len(c)])


class _FileCache:
    """The clouds of recently read LAS/LAZ files in this process, up to ``budget`` bytes (least recently used out).

    Survey files are cut at the grid lines, and the quantised coordinates of a file
    may end exactly on its neighbour's line, so a tile touches its own file and up to
    eight neighbours. Reading (decompressing) each of them per tile costs five to nine
    times the tile's own file; kept whole here, a file is decompressed about once per
    worker. A tile keeps the same points in the same order as a read with a box filter:
    :meth:`Tile.contains` lies inside that closed box. Keyed by path, size, modification
    time and class filter, so a changed file is read again.
    """

    def __init__(self, budget: int):
        self.budget, self._items, self._lock = int(budget), OrderedDict(), threading.Lock()

    def get(self, path: str, classes):
        st = os.stat(path)
        key = (str(path), st.st_size, st.st_mtime_ns, classes)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        cloud = read_cloud(path, classes=classes)
        with self._lock:
            self._items[key] = cloud
            while len(self._items) > 1 and sum(_nbytes(c) for c in self._items.values()) > self.budget:
                self._items.popitem(last=False)
        return cloud


def _nbytes(cloud) -> int:
    return int(cloud.xyz.nbytes + sum(np.asarray(v).nbytes for v in getattr(cloud, "attributes", {}).values()))


_FILES = _FileCache(512 * 2**20)  # about 50 files of 200,000 points with their attributes


def _survey(data, classes=None, name: str = "survey"):
    """PointCloud/array -> itself; path, folder, glob or a list of these -> _Files (LAS/LAZ lazily, others read now).

    A class filter on points without a ``classification`` attribute (an array, or a
    cloud read from a format without classes) is refused rather than ignored, and so
    are LAS/LAZ files whose headers name different CRS (a tile would join them).
    """
    if isinstance(data, (str, Path)) or (isinstance(data, (list, tuple)) and data
                                         and all(isinstance(p, (str, Path)) for p in data)):
        paths = cloud_files(data)  # files, folders (their LAS/LAZ files) and globs
        if all(p.suffix.lower() in LAS_SUFFIXES for p in paths):
            infos = [cloud_info(p) for p in paths]  # headers only
            crs = sorted({i.crs for i in infos if i.crs})
            if len(crs) > 1:
                raise CloudFileError(f"the {name} files are in different reference systems: {crs}; "
                                     "reproject them to one CRS first")
            return _Files(tuple(str(p) for p in paths), np.array([_extent(i) for i in infos]),
                          None if classes is None else tuple(classes))
        return _concat([read_cloud(p, classes=classes) for p in paths])
    if classes is None:
        return data
    if "classification" not in getattr(data, "attributes", {}):
        what = "an array" if not hasattr(data, "attributes") else "a PointCloud"
        raise LabkitError(f"classes={list(classes)} needs a 'classification' attribute, but the {name} is {what} "
                          "without one; pass a PointCloud (or LAS/LAZ files) with classes, or classes=None")
    return data.subset(np.isin(data["classification"], list(classes)))


def _extent(info) -> tuple:
    """(xmin, ymin, xmax, ymax) in metres from a LAS header (:func:`labkit.io.cloud_info`).

    The header stores the file's own units; the tiles cut the points that
    :func:`labkit.io.read_cloud` returns, which are in metres (feet converted from the
    file's CRS), so the extent is converted the same way.
    """
    f = header_factors(info, "m")
    return (float(info.mins[0] * f[0]), float(info.mins[1] * f[1]),
            float(info.maxs[0] * f[0]), float(info.maxs[1] * f[1]))


def _bounds_of(data, name: str) -> np.ndarray:
    if isinstance(data, _Files):
        return data.bounds()
    if len(data) == 0:
        raise EmptyRegionError(f"the {name} survey has no points (after the class filter, if any)")
    xyz = as_points(data, name=f"{name} survey")
    return np.r_[extent(xyz[:, :2])]


def _for_tile(data, tile: Tile):
    """What a tile task receives: the file list to read, or the points already cut out."""
    if isinstance(data, _Files):
        return data.for_tile(tile)
    xyz = as_points(data, name="survey cloud")
    mask = tile.contains(xyz)
    return data.subset(mask) if hasattr(data, "subset") else rows(xyz, mask)


def _cut_all(data, tiles: tuple) -> list:
    """``_for_tile`` for every tile; in-memory points are binned to grid cells once.

    Masking the whole cloud per tile costs tiles x points; instead each point gets
    its cell index, and a tile tests only the points of the cells its buffered box
    can reach, with :meth:`Tile.contains` (so the result is the same as per tile).
    """
    if isinstance(data, _Files) or not tiles:
        return [_for_tile(data, t) for t in tiles]
    xyz = as_points(data, name="survey cloud")
    x0, y0, x1, _ = tiles[0].bounds
    size = x1 - x0
    reach = 1 + int(np.ceil(tiles[0].buffer / size))  # neighbouring cells a buffered box may touch
    ncol, nrow = max(t.col for t in tiles) + 1, max(t.row for t in tiles) + 1
    # (col, row) of each point; points far outside the grid are clamped (Tile.contains still decides)
    col = np.clip(np.floor((xyz[:, 0] - x0) / size), -reach - 1, ncol + reach).astype(np.int64)
    row = np.clip(np.floor((xyz[:, 1] - y0) / size), -reach - 1, nrow + reach).astype(np.int64)
    key = row * (1 << 31) + col
    order = np.argsort(key, kind="stable")
    uniq, start = np.unique(key[order], return_index=True)
    bounds = np.r_[start, len(order)]
    out = []
    for t in tiles:
        keys = [(t.row + dr) * (1 << 31) + (t.col + dc) for dr in range(-reach, reach + 1)
                for dc in range(-reach, reach + 1)]
        pos = np.searchsorted(uniq, keys)
        hit = [p for p, k in zip(pos, keys) if p < len(uniq) and uniq[p] == k]
        idx = np.concatenate([order[bounds[p]:bounds[p + 1]] for p in hit]) if hit else np.zeros(0, int)
        idx = np.sort(idx[t.contains(rows(xyz, idx))])  # the points in their original order
        out.append(data.subset(idx) if hasattr(data, "subset") else rows(xyz, idx))
    return out


def _concat(clouds):
    """The clouds as one (:func:`labkit.regions.merge`: same CRS and units); no cloud -> no points."""
    if not clouds:
        return np.zeros((0, 3))
    return clouds[0] if len(clouds) == 1 else merge(*clouds)
