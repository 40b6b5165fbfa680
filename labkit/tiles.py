"""Shift fields over tiles: coherent areas at survey scale (seed 003, step 6; notebook 08).

A survey is cut into square tiles (e.g. 100 m); every tile is registered on its
own, giving one shift per tile (the *shift field*). Neighbouring tiles whose
shifts differ by more than their combined uncertainty do not move together;
tiles linked by agreeing neighbours, each fitting its area's common shift, form
*coherent areas* (the tests and their correction: :mod:`labkit.coherent_areas`).

The per-tile work runs on Dask: one ``dask.delayed`` task per tile, computed by
a local scheduler, a ``distributed.LocalCluster`` started for the run, a running
cluster named by its address (``tcp://HOST:PORT``) or any Client passed in. With
a ``results`` folder every finished tile is written at once as one JSON file, and
a rerun reads those back instead of computing them (resume after a crash).
Tiles of LAS/LAZ files are read lazily inside their task (only the files whose
header extent meets the tile, filtered by the tile's box while reading), so a
survey of hundreds of files never has to fit in memory.

Every option is checked before any file is opened, and a grid of more than
:data:`MAX_TILES` tiles (a size typed in centimetres, say) is refused with the
count and a size that fits, instead of running on for hours.

Equation numbers refer to ``notebooks/08-shift-field-over-tiles.ipynb``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import re
import time
import warnings
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ._atomic import atomic_write_text
from ._checks import as_points, choice, count, flag, non_negative, positive, probability
from .progress import progress_steps
from ._report import ReportMixin
from .coherent_areas import CORRECTIONS, NeighbourTest, neighbour_areas  # noqa: F401  (NeighbourTest re-exported)
from .errors import CloudFileError, EmptyRegionError, LabkitError

LAS_SUFFIXES = (".las", ".laz")
#: Most tiles a grid may have; a larger grid is refused before any work starts (a size typed in cm, not m).
MAX_TILES = 100_000


# --------------------------------------------------------------------------- tiles
@dataclass(frozen=True, eq=False)
class Tile:
    """One square tile: ``bounds`` = (xmin, ymin, xmax, ymax) of its core, read with ``buffer`` around it."""

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
    """
    from .io import write_cloud

    folder = Path(folder)
    if not folder.is_dir():
        raise LabkitError(f"folder {folder} does not exist")
    if not isinstance(suffix, str) or suffix.lower() not in LAS_SUFFIXES:
        raise LabkitError(f"suffix must be one of {LAS_SUFFIXES}, got {suffix!r}")
    from .cloud import PointCloud

    xyz = as_points(cloud, name="cloud to cut into tiles")
    cloud = cloud if isinstance(cloud, PointCloud) else PointCloud(xyz)
    paths = []
    for tile in tile_grid(np.r_[xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)], size, max_tiles=max_tiles):
        inside = tile.contains(xyz)
        if inside.any():
            x0, y0 = tile.bounds[:2]
            paths.append(write_cloud(cloud.subset(inside), folder / f"{prefix}_{x0:.0f}_{y0:.0f}{suffix}"))
    return paths


# --------------------------------------------------------------------------- survey input
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
        """Read the tile's points from each file, filtered while reading."""
        parts = [_read_part(p, tile.read_bounds, self.classes) for p in self.paths]
        return _concat([c.subset(tile.contains(c.xyz)) for c in parts if c is not None])


def _read_part(path: str, bbox: tuple, classes):
    """The points of one file inside ``bbox`` (read in chunks, filtered while reading), or None."""
    from .io import read_cloud

    try:
        return read_cloud(path, bbox=bbox, classes=classes)
    except EmptyRegionError:
        return None


