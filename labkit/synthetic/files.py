"""A row of small point-cloud files in a fresh folder: the test object of the file examples."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..core.checks import count, positive
from ..core.errors import LabkitError
from ..io.write import write_cloud


def tile_row(n: int = 3, *, size: float = 10.0, suffix: str = ".laz", folder=None) -> Path:
    """Write ``n`` tiles ``t0``, ``t1``, ... in a row along x, each 10 points on the x axis.

    Tile ``i`` holds the points ``x = size * i + size * j / 10`` (``j = 0..9``), ``y = z = 0``;
    its cloud is named ``t{i}``.

    Parameters
    ----------
    n : int
        Number of tiles (>= 1).
    size : float
        Edge (m) of a tile along x.
    suffix : str
        File type written: ``'.laz'``, ``'.las'`` or ``'.csv'``.
    folder : str or Path, optional
        Where to write; default a new temporary folder.

    Returns
    -------
    Path
        The folder holding ``t0{suffix}``, ``t1{suffix}``, ...

    Examples
    --------
    >>> from labkit.synthetic import tile_row
    >>> sorted(p.name for p in tile_row(2).iterdir())
    ['t0.laz', 't1.laz']
    """
    n = count(n, "n")
    size = positive(size, "size")
    if suffix not in (".laz", ".las", ".csv"):
        raise LabkitError(f"suffix must be '.laz', '.las' or '.csv', got {suffix!r}")
    folder = Path(tempfile.mkdtemp() if folder is None else folder)
    steps = size * np.arange(10) / 10
    for i in range(n):
        xyz = np.column_stack([size * i + steps, np.zeros(10), np.zeros(10)])
        write_cloud(PointCloud(xyz, name=f"t{i}"), folder / f"t{i}{suffix}")
    return folder
