"""Cutting test regions out of a cloud and thinning it (the registration study, step 1).

Every function takes a :class:`~labkit.cloud.PointCloud` and returns a new one;
the input is never modified. A crop that keeps no point raises
:class:`~labkit.core.errors.EmptyRegionError` naming the region.

Regions are defined in the horizontal plane (x, y) as is usual for ALS tiles:
an axis-parallel box (optionally bounded in z too), a circle, or a polygon
(even-odd rule, so a list of rings describes holes). All geometry runs on
coordinates reduced to a local origin, so 7-digit UTM values lose nothing.

The box, polygon and class masks live in :mod:`labkit.core.masks` (re-exported
here); :func:`labkit.io.read_cloud` applies them chunk by chunk while reading a
large file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .core.checks import as_points, as_rng, choice, count, positive
from .core.report import ReportMixin, fmt
from .cloud import PointCloud
from .core.errors import EmptyRegionError, LabkitError
from .neighbours.sampling import flat_keys, voxel_thin
from .core.masks import (
    ASPRS_NAMES, STABLE_CLASSES, as_bbox, as_classes, as_rings, box_mask, circle_mask, class_mask, polygon_mask,
)

#: Most grid cells a density grid may have (a cell typed in mm instead of m would exhaust the memory).
MAX_CELLS = 50_000_000

__all__ = [
    "crop_box",
    "crop_circle",
    "crop_polygon",
    "crop_classes",
    "thin_random",
    "thin_voxel",
    "equalize_density",
    "point_density",
    "density_grid",
    "DensityGrid",
    "merge",
]


# ----------------------------------------------------------------------------- region checks
def as_cloud(cloud, name: str = "cloud") -> PointCloud:
    """A PointCloud as is; an (n, 3) array-like wrapped into one (checked by ``as_points``).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.regions import as_cloud
    >>> cloud = as_cloud(np.zeros((5, 3)))
    >>> type(cloud).__name__, len(cloud), as_cloud(cloud) is cloud
    ('PointCloud', 5, True)
    """
    if isinstance(cloud, PointCloud):
        return cloud
    return PointCloud(as_points(cloud, min_points=0, name=name))


# ----------------------------------------------------------------------------- crops
def _keep(cloud: PointCloud, mask: np.ndarray, region: str) -> PointCloud:
    # (callers pass the cloud through as_cloud first)
    if not mask.any():
        raise EmptyRegionError(f"{region} contains none of the {len(cloud)} points of {_label(cloud)}")
    return cloud.subset(mask)


def _label(cloud: PointCloud) -> str:
    return f"cloud {cloud.name!r}" if cloud.name else "the cloud"


def crop_box(cloud: PointCloud, bbox) -> PointCloud:
    """Points inside an axis-parallel box (closed; z limits optional).

    Parameters
    ----------
    cloud : PointCloud
    bbox : sequence
        ``(xmin, ymin, xmax, ymax)``, ``(xmin, ymin, zmin, xmax, ymax, zmax)`` or a
        [min, max] array of shape (2, 2) or (2, 3), in the cloud's frame (metres).

    Raises
    ------
    EmptyRegionError
        If no point lies inside the box.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import crop_box
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (1000, 3)))
    >>> part = crop_box(cloud, (0, 0, 5, 5))
    >>> bool(np.all(part.xyz[:, :2] <= 5)), len(part) < len(cloud)
    (True, True)
    """
    box = as_bbox(bbox)
    cloud = as_cloud(cloud)
    return _keep(cloud, box_mask(cloud.xyz, box), f"box {box.ravel().tolist()}")


def crop_circle(cloud: PointCloud, centre, radius: float) -> PointCloud:
    """Points within horizontal distance ``radius`` (m) of ``centre`` = (x, y) (a vertical cylinder).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import crop_circle
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (1000, 3)))
    >>> part = crop_circle(cloud, (5, 5), 2.0)
    >>> bool(np.all(np.hypot(part.xyz[:, 0] - 5, part.xyz[:, 1] - 5) <= 2.0))
    True
    """
    c = np.asarray(centre, dtype=np.float64).ravel()
    if c.size not in (2, 3) or not np.isfinite(c).all():
        raise LabkitError(f"centre must be (x, y) in the cloud's frame, got {centre!r}")
    r = positive(radius, "radius")
    cloud = as_cloud(cloud)
    return _keep(cloud, circle_mask(cloud.xyz, c[:2], r), f"circle around ({c[0]:.3f}, {c[1]:.3f}) with r = {r:g} m")


def crop_polygon(cloud: PointCloud, polygon) -> PointCloud:
    """Points inside a polygon in the xy plane (even-odd rule; a list of rings gives holes).

    Points exactly on an edge may fall on either side (half-open crossing rule),
    as in every crossing-number implementation.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import crop_polygon
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (1000, 3)))
    >>> part = crop_polygon(cloud, [(0, 0), (10, 0), (0, 10)])
    >>> bool(np.all(part.xyz[:, 0] + part.xyz[:, 1] <= 10))
    True
    """
    rings = as_rings(polygon)
    cloud = as_cloud(cloud)
    n_vertices = sum(len(r) for r in rings)
    return _keep(cloud, polygon_mask(cloud.xyz, rings), f"polygon with {n_vertices} vertices")


def crop_classes(cloud: PointCloud, classes, *, exclude: bool = False) -> PointCloud:
    """Points of the given ASPRS classes (or all others with ``exclude=True``).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import crop_classes
    >>> cloud = PointCloud(np.zeros((4, 3)), {"classification": np.array([2, 5, 6, 2], dtype=np.uint8)})
    >>> crop_classes(cloud, [2, 6])["classification"].tolist()
    [2, 6, 2]
    >>> crop_classes(cloud, 2, exclude=True)["classification"].tolist()
    [5, 6]
    """
    cloud = as_cloud(cloud)
    if "classification" not in cloud:
        raise LabkitError(f"{_label(cloud)} has no 'classification' attribute to select classes from")
    codes = as_classes(classes)
    mask = class_mask(cloud["classification"], codes)
    what = f"classes {codes.tolist()}" if not exclude else f"everything but classes {codes.tolist()}"
    return _keep(cloud, ~mask if exclude else mask, what)


# ----------------------------------------------------------------------------- thinning
def thin_random(cloud: PointCloud, fraction: float | None = None, *, n: int | None = None, rng=None) -> PointCloud:
    """A random subset without replacement: a ``fraction`` of the points or exactly ``n`` of them.

    The kept points stay in their original order.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import thin_random
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (1000, 3)))
    >>> len(thin_random(cloud, 0.1, rng=0)), len(thin_random(cloud, n=50, rng=0))
    (100, 50)
    """
    if (fraction is None) == (n is None):
        raise LabkitError("give exactly one of fraction (0 < f <= 1) or n (number of points to keep)")
    cloud = as_cloud(cloud)
    total = len(cloud)
    if fraction is not None:
        f = positive(fraction, "fraction")
        if f > 1:
            raise LabkitError(f"fraction must lie in (0, 1], got {fraction!r}")
        n = int(round(f * total))
    else:
        n = count(n, "n", minimum=0)  # a whole number: 20.5 is refused, not truncated
    if not 1 <= n <= total:
        raise EmptyRegionError(f"random thinning must keep between 1 and {total} points, asked for {n}")
    idx = np.sort(as_rng(rng).choice(total, size=int(n), replace=False))
    return cloud.subset(idx)


def _cell_keys(xy: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer cell indices (n, d) and the grid origin for cells of edge ``size``."""
    if len(xy) and float((xy.max(axis=0) - xy.min(axis=0)).max()) / size > 2.0**52:
        raise LabkitError(f"a cell size of {size:g} m is too small for the cloud's extent (cell indices overflow)")
    origin = np.floor(xy.min(axis=0) / size) * size
    return np.floor((xy - origin) / size).astype(np.int64), origin