def _survey(data, classes=None, name: str = "survey"):
    """PointCloud/array -> itself; path, folder, glob or a list of these -> _Files (LAS/LAZ lazily, others read now).

    A class filter on points without a ``classification`` attribute (an array, or a
    cloud read from a format without classes) is refused rather than ignored.
    """
    if isinstance(data, (str, Path)) or (isinstance(data, (list, tuple)) and data
                                         and all(isinstance(p, (str, Path)) for p in data)):
        from .io import cloud_files

        paths = cloud_files(data)  # files, folders (their LAS/LAZ files) and globs
        if all(p.suffix.lower() in LAS_SUFFIXES for p in paths):
            return _Files(tuple(str(p) for p in paths), np.array([_las_extent(p) for p in paths]),
                          None if classes is None else tuple(classes))
        from .io import read_cloud

        return _concat([read_cloud(p, classes=classes) for p in paths])
    if classes is None:
        return data
    if "classification" not in getattr(data, "attributes", {}):
        what = "an array" if not hasattr(data, "attributes") else "a PointCloud"
        raise LabkitError(f"classes={list(classes)} needs a 'classification' attribute, but the {name} is {what} "
                          "without one; pass a PointCloud (or LAS/LAZ files) with classes, or classes=None")
    return data.subset(np.isin(data["classification"], list(classes)))


def _las_extent(path: Path) -> tuple:
    """(xmin, ymin, xmax, ymax) from the LAS header, without reading points."""
    import laspy

    try:
        with laspy.open(path) as reader:
            lo, hi = reader.header.mins, reader.header.maxs
    except Exception as exc:  # laspy raises several types for corrupt headers
        raise CloudFileError(f"cannot read the LAS header of {path}: {exc}") from None
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def _bounds_of(data, name: str) -> np.ndarray:
    if isinstance(data, _Files):
        return data.bounds()
    if len(data) == 0:
        raise EmptyRegionError(f"the {name} survey has no points (after the class filter, if any)")
    xyz = as_points(data, name=f"{name} survey")
    return np.r_[xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)]


def _for_tile(data, tile: Tile):
    """What a tile task receives: the file list to read, or the points already cut out."""
    if isinstance(data, _Files):
        return data.for_tile(tile)
    xyz = as_points(data, name="survey cloud")
    mask = tile.contains(xyz)
    return data.subset(mask) if hasattr(data, "subset") else xyz[mask]


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
        idx = np.sort(idx[t.contains(xyz[idx])])  # the points in their original order
        out.append(data.subset(idx) if hasattr(data, "subset") else xyz[idx])
    return out


def _concat(clouds):
    from .cloud import PointCloud

    if not clouds:
        return np.zeros((0, 3))
    if len(clouds) == 1:
        return clouds[0]
    keys = set.intersection(*(set(c.attributes) for c in clouds))
    return PointCloud(np.vstack([c.xyz for c in clouds]),
                      {k: np.concatenate([c[k] for c in clouds]) for k in keys}, crs=clouds[0].crs,
                      units=clouds[0].units)


