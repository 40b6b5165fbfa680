"""Registering the tiles: one shift per tile (eq. 1), every tile a task on Dask (notebook 08)."""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from ..core.checks import as_points, choice, count, non_negative, output_folder, positive
from ..core.crs import check_same_crs
from ..registration.compare import METHODS, shift_at, shift_covariance, standard_methods
from ..core.errors import LabkitError
from ..regions import as_classes
from .field import ShiftField, TileShift, tile_status
from .grid import MAX_TILES, Tile, tile_grid
from .schedule import _dask_client, _run_jobs, check_scheduler
from .store import _run_and_save, _run_key, _TileStore
from .survey import _bounds_of, _cut_all, _Files, _survey

__all__ = ["register_tile", "register_tiles"]


def register_tile(tile: Tile, source, target, method, min_points: int = 200) -> TileShift:
    """Load (if needed) and register one tile; never raises for a labkit error, reports it instead.

    The tile's status is ``'ok'`` only when the method converged and the tile's data determine
    every component of its shift (finite standard deviation); otherwise ``'not converged'`` or
    ``'undetermined'`` (:func:`~labkit.tiles.tile_status`), ``'too few points'`` or ``'failed'``.

    References
    ----------
    .. [1] Notebook 08, section 3, eq. 1.
    .. [2] P. J. Besl, N. D. McKay (1992): A method for registration of 3-D shapes. IEEE
       Transactions on Pattern Analysis and Machine Intelligence 14(2), 239-256,
       doi:10.1109/34.121791.
    .. [3] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.tiles import Tile, register_tile
    >>> tile = Tile(0, 0, (0.0, 0.0, 100.0, 100.0))
    >>> xyz = np.random.default_rng(0).uniform(0, 100, (50, 3))
    >>> s = register_tile(tile, xyz, xyz, method=lambda s, t: 1 / 0)  # too few points: no call
    >>> s.status, s.message
    ('too few points', '50 source and 50 target points; at least 200 of each needed')
    """
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
    cov = shift_covariance(result, c)
    deg = getattr(result, "degeneracy", None)
    determined = np.ones(3, bool) if deg is None else np.asarray(deg.axis_determined, bool)
    determined = determined & np.isfinite(np.diag(cov))  # a held rotation leaves the shift at c undetermined too
    converged = bool(result.converged)
    status = tile_status(converged, determined)
    message = str(getattr(result, "message", ""))
    if status == "undetermined":
        free = ", ".join(a for a, d in zip("XYZ", determined) if not d)
        rest = [m for m in message.split("; ") if not m.startswith(("converged", "UNDETERMINED"))]  # (said here)
        message = "; ".join([f"{free} not determined by the tile's data (empty in the CSV)"] + rest)
    return TileShift(tile, shift_at(result.matrix, c), cov, determined, ns, nt, int(result.n_used),
                     float(result.sigma0), converged, time.perf_counter() - t0, status, message)


def register_tiles(source, target, method=None, *, size: float = 100.0, buffer: float = 0.0,
                   min_points: int = 200, classes=None, client=None, scheduler: str = "threads",
                   progress=False, max_tiles: int = MAX_TILES, results=None) -> "ShiftField":
    """Split a survey into tiles and register every tile; the per-tile work runs on Dask.

    Parameters
    ----------
    source, target : PointCloud, array (n, 3), path, folder, glob, or a list of paths/folders/globs
        The two epochs. LAS/LAZ files are read lazily per tile: their header extents
        decide which files a tile touches, and only the points in the tile's box (with
        buffer) are kept while reading, so no process holds more than its tile. The files
        of one epoch must name one CRS in their headers (mixed ones are refused at once).
    method : callable(source, target) -> RegistrationResult, or str, optional
        Default: ``labkit.icp`` with ``dof="translation"``. A name among
        :data:`labkit.registration.compare.METHODS` (``'icp'``, ``'consensus'``, ...) means that
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
        Count the finished tiles (see :mod:`labkit.core.progress`); default silent.
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

    References
    ----------
    .. [1] Notebook 08, section 3, eq. 1 (shift field s = R c + t - c and its covariance).
    .. [2] P. J. Besl, N. D. McKay (1992): A method for registration of 3-D shapes. IEEE
       Transactions on Pattern Analysis and Machine Intelligence 14(2), 239-256,
       doi:10.1109/34.121791.
    .. [3] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.

    Examples
    --------
    Two 100 m tiles of a survey lifted by 5 cm, with a toy method (the centroids' difference):

    >>> import numpy as np
    >>> from labkit.registration import RegistrationResult
    >>> from labkit.tiles import register_tiles
    >>> def mean_shift(source, target):
    ...     t = np.mean(target, axis=0) - np.mean(source, axis=0)
    ...     return RegistrationResult(t, np.eye(3), np.zeros(3), np.eye(3) * 1e-6, ("tx", "ty", "tz"),
    ...                               1.0, len(source), 1.0, True, 1)
    >>> source = np.random.default_rng(0).uniform([0, 0, 0], [200, 100, 1], (4000, 3))
    >>> field = register_tiles(source, source + [0, 0, 0.05], mean_shift, scheduler="serial")
    >>> len(field), bool(field.ok.all()), field.translations[:, 2].round(3).tolist()
    (2, True, [0.05, 0.05])
    """
    # Check every option before any file is opened
    method = _as_method(method)
    scheduler = check_scheduler(scheduler)
    size, buffer = positive(size, "size"), non_negative(buffer, "buffer")
    min_points = count(min_points, "min_points", minimum=1)
    if classes is not None:
        classes = tuple(int(c) for c in as_classes(classes))
    # Describe the survey and cut the grid
    check_same_crs(source, target, "register_tiles")
    results = None if results is None else str(output_folder(results, "results"))
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


def _method_name(method) -> str:
    if isinstance(method, partial):
        return str(method.keywords.get("name") or getattr(method.func, "__name__", "method"))
    return getattr(method, "__name__", type(method).__name__)


def _default_method():
    from ..registration import icp  # not at the top: ICP's matching loads numba (import labkit.cli stays light)

    return partial(icp, dof="translation", rng=0)


def _as_method(method):
    """None -> the default ICP; a standard method's name -> that method (translation); a callable -> itself."""
    if method is None:
        return _default_method()
    if isinstance(method, str):
        choice(method, METHODS, "method")
        return standard_methods([method], dof="translation", rng=0)[method]
    if not callable(method):
        raise LabkitError("method must be a callable (source, target) -> RegistrationResult or the name of a "
                          f"standard method, got {type(method).__name__}")
    return method


