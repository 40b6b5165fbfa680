"""The grid: square tiles anchored at multiples of their size, and cutting a cloud into tile files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.checks import as_points, count, non_negative, positive
from ..cloud import PointCloud
from ..core.errors import LabkitError
from ..core.arrays import extent
from ..io import LAS_SUFFIXES, write_cloud

__all__ = ["MAX_TILES", "Tile", "tile_grid", "write_tiles"]

#: Most tiles a grid may have; a larger grid is refused before any work starts (a size typed in cm, not m).
MAX_TILES = 100_000


@dataclass(frozen=True, eq=False)
class Tile:
    """One square tile: ``bounds`` = (xmin, ymin, xmax, ymax) of its core, read with ``buffer`` around it.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.tiles import Tile
    >>> tile = Tile(0, 1, (100.0, 0.0, 200.0, 100.0), buffer=5.0)
    >>> tile.centre.tolist(), tile.read_bounds
    ([150.0, 50.0], (95.0, -5.0, 205.0, 105.0))
    >>> tile.contains(np.array([[96.0, 50, 0], [90.0, 50, 0]])).tolist()
    [True, False]
    """

    row: int
    col: int
    bounds: tuple
    buffer: float = 0.0

    @property
    def centre(self) -> np.ndarray:
        x0, y0, x1, y1 = self.bounds
        return np.array([(x0 + x1) / 2, (y0 + y1) / 2])

    @property
    def read_bounds(self) -> tuple:
        """The core enlarged by the buffer on every side."""
        x0, y0, x1, y1 = self.bounds
        b = self.buffer
        return (x0 - b, y0 - b, x1 + b, y1 + b)

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """Mask of points inside the buffered box; the core is half-open so tiles without buffer never share points."""
        x0, y0, x1, y1 = self.read_bounds
        x, y = xyz[:, 0], xyz[:, 1]
        if self.buffer > 0:
            return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return (x >= x0) & (x < x1) & (y >= y0) & (y < y1)


def tile_grid(bounds, size: float = 100.0, *, buffer: float = 0.0, max_tiles: int = MAX_TILES) -> tuple:
    """Square tiles of ``size`` metres covering ``bounds`` = (xmin, ymin, xmax, ymax).

    The grid is anchored at multiples of ``size`` (a 100 m grid starts at
    round hundreds), as survey tiling schemes are. A grid of more than
    ``max_tiles`` tiles is refused before it is built (``size=0.01`` over a
    60 m survey would be 36 million tiles).

    Examples
    --------
    >>> from labkit.tiles import tile_grid
    >>> grid = tile_grid((30.0, 10.0, 250.0, 90.0), 100.0)
    >>> [(t.row, t.col) for t in grid], [float(t.bounds[0]) for t in grid]
    ([(0, 0), (0, 1), (0, 2)], [0.0, 100.0, 200.0])
    """
    size = positive(size, "size")
    buffer = non_negative(buffer, "buffer")
    max_tiles = count(max_tiles, "max_tiles")
    try:
        x0, y0, x1, y1 = (float(v) for v in np.asarray(bounds, dtype=np.float64).ravel())
    except (TypeError, ValueError):
        raise LabkitError(f"bounds must be four numbers (xmin, ymin, xmax, ymax), got {bounds!r}") from None
    if not np.isfinite([x0, y0, x1, y1]).all() or not (x1 >= x0 and y1 >= y0):
        raise LabkitError(f"bounds must be finite (xmin, ymin, xmax, ymax) with min <= max, got {bounds}")
    gx0, gy0 = np.floor(x0 / size) * size, np.floor(y0 / size) * size
    # Count the tiles in floating point first: the grid is refused before anything is allocated
    ncol_f, nrow_f = max(1.0, np.floor((x1 - gx0) / size) + 1), max(1.0, np.floor((y1 - gy0) / size) + 1)
    if ncol_f * nrow_f > max_tiles:
        raise LabkitError(
            f"{ncol_f * nrow_f:,.0f} tiles of {size:g} m ({ncol_f:,.0f} x {nrow_f:,.0f}) over "
            f"{x1 - x0:,.1f} m x {y1 - y0:,.1f} m exceed the limit of {max_tiles:,}; is the size in metres? "
            f"Use a size of at least {_size_for(x1 - x0, y1 - y0, max_tiles):.3g} m "
            "or raise max_tiles (labkit tiles --max-tiles)")
    ncol, nrow = int(ncol_f), int(nrow_f)
    return tuple(Tile(r, c, (gx0 + c * size, gy0 + r * size, gx0 + (c + 1) * size, gy0 + (r + 1) * size),
                      float(buffer)) for r in range(nrow) for c in range(ncol))


def _size_for(width: float, height: float, max_tiles: int) -> float:
    """About the smallest tile edge that keeps a width x height area within ``max_tiles`` (anchoring adds a row)."""
    s = max(np.sqrt(width * height / max_tiles), 1e-9)
    for _ in range(60):  # grow until the anchored grid fits
        if (np.floor(width / s) + 2) * (np.floor(height / s) + 2) <= max_tiles:
            return s
        s *= 1.1
    return s


def write_tiles(cloud, folder, size: float = 100.0, *, prefix: str = "tile", suffix: str = ".laz",
                max_tiles: int = MAX_TILES) -> list:
    """Cut a cloud into square tiles of ``size`` metres and write one file per non-empty tile.

    The tiles are those of :func:`tile_grid` (anchored at multiples of
    ``size``); a file is named ``{prefix}_{xmin}_{ymin}{suffix}`` after its
    south-west corner in whole metres, as survey deliveries are. Every file is
    written atomically. Returns the paths in grid order.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from labkit.tiles import write_tiles
    >>> xyz = np.array([[10.0, 10, 0], [60.0, 10, 0], [160.0, 10, 0]])
    >>> [p.name for p in write_tiles(xyz, Path(tempfile.mkdtemp()), 100.0, prefix="als")]
    ['als_0_0.laz', 'als_100_0.laz']
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise LabkitError(f"folder {folder} does not exist")
    if not isinstance(suffix, str) or suffix.lower() not in LAS_SUFFIXES:
        raise LabkitError(f"suffix must be one of {LAS_SUFFIXES}, got {suffix!r}")
    xyz = as_points(cloud, name="cloud to cut into tiles")
    cloud = cloud if isinstance(cloud, PointCloud) else PointCloud(xyz)
    paths = []
    for tile in tile_grid(np.r_[extent(xyz[:, :2])], size, max_tiles=max_tiles):
        inside = tile.contains(xyz)
        if inside.any():
            x0, y0 = tile.bounds[:2]
            paths.append(write_cloud(cloud.subset(inside), folder / f"{prefix}_{x0:.0f}_{y0:.0f}{suffix}"))
    return paths