# --------------------------------------------------------------------------- per-tile registration
@dataclass(frozen=True, eq=False)
class TileShift:
    """The registration of one tile, reduced to what the shift field needs.

    ``translation`` is the shift at the centroid of the tile's source points
    (eq. 1) with its 3x3 ``covariance``; ``status`` is ``"ok"``,
    ``"too few points"`` or ``"failed"`` (then the numbers are NaN and
    ``message`` says why).
    """

    tile: Tile
    translation: np.ndarray
    covariance: np.ndarray
    axis_determined: np.ndarray
    n_source: int
    n_target: int
    n_used: int
    sigma0: float
    converged: bool
    runtime_s: float
    status: str
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def register_tile(tile: Tile, source, target, method, min_points: int = 200) -> TileShift:
    """Load (if needed) and register one tile; never raises for a labkit error, reports it instead."""
    from .compare import shift_at, shift_covariance

    t0 = time.perf_counter()
    min_points = count(min_points, "min_points")
    # Load the tile's points (lazily read for files)
    src = source.load(tile) if isinstance(source, _Files) else source
    tgt = target.load(tile) if isinstance(target, _Files) else target
    ns, nt = len(src), len(tgt)
    nan3, nan33 = np.full(3, np.nan), np.full((3, 3), np.nan)
    if min(ns, nt) < min_points:
        msg = f"{ns} source and {nt} target points; at least {min_points} of each needed"
        return TileShift(tile, nan3, nan33, np.zeros(3, bool), ns, nt, 0, np.nan, False,
                         time.perf_counter() - t0, "too few points", msg)
    # Register, and express the result as the shift at the source centroid (eq. 1)
    try:
        result = method(src, tgt)
    except (LabkitError, np.linalg.LinAlgError) as exc:
        return TileShift(tile, nan3, nan33, np.zeros(3, bool), ns, nt, 0, np.nan, False,
                         time.perf_counter() - t0, "failed", f"{type(exc).__name__}: {exc}")
    c = as_points(src).mean(axis=0)
    deg = getattr(result, "degeneracy", None)
    determined = np.ones(3, bool) if deg is None else np.asarray(deg.axis_determined, bool)
    return TileShift(tile, shift_at(result.matrix, c), shift_covariance(result, c), determined, ns, nt,
                     int(result.n_used), float(result.sigma0), bool(result.converged),
                     time.perf_counter() - t0, "ok", str(getattr(result, "message", "")))


def register_tiles(source, target, method=None, *, size: float = 100.0, buffer: float = 0.0,
                   min_points: int = 200, classes=None, client=None, scheduler: str = "threads",
                   progress=False, max_tiles: int = MAX_TILES, results=None) -> "ShiftField":
    """Split a survey into tiles and register every tile; the per-tile work runs on Dask.

    Parameters
    ----------
    source, target : PointCloud, array (n, 3), path, folder, glob, or a list of paths/folders/globs
        The two epochs. LAS/LAZ files are read lazily per tile: their header extents
        decide which files a tile touches, and only the points in the tile's box (with
        buffer) are kept while reading, so no process holds more than its tile.
    method : callable(source, target) -> RegistrationResult, or str, optional
        Default: ``labkit.icp`` with ``dof="translation"``. A name among
        :data:`labkit.compare.METHODS` (``'icp'``, ``'consensus'``, ...) means that
        standard method with ``dof="translation"``. With a distributed cluster of
        processes it must be picklable by cloudpickle.
    size : float
        Tile edge in metres.
    buffer : float
        Extra margin read around each tile (m). Tiles with a buffer share points,
        which correlates neighbouring shifts; the neighbour test ignores that.
    min_points : int
        Tiles with fewer source or target points are reported, not registered.
    classes : sequence of int, optional
        Keep only these ASPRS classes (e.g. ground and buildings); refused for
        input without a ``classification`` attribute (e.g. plain arrays).
    client : distributed.Client, optional
        Run on this cluster; otherwise ``scheduler``.
    scheduler : str
        ``'threads'``, ``'processes'``, ``'sync'`` (Dask's local schedulers), ``'serial'``
        (a plain loop without Dask), ``'cluster'`` (a ``distributed.LocalCluster`` started
        for this run, one single-threaded worker process per core, closed afterwards) or
        the address of a running Dask scheduler (``'tcp://HOST:PORT'``).
    progress : bool, "bar", "lines" or callable
        Count the finished tiles (see :mod:`labkit.progress`); default silent.
    max_tiles : int
        Refuse grids of more tiles (:data:`MAX_TILES`), before anything is read.
    results : path, optional
        Folder for one JSON file per tile, written (atomically) as soon as the tile is
        done. A tile whose file is there from an earlier run with the same options and
        input is read back instead of computed, so a run that was killed resumes where it
        stopped. The folder must be visible to the workers (a local cluster or a shared
        file system).

    Returns
    -------
    ShiftField
        ``n_reused`` counts the tiles read back from ``results``.
    """
    # Check every option before any file is opened
    method = _as_method(method)
    scheduler = check_scheduler(scheduler)
    size, buffer = positive(size, "size"), non_negative(buffer, "buffer")
    min_points = count(min_points, "min_points", minimum=1)
    if classes is not None:
        from .regions import as_classes

        classes = tuple(int(c) for c in as_classes(classes))
    # Describe the survey and cut the grid
    src, tgt = _survey(source, classes, "source"), _survey(target, classes, "target")
    b_src, b_tgt = _bounds_of(src, "source"), _bounds_of(tgt, "target")
    common = np.r_[np.maximum(b_src[:2], b_tgt[:2]), np.minimum(b_src[2:], b_tgt[2:])]
    if (common[2:] < common[:2]).any():
        raise LabkitError("source and target surveys do not overlap in x, y")
    tiles = tile_grid(common, size, buffer=buffer, max_tiles=max_tiles)
    # Tiles finished by an earlier run with the same options and input are read back
    store = None if results is None else _TileStore(results, _run_key(method, min_points, classes, size, buffer,
                                                                       src, tgt))
    earlier = {} if store is None else {i: r for i, t in enumerate(tiles) if (r := store.load(t)) is not None}
    todo = [i for i in range(len(tiles)) if i not in earlier]
    # One job per tile still to do: its inputs are cut out (clouds) or listed (files) here, read in the job
    todo_tiles = tuple(tiles[i] for i in todo)
    jobs = list(zip(todo_tiles, _cut_all(src, todo_tiles), _cut_all(tgt, todo_tiles)))
    run = partial(register_tile, method=method, min_points=min_points)
    if store is not None:
        run = partial(_run_and_save, run=run, store=store)
    with _dask_client(client, scheduler) as cl:
        computed = dict(zip(todo, _run_jobs(run, jobs, cl, scheduler, progress)))
    shifts = [earlier[i] if i in earlier else computed[i] for i in range(len(tiles))]
    return ShiftField(tuple(shifts), float(size), _method_name(method), n_reused=len(earlier))


