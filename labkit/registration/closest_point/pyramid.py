"""Coarse-to-fine ICP: a voxel pyramid with a shrinking matching distance (notebook 05, section 6b).

ICP's gate (``max_distance``) limits its reach: a source point moved further than the gate from the
surface finds no partner, and where the gate leaves too few pairs the shift is undetermined at the
start. The pyramid runs ICP first on voxel-thinned copies of both clouds with a wide gate, then on
finer copies with a narrower one, each level starting from the previous estimate, and ends with the
caller's own ICP on the full clouds (``icp(..., reach=R)``, ``coarse_to_fine=True``, or by default as a
retry when one level left axes undetermined for want of partners, :func:`retry_with_pyramid`):

1. levels: matching distance d_l = max_distance * 2^l (l = L..1) from about twice the reach down to
   the caller's ``max_distance``; voxel edge d_l / 4, never finer than the target's point spacing;
2. each coarse level: :func:`labkit.registration.icp` on one point per voxel of both clouds (the point
   nearest the voxel centre, so classes and attributes stay meaningful), formal covariance, no model test;
3. the fine level: the caller's ICP with all its options, started from the coarse estimate. Its
   covariance, degeneracy report and message are the result's: the coarse levels only move the start.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ...core.checks import as_points, positive
from ...neighbours.sampling import median_spacing, voxel_thin
from ...core.errors import EmptyRegionError, LabkitError
from ..options import with_keywords

#: A coarse level's voxel edge is this fraction of its matching distance.
VOXEL_SHARE = 0.25
#: At most this many coarse levels (the gate doubles per level: 2^4 = 16 times the matching distance).
MAX_LEVELS = 4
#: coarse_to_fine='auto' retries with the pyramid when more than this share of the searched source points
#: had no partner within the gate and axes were left undetermined (see :func:`retry_with_pyramid`).
RETRY_DISTANCE_SHARE = 0.2
#: ... with this reach, in matching distances.
RETRY_REACH = 2.5
#: ... and also when every undetermined direction missed the precision limit by less than this factor
#: (see :func:`retry_with_pyramid`).
RETRY_MARGIN = 2.0
#: Iterations of a coarse level (it only has to bring the next level within its reach).
COARSE_ITERATIONS = 20


def coarse_to_fine_levels(max_distance, reach=None, spacing=0.0):
    """Matching distances and voxel edges of the coarse levels, coarsest first (m).

    Parameters
    ----------
    max_distance : float
        The fine level's matching distance (the caller's gate).
    reach : float, optional
        The largest shift to be recovered (default ``max_distance``). The coarsest gate is the first
        ``max_distance * 2^l`` of at least twice the reach: a point moved by the reach still finds a
        partner near its true one.
    spacing : float
        Median point spacing of the target; no voxel is finer than it (thinning would keep every point).

    Returns
    -------
    list of (float, float)
        (matching distance, voxel edge) per coarse level; empty when no level is needed.

    Examples
    --------
    >>> coarse_to_fine_levels(0.5, reach=1.5)
    [(4.0, 1.0), (2.0, 0.5), (1.0, 0.25)]
    >>> coarse_to_fine_levels(0.5)  # reach = the gate: one coarse level with twice the gate
    [(1.0, 0.25)]
    """
    max_distance = positive(max_distance, "max_distance")
    reach = max_distance if reach is None else positive(reach, "reach")
    levels = []
    d = max_distance
    while d < 2 * reach and len(levels) < MAX_LEVELS:
        d *= 2
        levels.append((d, max(VOXEL_SHARE * d, spacing)))
    return levels[::-1]


def use_pyramid(max_distance, reach):
    """coarse_to_fine='auto': the pyramid only for a ``reach`` beyond the matching distance.

    Within the gate one level reaches the same fixed point as the pyramid, and faster; the pyramid
    pays where the gate leaves too few pairs at the start (a shift beyond the matching distance).
    Measurements on real clouds: benchmarks/bench_reach.py.

    Examples
    --------
    >>> use_pyramid(1.0, None), use_pyramid(1.0, 0.5), use_pyramid(1.0, 3.0)
    (False, False, True)
    """
    if reach is None or max_distance is None:
        return False
    return float(reach) > float(max_distance)


def retry_with_pyramid(result, max_distance):
    """coarse_to_fine='auto' after one level: retry with the pyramid where axes were left undetermined
    while many source points found no partner within the gate.

    Undetermined axes with few distance rejections are the geometry's verdict (a flat field, ridges in one
    direction: few searched points rejected by distance); with a shift or a point spacing near the gate,
    a large share of the searched points has no partner within it, and the single level may hold X and Y
    at a start metres off (benchmarks/bench_reach.py). The pyramid's own full-cloud level decides again.

    It also retries where every undetermined direction missed the precision limit (eq. 5.12a) by less than
    ``RETRY_MARGIN``: away from the fixed point the residual scale includes the misalignment, and a direction
    held at the start stays where it was (the real Autzen epochs 2010/2023, 0.6 pts/m^2 of hilly ground moved
    by about 1 m: X and Y missed the limit by 1 %). A flat field misses it by orders of magnitude.

    Examples
    --------
    A result with every axis determined is never retried:

    >>> from labkit.registration import icp
    >>> from labkit.synthetic import wavy_surface
    >>> target = wavy_surface(1500, 1, noise=0.0)  # slopes in X and Y, no noise
    >>> res = icp(target[::5] + [0.02, 0.0, 0.0], target, coarse_to_fine=False)
    >>> retry_with_pyramid(res, max_distance=1.0)
    False
    """
    if max_distance is None or not np.isfinite(max_distance) or not result.degeneracy.undetermined_axes:
        return False
    deg = result.degeneracy
    if deg.direction_std is not None and deg.max_std is not None:
        weak = ~np.asarray(deg.constrained, dtype=bool)
        if weak.any() and np.all(deg.direction_std[weak] <= RETRY_MARGIN * deg.max_std):
            return True  # marginal: the misalignment itself inflates the residuals the precision comes from
    corr = result.correspondences
    rejected = dict(corr.rejected)
    searched = len(corr) - rejected.get("class", 0) - rejected.get("noise", 0)
    return rejected.get("distance", 0) > RETRY_DISTANCE_SHARE * max(searched, 1)


def _thin(cloud, normals, size):
    """One point per voxel of a cloud (array or PointCloud) and its given normals."""
    xyz = as_points(cloud, min_points=3)
    idx = voxel_thin(xyz, size)
    thinned = cloud.subset(idx) if hasattr(cloud, "subset") else xyz[idx]
    return thinned, None if normals is None else np.asarray(normals)[idx], len(idx)


def pyramid_icp(source, target, *, icp_function, reach=None, **options):
    """Coarse-to-fine ICP: :func:`labkit.registration.icp` with ``coarse_to_fine=True``.

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
    icp_function : callable
        The single-level ICP (``labkit.registration.icp``), called once per level.
    reach : float, optional
        Largest expected shift (m); default the matching distance ``max_distance``. Larger values add
        coarse levels with wider gates (at most four, 16 times ``max_distance``).
    **options
        The options of :func:`labkit.registration.icp` (the matching options as keywords or as
        ``options=MatchOptions(...)``); the fine level uses all of them unchanged.

    Returns
    -------
    RegistrationResult
        The fine level's result (covariance, degeneracy, message from the full clouds only), with
        ``history`` and ``iterations`` over all levels, ``runtime_s`` of the whole pyramid, the levels
        named in ``method`` and ``message``.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_surface  # slopes in X and Y; 2 mm noise unless told
    >>> rng = np.random.default_rng(1)
    >>> target = wavy_surface(1500, rng)
    >>> source = wavy_surface(600, rng) - [0.6, -0.4, 0.05]  # moved beyond the gate
    >>> from labkit.registration import icp
    >>> res = pyramid_icp(source, target, icp_function=icp, reach=1.0, max_distance=0.25)
    >>> "coarse_to_fine" in res.method, bool(np.allclose(res.translation, [0.6, -0.4, 0.05], atol=0.01))
    (True, True)
    """
    t0 = time.perf_counter()
    match_options = with_keywords(options.pop("options", None), options)  # the matching options: one object
    max_distance = match_options.max_distance
    if max_distance is None:
        raise LabkitError("coarse_to_fine=True needs a finite max_distance (the fine level's gate)")
    levels = coarse_to_fine_levels(max_distance, reach, median_spacing(as_points(target, min_points=2), 2000, distinct=True))
    initial = options.pop("initial", None)
    history, notes = [], []
    coarse = dict(options, consistency_alpha=None, covariance="formal", progress=False,
                  max_iterations=min(COARSE_ITERATIONS, int(options.get("max_iterations", 50))))  # fmt: skip
    for d, voxel in levels:
        src, src_n, n_src = _thin(source, match_options.source_normals, voxel)
        tgt, tgt_n, n_tgt = _thin(target, match_options.target_normals, voxel)
        k = match_options.k
        if min(n_src, n_tgt) < max(k, 30):  # too coarse for neighbourhoods: skip to the next level
            notes.append(f"{d:g} m skipped ({min(n_src, n_tgt)} voxels)")
            continue
        level = dict(coarse, max_std=options.get("max_std"),
                     options=match_options.replace(max_distance=d, source_normals=src_n, target_normals=tgt_n))  # fmt: skip
        try:
            res = icp_function(src, tgt, initial=initial, coarse_to_fine=False, **level)
        except EmptyRegionError:  # too few pairs at this voxel size: the next level tries
            notes.append(f"{d:g} m: too few pairs")
            continue
        initial = res.matrix
        history.extend(res.history)
        notes.append(f"{d:g} m / voxel {voxel:.2g} m: {res.iterations} it.")
    final = icp_function(source, target, initial=initial, coarse_to_fine=False, options=match_options, **options)
    history.extend(final.history)
    history = tuple(replace(h, iteration=i + 1) for i, h in enumerate(history))
    text = "coarse-to-fine " + ("; ".join(notes) if notes else "(no coarse level needed)")
    return replace(
        final, history=history, iterations=len(history), runtime_s=time.perf_counter() - t0,
        method=final.method[:-1] + ", coarse_to_fine)" if final.method.endswith(")") else final.method,
        message=f"{final.message}; {text}; final level {final.iterations} it.",
    )  # fmt: skip