def thin_voxel(cloud: PointCloud, size: float, *, keep: str = "centre") -> PointCloud:
    """One point per occupied voxel (cube of edge ``size`` metres).

    Parameters
    ----------
    cloud : PointCloud
    size : float
        Voxel edge length in metres.
    keep : {'centre', 'first'}
        Which point of a voxel survives: the one nearest the voxel centre (default,
        a real measured point, so attributes stay meaningful) or the first in file order.

    Returns
    -------
    PointCloud
        The surviving points in their original order.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import thin_voxel
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 4, (5000, 3)))
    >>> len(thin_voxel(cloud, 1.0))
    64
    """
    choice(keep, ("centre", "first"), "keep")
    size = positive(size, "size")
    cloud = as_cloud(cloud)
    _, origin = _cell_keys(cloud.xyz, size)  # the grid through multiples of size
    return cloud.subset(voxel_thin(cloud.xyz, size, keep=keep, origin=origin))


# ----------------------------------------------------------------------------- density
@dataclass(frozen=True, eq=False, repr=False)
class DensityGrid(ReportMixin):
    """Point counts on a horizontal grid.

    Attributes
    ----------
    counts : ndarray (ny, nx) int
        Points per cell; row 0 is the southern (smallest y) row.
    cell : float
        Cell edge length (m).
    origin : ndarray (2,)
        x, y of the lower-left corner of cell [0, 0].

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import density_grid
    >>> grid = density_grid(PointCloud(np.array([[0.2, 0.2, 0], [0.7, 0.4, 0], [1.5, 0.5, 0]])), cell=1.0)
    >>> type(grid).__name__, grid.counts.tolist(), [float(v) for v in grid.extent]
    ('DensityGrid', [[2, 1]], [0.0, 2.0, 0.0, 1.0])
    """

    counts: np.ndarray
    cell: float
    origin: np.ndarray

    @property
    def density(self) -> np.ndarray:
        """Points per square metre in each cell (pts/m^2)."""
        return self.counts / self.cell**2

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid, as matplotlib's ``imshow`` wants it."""
        ny, nx = self.counts.shape
        x0, y0 = self.origin
        return (x0, x0 + nx * self.cell, y0, y0 + ny * self.cell)

    def _report(self):
        occ = self.counts[self.counts > 0] / self.cell**2
        rows = [
            ("cells", f"{self.counts.shape[1]} x {self.counts.shape[0]} of {self.cell:g} m"),
            ("occupied cells", f"{occ.size} of {self.counts.size}"),
            ("density (occupied)", f"mean {fmt(occ.mean(), 1)}, median {fmt(np.median(occ), 1)} pts/m^2"),
        ]
        return "Density grid", [("", rows)]