SCHEDULERS = ("threads", "processes", "sync", "serial", "cluster")
_ADDRESS = re.compile(r"^(tcp|tls|ucx)://(\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")


def check_scheduler(scheduler: str) -> str:
    """A scheduler name of :data:`SCHEDULERS` or a Dask scheduler address ``tcp://HOST:PORT``; else LabkitError."""
    if isinstance(scheduler, str):
        text = scheduler.strip()
        if text in SCHEDULERS:
            return text
        m = _ADDRESS.match(text)
        if m and 0 < int(m.group(3)) < 65536:
            return text
    raise LabkitError(f"scheduler must be one of {', '.join(SCHEDULERS)} or a Dask scheduler address "
                      f"like tcp://HOST:PORT, got {scheduler!r}")


def _is_address(scheduler) -> bool:
    return isinstance(scheduler, str) and "://" in scheduler


@contextlib.contextmanager
def _dask_client(client, scheduler: str):
    """The distributed Client to run on (given, started for a LocalCluster, or connected by address), or None."""
    if client is not None or not (scheduler == "cluster" or _is_address(scheduler)):
        yield client
        return
    try:
        import distributed
    except ImportError:
        raise LabkitError(f"scheduler={scheduler!r} needs dask.distributed (pip install distributed); "
                          "use scheduler='threads'") from None
    if scheduler == "cluster":
        with distributed.LocalCluster(threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
                distributed.Client(cluster) as cl:
            yield cl
        return
    try:
        cl = distributed.Client(scheduler, timeout="10s")
    except OSError as exc:
        raise LabkitError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    with cl:
        yield cl


# --------------------------------------------------------------------------- results per tile (resume)
def _run_key(method, min_points, classes, size, buffer, src, tgt) -> dict:
    """What a stored tile result depends on besides its tile: options and a fingerprint of the input."""
    key = {"method": _method_text(method), "min_points": int(min_points),
           "classes": None if classes is None else list(classes), "size": float(size), "buffer": float(buffer),
           "source": _fingerprint(src), "target": _fingerprint(tgt)}
    return json.loads(json.dumps(key))  # as it reads back from a file


def _method_text(method) -> str:
    if isinstance(method, partial):
        func = getattr(method.func, "__module__", "") + "." + getattr(method.func, "__qualname__", "")
        return f"{func}{sorted((k, repr(v)) for k, v in method.keywords.items())}"
    return getattr(method, "__module__", "") + "." + getattr(method, "__qualname__", type(method).__name__)


def _fingerprint(data) -> list:
    if isinstance(data, _Files):
        return [[str(Path(p).resolve()), Path(p).stat().st_size, Path(p).stat().st_mtime_ns] for p in data.paths]
    xyz = as_points(data, name="survey cloud")
    return [len(xyz), float(np.sum(xyz, dtype=np.float64)), float(np.sum(xyz * xyz, dtype=np.float64))]


@dataclass(frozen=True)
class _TileStore:
    """One JSON per tile in ``folder``; a file counts only if it was written with the same ``key``."""

    folder: str
    key: dict

    def path(self, tile: Tile) -> Path:
        return Path(self.folder) / f"tile_{tile.row}_{tile.col}.json"

    def load(self, tile: Tile) -> "TileShift | None":
        path = self.path(tile)
        try:
            rec = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None  # missing or cut short: compute again
        same_tile = rec.get("tile") == _tile_json(tile)
        return _shift_from_json(rec, tile) if rec.get("key") == self.key and same_tile else None

    def save(self, shift: "TileShift") -> None:
        Path(self.folder).mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path(shift.tile), json.dumps(dict(_shift_json(shift), key=self.key), indent=1))


