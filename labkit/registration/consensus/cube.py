"""Maximum consensus over translations and the consensus cube (notebook 06, the registration study, step 3).

For a translation t the consensus is (eq. 6.1, 6.2)

    C(t) = sum_p w_p * [ exists q in target: pair (p, q) consistent at t ]

with "consistent" meaning |p + t - q| < eps (point-to-point) or
|n_q . (p + t - q)| < eps and |p + t - q| < radius (point-to-plane, eq. 6.3,
6.4), optionally with the angle between the normals of p and q below
``max_angle_deg`` (eq. 6.4a). Each source point counts at most once per t. Normals
that the local PCA cannot determine (identical or collinear neighbours) are
dropped, never used.

Only the difference vectors d = q - p with d inside the search window (grown
by the search radius) can ever be consistent, so both the cube and the branch
and bound work on this list of pairs, never on 8 million nearest-neighbour searches.

This module holds the two searches; the rest lives in modules named after it:

- inputs, voting points, tolerances and candidate pairs: :mod:`labkit.registration.consensus.inputs`
- the cube and its peak (records): :mod:`labkit.registration.consensus.result`
- branch and bound, and the least-squares refinement with its cluster-robust (sandwich)
  covariance: :mod:`labkit.registration.consensus.bnb`
- the compiled counting kernels: :mod:`labkit.registration.consensus.kernels`
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ...core.checks import choice, count, non_negative, positive
from ...core.crs import check_same_crs, crs_of
from . import kernels as K
from ...neighbours.sampling import even_subset
from .inputs import candidate_pairs, grid, prepare_problem, search_box
from .bnb import branch_and_bound, refine
from .plateau import centre_result
from .result import AXES, ConsensusCube, PeakShape, peak_shape
from ..height_model import fill_held_axes
from ..selection import SELECT, select_points

#: Default work budget of the branch and bound: pair tests (about 6 s on one idle core)
MAX_WORK = 1_000_000_000

__all__ = ["consensus_cube", "consensus_inputs", "max_consensus", "ConsensusCube", "PeakShape", "peak_shape",
           "even_subset", "AXES"]



def consensus_inputs(source, target, metric: str = "point_to_plane", eps: float | None = 0.05,
                     max_angle_deg: float | None = None, weights=None, *, radius: float | None = None,
                     source_normals=None, target_normals=None, k: int = 12):
    """The points, normals and tolerances the consensus is counted on, as :func:`consensus_cube` prepares them.

    For checking a count by hand (notebook 06, eq. 6.2-6.4: the consensus at one translation straight
    from its definition) and for benchmarks against a brute-force count: the same reduced points,
    the same target normals (the undeterminable ones dropped) and the same search radius.

    Parameters
    ----------
    source, target, metric, eps, max_angle_deg, weights, radius, source_normals, target_normals, k
        As in :func:`consensus_cube`.

    Returns
    -------
    Problem
        A record with ``src`` (n, 3) and ``tgt`` (m, 3) in the local frame (``origin`` added
        back gives the input frame), ``w`` the source weights, ``tgt_normals`` (m, 3) or None,
        ``eps`` and ``radius`` (m), ``noise`` the median local noise of the target.

    References
    ----------
    .. [1] Notebook 06, section 1, eqs. 6.3-6.4a, and section 5, eq. 6.11.
    .. [2] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import consensus_inputs
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(400, 0, size=5, noise=0.002)
    >>> pb = consensus_inputs(floor[:200], floor[200:], eps=0.02)
    >>> pb.src.shape, pb.tgt.shape, round(pb.eps, 3), bool(np.allclose(abs(pb.tgt_normals[:, 2]), 1, atol=0.01))
    ((200, 3), (200, 3), 0.02, True)
    """
    return prepare_problem(source, target, metric, eps, radius, max_angle_deg, weights,
                           (source_normals, target_normals), k)


def consensus_cube(
    source,
    target,
    extent=1.0,
    step: float = 0.01,
    metric: str = "point_to_plane",
    eps: float | None = 0.05,
    max_angle_deg: float | None = None,
    weights=None,
    *,
    radius: float | None = None,
    center=None,
    source_normals=None,
    target_normals=None,
    k: int = 12,
    level: float = 0.07,
    use_numba: bool | None = None,
    workers: int = 2,
) -> ConsensusCube:
    """Consensus of every translation on a regular grid, exactly (eq. 6.5).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        The cloud to move and the reference, same frame (UTM is fine).
    extent : float or (3,) float
        Half-width (m) of the search box per axis around ``center``.
    step : float
        Grid step (m); at most 1e8 cells are allowed.
    metric : {'point_to_plane', 'point_to_point'}
        Consistency test of a pair (eq. 6.3 or 6.4); the same name and values as in :func:`icp`.
    eps : float or None
        Distance tolerance (m), > 0; None: from the local noise as in :func:`max_consensus`.
    max_angle_deg : float, optional
        Largest angle (deg) between source and target normals for a consistent pair (eq. 6.4a):
        removes pairs between differently oriented surfaces before counting.
    weights : array_like (n,) or dict, optional
        Weight per source point, or per class code (needs ``source['classification']``).
    radius : float, optional
        Search radius (m) around target points for point-to-plane; default: the
        median distance of target points to their 4th nearest neighbour, and never
        less than ``eps`` (point-to-point searches within ``eps``).
    center : (3,) float, optional
        Centre of the search box (an a-priori shift); default zero.
    source_normals, target_normals : array_like (n, 3), optional
        Precomputed unit normals (either may be None); otherwise PCA normals.
    k : int
        Neighbours for PCA normals (and, in :func:`max_consensus`, for the local planes of the
        refinement).
    level : float
        The top region of the peak: counts above ``peak - level * (peak - median)``; keep it
        below the share of points on the surfaces that constrain the weakest direction
        (roofs in a village: 10-20 %), else the top region leaks into the plateau of the ground.
    use_numba : bool, optional
        Force (True) or forbid (False) the compiled kernel; default: use it if installed.
    workers : int
        Threads for the compiled kernel.

    Returns
    -------
    ConsensusCube

    Raises
    ------
    LabkitError
        Grid too large, eps <= 0, bad weights or normals; EmptyRegionError if the clouds do not overlap.

    References
    ----------
    .. [1] Notebook 06, sections 1-2, eqs. 6.1-6.6; the registration study, step 3 (shifts in cm steps up to 1 m
       each way, the consensus cube).
    .. [2] T.-J. Chin, D. Suter (2017): The Maximum Consensus Problem: Recent Algorithmic Advances.
       Synthesis Lectures on Computer Vision, Morgan & Claypool.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> cube = consensus_cube(source[::2], target, extent=0.06, step=0.02, eps=0.01, center=[0.04, 0.02, 0.04],
    ...                       use_numba=False)
    >>> cube.counts.shape, cube.peak.kind
    ((7, 7, 7), 'point')
    >>> bool(np.allclose(cube.best_translation, [0.05, 0.02, 0.03], atol=0.02))  # within one grid step
    True
    """
    t0 = time.perf_counter()
    # Grid, reduced coordinates, normals, weights
    axes, step = grid(extent, step, center)
    pb = prepare_problem(source, target, metric, eps, radius, max_angle_deg, weights,
                         (source_normals, target_normals), k)
    # Candidate pairs in the window
    a0 = np.array([a[0] for a in axes])
    a1 = np.array([a[-1] for a in axes])
    ptr, _, D, nrm = candidate_pairs(pb, a0, a1, pb.radius)
    # Rasterize the consistent set of every pair, one count per source point and cell
    shape = tuple(a.size for a in axes)
    numba_ok = K.HAVE_NUMBA if use_numba is None else bool(use_numba) and K.HAVE_NUMBA
    w = np.ones(len(pb.w), np.int32) if weights is None else pb.w  # whole counts: int32 from the kernel
    counts = K.raster(ptr, (D - a0) / step, nrm, pb.radius / step, pb.eps / step, w, shape, use_numba=numba_ok,
                      workers=max(1, int(workers)))
    kernel = "numba" if numba_ok else "numpy"
    # Peak and its shape
    peak = peak_shape(counts, axes, pb.eps, level)
    idx = np.unravel_index(np.argmax(counts), shape)
    t_max = np.array([a[i] for a, i in zip(axes, idx)])
    best = np.where(peak.axis_constrained, peak.summit, np.nan) if peak.kind != "flat" else np.full(3, np.nan)
    return ConsensusCube(
        counts=counts, axes=axes, best_translation=best, argmax_translation=t_max, best_count=float(counts[idx]),
        peak=peak, metric=pb.metric, eps=pb.eps, radius=pb.radius, max_angle_deg=pb.max_angle_deg,
        n_source=len(pb.src), n_pairs=int(D.shape[0]), step=step, kernel=kernel, runtime_s=time.perf_counter() - t0,
    )


def max_consensus(
    source,
    target,
    extent=1.0,
    metric: str = "point_to_plane",
    eps: float | None = None,
    tol: float = 0.001,
    max_angle_deg: float | None = None,
    weights=None,
    *,
    radius: float | None = None,
    center=None,
    source_normals=None,
    target_normals=None,
    k: int = 12,
    max_points: int | None = 5000,
    refine_points: int | None = None,
    max_time: float | None = None,
    max_boxes: int = 20000,
    max_work: int | None = MAX_WORK,
    gap_tol: float = 0.0,
    init_step: float | None = None,
    reject_sigma: float = 3.0,
    block_size: float | None = None,
    max_std: float | None = None,
    use_numba: bool | None = None,
    select: str = "auto",
    recentre: bool = True,
    height_model: bool = True,
):
    """Globally best translation by branch and bound, then least squares on the consensus set.

    Branch and bound (eq. 6.7, 6.8) splits the search box into octants; a box
    with centre c and half diagonal h cannot hold a translation with more
    consensus than C(c) evaluated with eps + h (and radius + h). Boxes whose
    bound does not exceed the best consensus found so far are dropped; the
    search stops when the bounds meet, every open box is smaller than ``tol``,
    or the budget (``max_boxes`` splits or ``max_work`` pair tests; ``max_time``
    seconds only when asked for) is spent. It
    then returns the best translation found and the certified gap: no
    translation in the box has more than ``upper = lower + gap`` consensus.
    The consensus set of that translation is adjusted by weighted least squares
    with iterative deletion (eq. 6.10-6.13); its covariance is the
    cluster-robust sandwich over spatial blocks (eq. 6.14).

    Maximum consensus is the route for large shifts: it searches the whole box
    +-``extent`` globally, where ICP only converges from a start within about its
    matching distance. For a rigid transformation or the last millimetre, follow it
    with ICP started at its translation (``labkit register --method consensus+icp``,
    or ``icp(source, target, initial=result.matrix)``; notebook 06).

    Parameters
    ----------
    source, target, extent, metric, max_angle_deg, weights, radius, center, source_normals, target_normals, k
        As in :func:`consensus_cube`.
    eps : float, optional
        Distance tolerance (m). Default: 3 sqrt(2) times the median local noise of the
        target (the spread of its k-neighbourhoods along their normals, eq. 6.11), kept
        within 5 mm and 10 cm.
    tol : float
        Boxes with an edge below ``tol`` (m) are not split further.
    max_points : int or None
        At most this many source points vote, spread evenly in space (one per voxel);
        None: all of them. 5000 points decide a translation (three parameters) well.
    refine_points : int, optional
        Refine on up to this many source points spread evenly in space (those with a target
        point within the search radius and within eps of their local target plane at the
        branch-and-bound optimum) instead of the consensus set of the voting points (default).
        The search needs few points, the precision of weak directions needs many: on the real
        ALS halves at 30,000 points, 30,000 refinement points halve the stated std of X and Y.
        The refinement's time grows in proportion.
    max_time : float or None
        Time budget (s) of the branch and bound, off by default; when it is spent the best
        translation found so far is returned with its certified gap (converged = False). Wall
        time depends on the load of the machine, so with it the same input can give different
        results; the default budgets count work instead and are deterministic.
    max_boxes : int
        Budget of box splits (>= 0); when exhausted the result says so (converged = False).
    max_work : int or None
        Budget of pair tests (8 per candidate pair of every split box, counted by the search,
        ``history[0].pair_tests``): about 6 s on one idle core by default. The same input always
        gives the same result. None: no work limit.
    gap_tol : float
        Boxes whose upper bound exceeds the best consensus by at most ``gap_tol`` are
        not split (0: search until the bounds meet or the boxes are below ``tol``).
    init_step : float, optional
        Edge (m) of the first-level boxes, bounded all at once by two rasterized cubes;
        default: twice eps, at least 1/32 of the box.
    reject_sigma : float
        Deletion threshold (> 0) for standardized residuals in the refinement, in robust standard
        deviations (as ``reject_sigma`` of :func:`icp`).
    block_size : float, optional
        Edge (m) of the square (XY) blocks of the jackknife covariance; default: twice and four
        times the radius of the target's k-neighbourhoods (median distance to the k-th
        neighbour; two voting points closer than twice it share target points), and per axis the
        larger of the two variances counts (errors correlated over longer distances, such as the
        shape of the terrain or one roof, show as a growth with the block edge); each is scaled
        for its number of blocks (Student's t with B - 1 degrees of freedom, as ICP's sandwich).
    max_std : float, optional
        A direction of the translation is determined when its standard deviation is at
        most ``max_std`` (m); default eps / 2. Weaker directions are named undetermined and
        get the variance of a uniform distribution over the box; their value is the centre of
        the consensus hill along them (:func:`labkit.registration.consensus.plateau.centre_held`),
        not its highest point, which lands anywhere on a top that is flat within the counting
        noise (on 6 random halves of a real ALS file of parallel roofs up to 0.6 m off, the
        centre within 7 cm).
    select : {'auto', 'all'}
        Which points vote (:func:`labkit.registration.selection.select_points`): 'auto' (default) the
        stable classes of classified clouds, the surface points of unclassified ones (vegetation left
        out); ``result.selection`` says which. Given ``weights`` or normals, all points.
    height_model : bool
        Point-to-plane only: where the voting surfaces leave X or Y undetermined (the normals of
        ground and roofs are nearly vertical), match the height models of all points and fill those
        axes when that determines them, as :func:`labkit.registration.icp` does
        (:func:`labkit.registration.height_model.fill_held_axes`); ``result.height_model`` and the
        message say which axes came from where. False: leave them undetermined.
    recentre : bool
        When the best translation lies at a face of the box (within a first-level box or a tenth
        of ``extent``), search once more in a box of the same size centred there along those axes
        and keep the search with the higher consensus: shifts near or beyond ``extent`` are reached
        (the message says so).

    Notes
    -----
    With ``select='all'`` on ALS with vegetation the votes of the crowns can pull the horizontal
    shift by several stated standard deviations without showing in the residuals: weight by
    class (e.g. ``weights={2: 1, 6: 1}``, ground and buildings, on a PointCloud with classes).
    Measurements on real clouds: benchmarks/bench_consensus.py; Monte Carlo checks of the
    stated covariance: tests/test_consensus.py.
    The k-neighbourhood planes lie inside curved surfaces, a bias that no resampling shows; the
    refinement therefore also fits the other way round (target points on the local planes of the
    source, estimating -t) and states the mean of the two, with a jackknife that deletes each block
    from both fits (unless ``weights`` are given: the target has none). The mean cancels that bias
    to first order only; half the measured bias enters the covariance as the std of the remainder.
    Monte Carlo on real random halves: tests/registration/test_real_als_trust.py; on 50 m tiles of sparse
    ALS (0.5 pts/m^2, 160 tiles) rms error / stated std 1.05, 1.08, 1.06 in X, Y, Z, 2 of 480 components
    beyond 3 std (1.15, 1.20, 1.16 and 5 of 480 with the plain jackknife): tests/registration/test_consensus.py.

    Returns
    -------
    RegistrationResult
        method 'max_consensus'; ``history`` holds the branch-and-bound summary
        (:class:`labkit.registration.consensus.bnb.BnBOutcome`) and one record per
        adjustment; the message names the certified gap and why the search stopped.

    Raises
    ------
    LabkitError
        Bad parameters (eps, tol, max_time, init_step, block_size <= 0; max_boxes,
        gap_tol < 0; reject_sigma <= 0; max_points < 3), bad weights or normals;
        DegenerateGeometryError when no target normal is determined; EmptyRegionError
        when the clouds do not overlap within the box.

    References
    ----------
    .. [1] Notebook 06, section 5, eqs. 6.7-6.14; the registration study, step 3.
    .. [2] T.-J. Chin, D. Suter (2017): The Maximum Consensus Problem: Recent Algorithmic Advances.
       Synthesis Lectures on Computer Vision, Morgan & Claypool.
    .. [3] B. Efron (1982): The Jackknife, the Bootstrap and Other Resampling Plans. CBMS-NSF
       Regional Conference Series in Applied Mathematics 38, SIAM, Philadelphia.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> res = max_consensus(source, target, extent=0.08, eps=0.01, tol=0.02, max_points=100, use_numba=False)
    >>> bool(np.allclose(res.translation, [0.05, 0.02, 0.03], atol=0.01))
    True
    """
    check_same_crs(source, target, "max_consensus")
    t0 = time.perf_counter()
    # The points that vote: stable classes or surfaces (selection.py)
    choice(select, SELECT, "select")
    own = weights is not None or source_normals is not None or target_normals is not None
    whole = (source, target)  # the height models use every point (roof edges, crowns)
    source, target, selection = select_points(source, target, "all" if own else select, k=max(int(k), 3))
    # Parameters of the search and of the adjustment
    tol = positive(tol, "tol")
    ext, c = search_box(extent, center)
    opts = _search_options(max_points, max_time, max_boxes, gap_tol, init_step, reject_sigma, block_size, max_std,
                           max_work)
    refine_points = None if refine_points is None else count(refine_points, "refine_points", minimum=3)
    # Reduced coordinates: even subset of the source, search target, normals, tolerances
    pb = prepare_problem(source, target, metric, eps, radius, max_angle_deg, weights, (source_normals, target_normals),
                         k, max_points=opts["max_points"], pair_window=float((ext + np.abs(c)).max()),
                         refine_points=refine_points)
    step0 = opts["init_step"] or max(2 * pb.eps, float(2 * ext.max()) / 32)
    ptr, src_of, D, nrm = candidate_pairs(pb, c - ext, c + ext, pb.radius + 2 * step0)
    # Branch and bound over continuous translations, within the budget
    bb = branch_and_bound(ptr, src_of, D, nrm, pb, c, ext, tol, opts["max_boxes"], step0, opts["gap_tol"],
                          use_numba, max_time=opts["max_time"], max_work=opts["max_work"])
    near = np.abs(bb.translation - c) > ext - np.maximum(step0, 0.1 * ext)
    if recentre and near.any():  # the best shift lies at a face of the box: the maximum may lie beyond it
        c2 = np.where(near, bb.translation, c)
        ptr2, src2, D2, nrm2 = candidate_pairs(pb, c2 - ext, c2 + ext, pb.radius + 2 * step0)
        bb2 = branch_and_bound(ptr2, src2, D2, nrm2, pb, c2, ext, tol, opts["max_boxes"], step0, opts["gap_tol"],
                               use_numba, max_time=opts["max_time"], max_work=opts["max_work"])
        moved = f"best shift at the face of the box +-{ext.max():g} m around {np.round(c, 3).tolist()}: searched again"
        if bb2.lower > bb.lower:
            ptr, src_of, D, nrm, bb, c = ptr2, src2, D2, nrm2, bb2, c2
            moved += f" around {np.round(c2, 3).tolist()} m and kept that search"
        else:
            moved += f" around {np.round(c2, 3).tolist()} m, no better consensus there"
        bb = replace(bb, reason=f"{bb.reason}; {moved}")
    # Least squares with weights and iterative deletion on the consensus set; sandwich covariance
    res = refine(bb, src_of, D, nrm, pb, opts["reject_sigma"], ext, time.perf_counter() - t0, t0,
                 k=max(4, int(k)), block_size=opts["block_size"], max_std=opts["max_std"])
    res = replace(res, selection=selection, message=f"{res.message}; points: {selection.reason}",
                  crs=crs_of(whole[0]) or crs_of(whole[1]))  # the frame of the result, as icp states it
    before = None if res.degeneracy is None else np.asarray(res.degeneracy.axis_determined, dtype=bool)
    if height_model and metric == "point_to_plane":
        res, _ = fill_held_axes(res, *whole)
    filled = None if before is None else np.asarray(res.degeneracy.axis_determined, dtype=bool) & ~before
    # what neither the refinement nor the height model determines: the centre of the consensus hill
    return centre_result(res, pb, c, ext, opts["max_std"] or pb.eps / 2, filled, use_numba=use_numba)


def _search_options(max_points, max_time, max_boxes, gap_tol, init_step, reject_sigma, block_size, max_std,
                    max_work=None) -> dict:
    """Checked budget and adjustment options of :func:`max_consensus`."""
    return {
        "max_work": None if max_work is None else count(max_work, "max_work", minimum=1),
        "max_points": None if max_points is None else count(max_points, "max_points", minimum=3),
        "max_time": None if max_time is None else positive(max_time, "max_time"),
        "max_boxes": count(max_boxes, "max_boxes", minimum=0),
        "gap_tol": non_negative(gap_tol, "gap_tol"),
        "init_step": None if init_step is None else positive(init_step, "init_step"),
        "reject_sigma": positive(reject_sigma, "reject_sigma"),
        "block_size": None if block_size is None else positive(block_size, "block_size"),
        "max_std": None if max_std is None else positive(max_std, "max_std"),
    }