def density_grid(cloud: PointCloud, cell: float = 1.0) -> DensityGrid:
    """Count points per horizontal grid cell of edge ``cell`` metres.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import density_grid
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (2000, 3)))
    >>> grid = density_grid(cloud, cell=2.0)
    >>> grid.counts.shape, int(grid.counts.sum())
    ((5, 5), 2000)
    """
    cell = positive(cell, "cell")
    cloud = as_cloud(cloud)
    if len(cloud) == 0:
        raise EmptyRegionError(f"{_label(cloud)} is empty; no density to compute")
    span = cloud.xyz[:, :2].max(axis=0) - np.floor(cloud.xyz[:, :2].min(axis=0) / cell) * cell
    n_cells = float(np.prod(np.floor(span / cell) + 1))
    if n_cells > MAX_CELLS:
        raise LabkitError(f"a density grid of {cell:g} m cells over {span[0]:,.1f} m x {span[1]:,.1f} m has "
                          f"{n_cells:,.0f} cells, more than {MAX_CELLS:,}; is the cell in metres?")
    cells, origin = _cell_keys(cloud.xyz[:, :2], cell)
    nx, ny = cells.max(axis=0) + 1
    counts = np.bincount(cells[:, 1] * nx + cells[:, 0], minlength=nx * ny).reshape(ny, nx)
    return DensityGrid(counts=counts, cell=cell, origin=origin)


def point_density(cloud: PointCloud, cell: float | None = None) -> float:
    """Mean point density in pts/m^2: points divided by the area of the occupied grid cells.

    Parameters
    ----------
    cloud : PointCloud
    cell : float, optional
        Grid cell (m). By default chosen so that a cell holds about 10 points on
        average over the convex hull, which keeps Poisson gaps inside the cloud
        from being counted as empty and keeps the ragged border small.

    Notes
    -----
    Counting occupied cells follows the cloud's real footprint (gaps such as
    water or data holes do not dilute the density), unlike ``n / hull area``.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import point_density
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (2000, 3)))
    >>> round(point_density(cloud, cell=1.0), 1)
    20.0
    """
    cloud = as_cloud(cloud)
    if len(cloud) < 3:
        raise EmptyRegionError(f"{_label(cloud)} has {len(cloud)} points; density needs at least 3")
    if cell is None:
        cell = np.sqrt(10.0 / _hull_density(cloud.xyz[:, :2]))
    grid = density_grid(cloud, cell)
    return float(len(cloud) / (np.count_nonzero(grid.counts) * grid.cell**2))