def _run_and_save(tile, source, target, *, run, store):
    """Register one tile and write its JSON at once (a crash later loses nothing finished)."""
    shift = run(tile, source, target)
    store.save(shift)
    return shift


def _tile_json(tile: Tile) -> dict:
    return {"row": int(tile.row), "col": int(tile.col), "bounds": [float(v) for v in tile.bounds],
            "buffer": float(tile.buffer)}


def _shift_json(s: "TileShift") -> dict:
    return {"tile": _tile_json(s.tile), "translation": s.translation.tolist(), "covariance": s.covariance.tolist(),
            "axis_determined": [bool(v) for v in s.axis_determined], "n_source": int(s.n_source),
            "n_target": int(s.n_target), "n_used": int(s.n_used), "sigma0": float(s.sigma0),
            "converged": bool(s.converged), "runtime_s": float(s.runtime_s), "status": s.status,
            "message": s.message}


def _shift_from_json(rec: dict, tile: Tile) -> "TileShift":
    return TileShift(tile, np.array(rec["translation"], float), np.array(rec["covariance"], float),
                     np.array(rec["axis_determined"], bool), int(rec["n_source"]), int(rec["n_target"]),
                     int(rec["n_used"]), float(rec["sigma0"]), bool(rec["converged"]), float(rec["runtime_s"]),
                     str(rec["status"]), str(rec["message"]))


def _method_name(method) -> str:
    if isinstance(method, partial):
        return str(method.keywords.get("name") or getattr(method.func, "__name__", "method"))
    return getattr(method, "__name__", type(method).__name__)


def _default_method():
    from .registration import icp

    return partial(icp, dof="translation", rng=0)


def _as_method(method):
    """None -> the default ICP; a standard method's name -> that method (translation); a callable -> itself."""
    if method is None:
        return _default_method()
    if isinstance(method, str):
        from .compare import METHODS, standard_methods

        choice(method, METHODS, "method")
        return standard_methods([method], dof="translation", rng=0)[method]
    if not callable(method):
        raise LabkitError("method must be a callable (source, target) -> RegistrationResult or the name of a "
                          f"standard method, got {type(method).__name__}")
    return method


def _run_jobs(run, jobs, client, scheduler, progress) -> list:
    """Results of ``run(*job)`` in the order of ``jobs``; progress counts finished tiles."""

    with progress_steps(progress, len(jobs), "tiles", "tiles") as step:
        if not jobs:
            return []
        if client is None and scheduler == "serial":
            out = []
            for job in jobs:
                out.append(run(*job))
                step(1)
            return out
        import dask

        tasks = [dask.delayed(run, pure=True)(*j, dask_key_name=f"tile-{j[0].row}-{j[0].col}") for j in jobs]
        if client is not None:
            from distributed import as_completed

            futures = client.compute(tasks)
            for _ in as_completed(futures):
                step(1)
            return client.gather(futures)
        from dask.callbacks import Callback

        def posttask(key, result, dsk, state, worker_id):
            name = key[0] if isinstance(key, tuple) else key
            if isinstance(name, str) and name.startswith("tile-"):
                step(1)

        with Callback(posttask=posttask):
            return list(dask.compute(*tasks, scheduler=scheduler))


# --------------------------------------------------------------------------- the field and its test
@dataclass(frozen=True, eq=False, repr=False)
class ShiftField(ReportMixin):
    """The shift of every tile of a survey."""

    tiles: tuple
    size: float
    method: str = ""
    n_reused: int = 0  # tiles read back from an earlier run's results (register_tiles(results=...))

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def ok(self) -> np.ndarray:
        return np.array([t.ok for t in self.tiles], bool)

    @property
    def centres(self) -> np.ndarray:
        return np.array([t.tile.centre for t in self.tiles]).reshape(-1, 2)

    @property
    def translations(self) -> np.ndarray:
        return np.array([t.translation for t in self.tiles]).reshape(-1, 3)

    @property
    def covariances(self) -> np.ndarray:
        return np.array([t.covariance for t in self.tiles]).reshape(-1, 3, 3)

    @property
    def determined(self) -> np.ndarray:
        """(n, 3) bool: which components of each tile's shift its data determine."""
        return np.array([t.axis_determined for t in self.tiles], bool).reshape(-1, 3)

    @property
    def determined_translations(self) -> np.ndarray:
        """The translations with undetermined components (held at 0 by the method) set to NaN."""
        return np.where(self.determined, self.translations, np.nan)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.einsum("nii->ni", self.covariances), 0, None))

    def neighbour_test(self, alpha: float = 0.05, *, extra_std: float = 0.0, diagonal: bool = False,
                       correction: str = "holm") -> NeighbourTest:
        """Test whether neighbouring tiles shift alike and find the coherent areas; see :func:`neighbour_test`."""
        return neighbour_test(self, alpha, extra_std=extra_std, diagonal=diagonal, correction=correction)

    def to_csv(self, path) -> Path:
        """One line per tile: index, bounds, shift, standard deviations, counts, status (atomic write)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["row", "col", "xmin", "ymin", "xmax", "ymax", "dx", "dy", "dz", "sx", "sy", "sz",
                    "n_source", "n_target", "n_used", "sigma0", "converged", "runtime_s", "status", "message"])
        for t, s in zip(self.tiles, self.std):
            w.writerow([t.tile.row, t.tile.col, *t.tile.bounds, *(f"{v:.6g}" for v in (*t.translation, *s)),
                        t.n_source, t.n_target, t.n_used, f"{t.sigma0:.6g}", t.converged, f"{t.runtime_s:.3f}",
                        t.status, t.message])
        return atomic_write_text(path, buf.getvalue())

    def _report(self):
        ok = self.ok
        tr = self.determined_translations[ok]  # undetermined components do not enter the statistics
        rows = [("tiles", f"{len(self)} of {self.size:g} m; {int(ok.sum())} registered"),
                ("method", self.method or "?")]
        if ok.any():
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an axis no tile determines gives nan
                med, spread = np.nanmedian(tr, axis=0), np.nanstd(tr, axis=0)
            rows += [("median shift", "[" + ", ".join(f"{v:+.4f}" for v in med) + "] m"),
                     ("spread (std) of shifts", "[" + ", ".join(f"{v:.4f}" for v in spread) + "] m")]
            undet = (~self.determined[ok]).sum(axis=0)
            if undet.any():
                rows.append(("undetermined (tiles per axis)", ", ".join(f"{a} {k}" for a, k in zip("XYZ", undet))))
        for status in ("too few points", "failed"):
            n = sum(t.status == status for t in self.tiles)
            if n:
                rows.append((status, f"{n} tiles"))
        return "Shift field", [("", rows)]


def neighbour_test(field: ShiftField, alpha: float = 0.05, *, extra_std: float = 0.0, diagonal: bool = False,
                   correction: str = "holm") -> NeighbourTest:
    """Do neighbouring tiles agree within their uncertainty, and which areas move as one? (notebook 08, eqs. 2-7)

    For tiles i, j sharing an edge (or a corner with ``diagonal``) the
    difference d = t_i - t_j has covariance C = Sigma_i + Sigma_j + 2 s^2 I
    (eq. 2; s = ``extra_std``, an uncertainty per tile beyond the formal one,
    e.g. for systematic effects the covariance of ICP does not see). On the
    axes both tiles determine, T = d^T C^-1 d is chi-square distributed with as
    many degrees of freedom (eq. 3). Tiles linked by agreeing pairs are a first
    guess of the coherent areas; each tile is then tested against its area's
    common weighted shift (eqs. 5, 6), and an area with a tile that disagrees
    is split, so that a chain of small steps is not one area (see
    :mod:`labkit.coherent_areas`).

    Parameters
    ----------
    field : ShiftField
    alpha : float
        Level of the tests; with ``correction='holm'`` the family-wise level: the
        chance that a survey whose tiles all shift alike shows any disagreeing
        border or more than one area.
    extra_std : float
        Extra standard deviation per tile (m).
    diagonal : bool
        Also test tiles that share only a corner.
    correction : {'holm', 'fdr', 'none'}
        Control of the many tests (about three per tile) (eq. 7). ``'holm'`` (default)
        keeps the family-wise error at alpha under any dependence (pairs sharing a
        tile are correlated): a flagged border is then evidence about the survey,
        not the expected few percent of false alarms among hundreds of borders -
        without correction a stable survey of 100 tiles shows about ten. ``'fdr'``
        (Benjamini-Hochberg) bounds the expected share of false alarms among the
        flagged ones instead; it finds more where much has moved (a campaign after
        a landslide). ``'none'`` tests each pair at alpha (as notebook 08 does first).

    Returns
    -------
    NeighbourTest
    """
    alpha = probability(alpha, "alpha")
    extra_std = non_negative(extra_std, "extra_std")
    diagonal = flag(diagonal, "diagonal")
    correction = choice(correction, CORRECTIONS, "correction")
    if not isinstance(field, ShiftField):
        raise LabkitError(f"neighbour_test needs a ShiftField (from register_tiles), got {type(field).__name__}")
    return neighbour_areas(_neighbour_pairs(field, diagonal), field.translations, field.covariances,
                           field.determined, field.ok, alpha=alpha, extra_std=extra_std, correction=correction)


def _neighbour_pairs(field: ShiftField, diagonal: bool) -> np.ndarray:
    index = {(s.tile.row, s.tile.col): n for n, s in enumerate(field.tiles) if s.ok}
    steps = [(0, 1), (1, 0)] + ([(1, 1), (1, -1)] if diagonal else [])
    pairs = [(n, index[(r + dr, c + dc)]) for (r, c), n in index.items() for dr, dc in steps
             if (r + dr, c + dc) in index]
    return np.array(sorted(pairs), int).reshape(-1, 2)