def _hull_density(xy: np.ndarray) -> float:
    """Points per m^2 of the 2D convex hull (a rough first guess)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        area = ConvexHull(xy - xy.mean(axis=0)).volume  # 'volume' of a 2D hull is its area
    except QhullError:
        raise LabkitError("the points are collinear in xy; an area density is undefined") from None
    return len(xy) / area


def equalize_density(cloud: PointCloud, target, *, cell: float = 1.0, rng=None) -> PointCloud:
    """Thin ``cloud`` cell by cell to a target density (e.g. DIM ~100 -> ALS ~20 pts/m^2).

    Parameters
    ----------
    cloud : PointCloud
        The denser cloud.
    target : float or PointCloud
        Target density in pts/m^2, or a reference cloud whose mean density
        (:func:`point_density`) is the target.
    cell : float
        Horizontal grid cell (m). Each cell keeps ``target * cell**2`` points on
        average (the fractional part by a random draw, so the mean density is
        unbiased); cells that already hold fewer points keep them all.
    rng : int or Generator, optional

    Returns
    -------
    PointCloud
        The kept points in their original order.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import equalize_density, point_density
    >>> cloud = PointCloud(np.random.default_rng(0).uniform(0, 10, (2000, 3)))
    >>> even = equalize_density(cloud, 5.0, rng=0)
    >>> len(even), round(point_density(even, cell=1.0), 1)
    (500, 5.0)
    """
    density = point_density(target) if isinstance(target, PointCloud) else positive(target, "target density")
    cell = positive(cell, "cell")
    cloud = as_cloud(cloud)
    gen = as_rng(rng)
    cells, _ = _cell_keys(cloud.xyz[:, :2], cell)
    key = flat_keys(cells)
    # Quota per cell: floor(t) plus one with probability frac(t)
    quota_mean = density * cell**2
    uniq, inverse = np.unique(key, return_inverse=True)
    quota = np.floor(quota_mean) + (gen.random(uniq.size) < quota_mean % 1.0)
    # Rank of each point inside its cell in a random order
    order = np.lexsort((gen.random(len(key)), inverse))
    sorted_cell = inverse[order]
    starts = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.arange(len(order)) - starts
    kept = np.sort(order[rank < quota[sorted_cell]])
    if kept.size == 0:
        raise EmptyRegionError(f"a target of {density:g} pts/m^2 on {cell:g} m cells keeps no point")
    return cloud.subset(kept)


# ----------------------------------------------------------------------------- merging
def merge(*clouds: PointCloud, name: str = "") -> PointCloud:
    """One cloud from several (e.g. neighbouring tiles); keeps the attributes all of them have.

    Raises
    ------
    LabkitError
        If no cloud is given or the clouds carry different CRS texts.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.cloud import PointCloud
    >>> from labkit.regions import merge
    >>> a, b = PointCloud(np.zeros((3, 3)), name="a"), PointCloud(np.ones((2, 3)), name="b")
    >>> both = merge(a, b, name="ab")
    >>> len(both), both.name
    (5, 'ab')
    """
    if not clouds:
        raise LabkitError("merge needs at least one PointCloud")
    if not all(isinstance(c, PointCloud) for c in clouds):
        bad = next(type(c).__name__ for c in clouds if not isinstance(c, PointCloud))
        raise LabkitError(f"merge takes PointClouds (wrap arrays with PointCloud(xyz)), got a {bad}")
    crs = {c.crs for c in clouds if c.crs}
    if len(crs) > 1:
        raise LabkitError(f"cannot merge clouds in different reference systems: {sorted(crs)}")
    units = [c.units for c in clouds if c.units.known]
    if len({u.coordinates for u in units}) > 1:  # e.g. one read in metres, one in native feet
        raise LabkitError(f"cannot merge clouds in different units: {sorted({u.label() for u in units})}")
    return PointCloud.concatenate(clouds, name=name or clouds[0].name, crs=crs.pop() if crs else None,
                                  units=units[0] if units else None)
