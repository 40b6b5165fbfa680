"""Iterative closest point with rejection, robust weights and a degeneracy report (notebook 05).

The registration study's ``ICP`` and ``Optimierung`` (the registration study, step 2): in every iteration
the correspondences of :func:`labkit.registration.match` are cleaned by iterative
deletion beyond k robust standard deviations and down-weighted by Huber or Tukey,
then one weighted least-squares adjustment gives the update of the
transformation. Equation numbers refer to notebook 05.

This module holds the loop; each step lives in a module named after it:

- robust weights and deletion: :mod:`labkit.registration.closest_point.weights`
- one adjustment (design, solve, degeneracy): :mod:`labkit.registration.closest_point.adjustment`
- information after re-matching (eq. 5.12b): :mod:`labkit.registration.closest_point.information`
- cluster-robust covariance and held priors: :mod:`labkit.registration.closest_point.covariance`
- update, damping and stopping rules: :mod:`labkit.registration.closest_point.iteration`
- result, message and consistency test: :mod:`labkit.registration.closest_point.result`
- coarse-to-fine pyramid: :mod:`labkit.registration.closest_point.pyramid`
- one oblique weak direction held alone, moved to the outlines: :mod:`labkit.registration.closest_point.outline`

(The module is not called ``icp``: ``labkit.registration.icp`` is the function.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ...core.checks import as_points, choice, count, non_negative, positive
from ...core.crs import check_same_crs, crs_of
from ...core.frame import local_origin
from ...core.jit import compiled, have_numba
from ...core.report import ReportMixin, fmt
from ...core.errors import LabkitError
from ...core.progress import IterationSteps
from ...transforms import angles_from_rotation, check_transform
from .adjustment import NAMES, IcpSettings, adjust, default_max_std, held_shift_std
from .information import TiltVariance
from .iteration import cycle_converged, cycle_period, step_damping, update_transform, within_precision
from .result import icp_result
from ..matching.match import prepare
from ..options import FIELDS, MatchOptions, takes_match_options
from .pyramid import RETRY_REACH, pyramid_icp, retry_with_pyramid, use_pyramid
from ..result import RegistrationResult
from ..selection import SELECT, check_other_classes, select_points
from ..height_model import fill_held_axes
from .class_shift import class_shift
from .outline import refine_weak_direction


@dataclass(frozen=True, eq=False)
class IterationRecord(ReportMixin):
    """State after one ICP iteration.

    Attributes
    ----------
    iteration : int
    translation : ndarray (3,)
        Current shift (dX, dY, dZ) in metres (rotation about the result's origin).
    rms : float
        Weighted RMS of the residuals of the used correspondences before the update (m).
    n_used : int
        Correspondences in this iteration's adjustment.
    step : float
        Size of the update: |dt| + L |omega| in metres (L: radius of the source).
    rotation_deg : ndarray (3,)
        Current angles rx, ry, rz in degrees.
    scale : float
        Robust scale (1.4826 MAD) of the standardized residuals.
    n_deleted : int
        Correspondences deleted beyond ``reject_sigma`` robust standard deviations.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import icp
    >>> from labkit.synthetic import wavy_surface
    >>> target = wavy_surface(1500, 1, noise=0.001)  # slopes in X and Y, 1 mm noise
    >>> res = icp(target[::5] + [0.02, -0.01, 0.03], target, dof="translation")
    >>> last = res.history[-1]  # one IterationRecord per iteration
    >>> last.iteration == res.iterations, np.round(last.translation, 3)
    (True, array([-0.02,  0.01, -0.03]))
    """

    iteration: int
    translation: np.ndarray
    rms: float
    n_used: int
    step: float
    rotation_deg: np.ndarray
    scale: float
    n_deleted: int

    def _report(self):
        rows = [
            ("translation", fmt(self.translation, 4, "m")),
            ("rms", fmt(self.rms, 4)),
            ("used / deleted", f"{self.n_used} / {self.n_deleted}"),
            ("step", f"{self.step:.2e} m"),
        ]
        return f"ICP iteration {self.iteration}", [("", rows)]


@takes_match_options
def icp(
    source,
    target,
    *,
    options: MatchOptions | None = None,
    dof="translation",
    metric="point_to_plane",
    max_iterations=50,
    tol=1e-5,
    robust=None,
    reject_sigma=3.0,
    robust_start=0.01,
    initial=None,
    rel_threshold=1e-2,
    max_std=None,
    held_rotation_std_deg=0.02,
    covariance="block",
    block_size=2.0,
    consistency_alpha=1e-3,
    min_correspondences=20,
    max_distance=1.0,
    max_angle_deg=30.0,
    classes=None,
    class_sigma=None,
    default_sigma=0.0,
    noise_weighting=True,
    max_noise=None,
    sample="auto",
    unique=True,
    k=20,
    target_normals=None,
    source_normals=None,
    surface="auto",
    coarse_to_fine="auto",
    reach=None,
    select="auto",
    height_model=True,
    outlines=True,
    rng=0,
    progress=False,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` by ICP (seed: ``ICP``).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        The clouds in one frame (UTM allowed). The result maps source onto target.
    options : MatchOptions, optional
        The matching options in one object (:class:`labkit.registration.MatchOptions`, which documents
        each of them). A matching keyword given as well overrides its field.
    dof : {'translation', 'rigid'}
        Estimate (tx, ty, tz) only (default) or also three small angles.
    metric : {'point_to_plane', 'point_to_point'}
        Residual per correspondence: eq. (5.2) or the three components of eq. (5.1).
    max_iterations : int
    tol : float
        Convergence when the update is below ``tol`` metres (rotations at the cloud's radius) or below
        5 % of every component's standard deviation, or when the iterates settle or cycle within
        their precision. A step that reverses the previous one is halved (down to 1/8).
    robust : {None, 'huber', 'tukey'}
        IRLS weights on the standardized residuals (eq. 5.9).
    reject_sigma : float or None
        Iterative deletion beyond ``reject_sigma`` robust standard deviations (1.4826 MAD, eq. 5.8);
        None: no deletion.
    robust_start : float
        Deletion and robust weights start once an update is smaller than this (m).
    initial : ndarray (4, 4), optional
        Initial transformation in the caller's frame.
    rel_threshold : float
        Numerical floor of the consistency test's eigen-directions (relative to the largest).
    max_std : float, optional
        Precision limit (m) of determinability (eq. 5.12a): a direction of the normal matrix, counted
        with the information that survives re-matching (eq. 5.12b), whose standard deviation exceeds
        it is undetermined; its parameters are held and reported with std inf. Default: a tenth of
        ``max_distance``. Rotations count in metres at the cloud's radius.
    held_rotation_std_deg : float
        Prior standard deviation (degrees) of a rotation held at its initial value; its effect on the
        other parameters is added to their covariance (eq. 5.15). 0: the conditional covariance alone.
    covariance : {'formal', 'block'}
        ``'formal'``: sigma0^2 N^-1 (eq. 5.11). ``'block'`` (default): the cluster-robust sandwich
        J^-1 M J^-1 over square cells of the correspondences (eq. 5.13), each std read with the t quantile
        of the cells that inform it (few on sparse ALS, where walls and roof edges alone fix X and Y).
    block_size : float
        Cell edge (m) for ``covariance='block'``.
    consistency_alpha : float or None
        Level of the test whether all groups of the final correspondences support one transformation
        (eq. 5.16), in up to three groupings: by class, by terciles of local noise and by the four
        spatial quadrants. When one rejects, the result says so and its covariance includes the spread
        between the groups of the grouping that disagrees most (jackknife, eq. 5.17). None: no test.
    min_correspondences : int
        Fewer correspondences after rejection raise :class:`EmptyRegionError`.
    max_distance, max_angle_deg, classes, class_sigma, default_sigma, noise_weighting, max_noise, sample,
    unique, k, target_normals, source_normals, surface
        The matching options as keywords, see :class:`~labkit.registration.MatchOptions`.
        ``max_distance`` also sets the defaults of ``max_std`` and of a held shift's prior.
    select : {'auto', 'all'}
        Which points take part (:func:`labkit.registration.selection.select_points`): 'auto' takes
        the stable classes of classified clouds, else the surface points (vegetation left out);
        ``result.selection`` says which and why. Given ``classes``, ``max_noise`` or per-point
        normals, all points take part.
        With stable classes, every class left out (50 points or more in both clouds) is matched at
        the result, its own shift (one translation step) tested against it: ``result.class_checks``.
    height_model : bool or HeightModelShift
        With ``select='auto'``, ``dof='translation'`` and point-to-plane: where the selected points
        leave X or Y undetermined (the normals of ground and roofs are nearly vertical), match the
        height models of all points (roof edges, crowns) and fill those axes when that determines them
        (:func:`labkit.registration.height_model.fill_held_axes`); ``result.height_model`` and the
        message say which axes came from where. False: leave them undetermined. A
        :class:`~labkit.registration.height_model.HeightModelShift` of the same clouds made at
        ``initial`` (``result.height_model`` of :func:`max_consensus` started from): used instead of matching again.
    outlines : bool
        With ``select='auto'``, ``dof='translation'`` and point-to-plane: where X and Y are still held
        because of one oblique undetermined direction (parallel ridges), hold that direction alone, solve
        the rest and move it to where the plan-view outlines agree; X and Y stay undetermined
        (:func:`labkit.registration.closest_point.outline.refine_weak_direction`). False: hold X and Y.
    coarse_to_fine : {'auto', True, False}
        Run a voxel pyramid first (:mod:`labkit.registration.closest_point.pyramid`), from twice ``reach`` down to
        ``max_distance``; the covariance and degeneracy report come from the full clouds. 'auto':
        when ``reach`` exceeds ``max_distance``, and as a retry when one level left axes
        undetermined for want of partners within the gate
        (:func:`labkit.registration.closest_point.pyramid.retry_with_pyramid`).
    reach : float, optional
        Largest expected shift (m) for the pyramid; default ``max_distance``.
    rng : int, Generator or None
        For the sampling (only a source of more than 300,000 points, or an explicit ``sample``, is
        sampled). Default 0: the same input gives the same result in every run; None draws a fresh seed.
    progress : bool, "bar", "lines" or callable
        One step per iteration with the current shift and number of pairs (:mod:`labkit.core.progress`).

    Returns
    -------
    RegistrationResult
        ``translation``, ``rotation`` (about ``origin``), ``covariance`` (see ``covariance``) with
        ``inf`` variances for undetermined parameters, the degeneracy report (eq. 5.12), the
        history of :class:`IterationRecord` and the final ``correspondences``.

    Raises
    ------
    LabkitError
        Bad input (shapes, NaN, identical or collinear points, option values).
    EmptyRegionError
        Too few correspondences survive the rejection rules (e.g. no overlap).

    Notes
    -----
    Each iteration matches (residuals eq. 5.1-5.2, exclusions eq. 5.5), weights and deletes the
    correspondences (eq. 5.6, 5.8-5.9), solves N dx = n (eq. 5.7) and updates R, t (eq. 5.3). Directions the data do not
    determine (eq. 5.12a-b; the tilt of the target normals is the larger of its white-noise model
    and what the two epochs' normals show, eq. 5.12c; a flat field leaves X and Y free) are held at their initial value,
    reported with std inf and named in ``result.message``; a held parameter's prior enters the
    covariance of the others (eq. 5.15). The formal covariance (eq. 5.11) is optimistic because
    the weights are estimated from the same data; the default block covariance (eq. 5.13) takes
    the variance from the residuals. Monte Carlo checks of the stated covariance are in
    tests/test_icp.py; measurements on real clouds in benchmarks/bench_icp.py and
    benchmarks/bench_reach.py.

    References
    ----------
    .. [1] Notebook 05, eqs. 5.1-5.18; the registration study, step 2 (ICP with kd-tree matching, own adjustment)
       and step 4 (PCA normals, local noise as weights).
    .. [2] P. J. Besl, N. D. McKay (1992): A method for registration of 3-D shapes. IEEE
       Transactions on Pattern Analysis and Machine Intelligence 14(2), 239-256,
       doi:10.1109/34.121791.
    .. [3] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.
    .. [4] S. Rusinkiewicz, M. Levoy (2001): Efficient variants of the ICP algorithm. Proc. Third
       International Conference on 3-D Digital Imaging and Modeling (3DIM), 145-152.
    .. [5] K.-Y. Liang, S. L. Zeger (1986): Longitudinal data analysis using generalized linear
       models. Biometrika 73(1), 13-22 (the cluster-robust sandwich).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_surface  # slopes in X and Y; 2 mm noise unless told
    >>> rng = np.random.default_rng(1)
    >>> target = wavy_surface(1500, rng)
    >>> source = wavy_surface(300, rng) - [0.05, 0.02, 0.03]  # another sampling, moved
    >>> res = icp(source, target)
    >>> res.converged, bool(np.allclose(res.translation, [0.05, 0.02, 0.03], atol=0.005))
    (True, True)
    """
    check_same_crs(source, target, "icp")
    # the matching keywords arrive checked in `options` (takes_match_options); the body reads only that
    choice(select, SELECT, "select")
    if select != "all":  # 0. the points that take part: stable classes or surfaces (selection.py)
        settings = {name: v for name, v in locals().items() if name not in ("source", "target", "select", *FIELDS)}
        return _with_selection(source, target, options, settings)
    reach = None if reach is None else positive(reach, "reach")
    if reach is not None and coarse_to_fine is False:
        raise LabkitError("reach= sets the coarsest level of the pyramid: give coarse_to_fine=True or 'auto' with it")
    if coarse_to_fine is not False:  # the voxel pyramid runs this function once per level (pyramid.py)
        settings = {name: v for name, v in locals().items()  # the matching options are in `options`
                    if name not in ("source", "target", "coarse_to_fine", "reach", *FIELDS)}
        choice(coarse_to_fine, (True, False, "auto"), "coarse_to_fine")
        max_distance = options.max_distance
        if coarse_to_fine is True or use_pyramid(max_distance, reach):
            return pyramid_icp(source, target, icp_function=icp, reach=reach, **settings)
        single = icp(source, target, coarse_to_fine=False, **settings)  # 'auto': one level, the pyramid if
        if not retry_with_pyramid(single, max_distance):  # it left axes undetermined for want of partners
            return single
        res = pyramid_icp(source, target, icp_function=icp, reach=RETRY_REACH * max_distance, **settings)
        note = f"; retried coarse-to-fine: one level left {', '.join(single.degeneracy.undetermined_axes)} undetermined"
        return replace(res, runtime_s=res.runtime_s + single.runtime_s, message=res.message + note)
    t_start = time.perf_counter()
    choice(dof, tuple(NAMES), "dof")
    choice(metric, ("point_to_plane", "point_to_point"), "metric")
    choice(robust, (None, "huber", "tukey"), "robust")
    choice(covariance, ("formal", "block"), "covariance")
    block_size = positive(block_size, "block_size")
    positive(max_iterations, "max_iterations")  # > 0; a whole number: checked below
    tol = positive(tol, "tol")
    robust_start = positive(robust_start, "robust_start")
    held_rotation_std = np.radians(non_negative(held_rotation_std_deg, "held_rotation_std_deg"))
    if consistency_alpha is not None and not 0 < consistency_alpha < 1:
        raise LabkitError(f"consistency_alpha must lie in (0, 1) or be None, got {consistency_alpha!r}")
    reject_sigma = None if reject_sigma is None else positive(reject_sigma, "reject_sigma")
    if max_std is not None:
        max_std = positive(max_std, "max_std")
    max_iterations = count(max_iterations, "max_iterations")
    # 1. the clouds checked once; shared local origin, initial transformation in the local frame
    tgt_xyz = as_points(target, min_points=3, name="target")
    src_xyz = as_points(source, min_points=3, name="source")
    _require_surface(src_xyz, "source")
    _require_surface(tgt_xyz, "target")
    origin = local_origin(tgt_xyz)
    R, t = _initial_local(initial, origin)
    # 2. kd-tree of the target, sampling and exclusions: once
    matcher = prepare(source, target, options=options, rng=rng, origin=origin, points=(src_xyz, tgt_xyz), start=(R, t))
    L = max(float(np.sqrt(_squared_norms(matcher.source).mean())), 1.0)  # rms radius of the source points
    opts = IcpSettings(
        origin=origin, dof=dof, metric=metric, robust=robust, reject_sigma=reject_sigma, L=L,
        rel_threshold=rel_threshold, min_correspondences=min_correspondences, covariance=covariance,
        block_size=block_size, held_rotation_std=held_rotation_std, consistency_alpha=consistency_alpha,
        max_std=default_max_std(max_std, matcher.options["max_distance"]),
        held_shift_std=held_shift_std(matcher.options["max_distance"]),
        tilt=TiltVariance(matcher), sample=options.sample,
    )  # fmt: skip
    plain = replace(opts, robust=None, reject_sigma=None, cascade=False)  # warm-up stage: no robust measures, no cascade
    history, converged, adj, step, robust_stage = [], False, None, np.inf, False
    damping, previous = 1.0, None  # step length factor, halved when a step reverses the last one
    # 3. iterate: match, clean, adjust, update (progress: one step per iteration, shift and pairs)
    steps = IterationSteps(progress, max_iterations, "ICP")
    for it in range(1, max_iterations + 1):
        steps.update(history)
        # once entered, the robust stage stays: its first steps can be large (the outliers
        # lose their pull), and falling back to the plain stage would undo them (a 3-cycle)
        robust_stage = robust_stage or step < robust_start
        corr = matcher(R, t)
        adj = adjust(corr, R, t, opts if robust_stage else plain)
        damping, previous = step_damping(adj.dx, previous, damping, L, tol)
        R, t, step = update_transform(R, t, damping * adj.dx, dof, L)
        history.append(_record(it, R, t, adj, step))
        final_stage = robust_stage or (robust is None and reject_sigma is None)
        cycle = cycle_period(history, max(0.1 * tol, 0.01 * _smallest_std(adj)))  # repeats within 1 % of a std
        small = step < tol or within_precision(adj)
        settled = len(history) >= 4 and cycle_converged(history[-4:], adj, tol, share=0.05)  # damped chatter
        if final_stage and (small or settled or (cycle and cycle_converged(history[-cycle:], adj, 100 * tol))):
            converged = True
            break
    steps.close(history)
    # 4. final report from the last adjustment
    res = icp_result(R, t, origin, adj, history, converged, matcher, opts, time.perf_counter() - t_start)
    return replace(res, crs=crs_of(source) or crs_of(target))  # the other routes return this one's result


def _with_selection(source, target, options, settings):
    """icp on the points that :func:`select_points` chose; the result names them."""
    own = (options.classes is not None or options.max_noise is not None
           or options.source_normals is not None or options.target_normals is not None)
    if own:
        src, tgt, sel = select_points(source, target, "all", k=options.k)
        sel = replace(sel, reason="all points (classes, max_noise or normals given by the caller)")
    else:
        src, tgt, sel = select_points(source, target, "auto", k=options.k)
    res = icp(src, tgt, select="all", **settings)
    corr = res.correspondences
    if corr is not None and sel.source_rows is not None:  # indices into the caller's clouds
        back = lambda rows, i: np.where(i >= 0, rows[np.clip(i, 0, None)], -1)  # noqa: E731
        corr = replace(corr, source_index=back(sel.source_rows, corr.source_index),
                       target_index=back(sel.target_rows, corr.target_index), n_source=sel.n_source)
    if settings["height_model"] and settings["dof"] == "translation" and settings["metric"] == "point_to_plane":
        # X, Y from height jumps where the normals of the selected surfaces leave them undetermined
        hm = settings["height_model"]  # True, or a match made at the start (max_consensus): not matched again
        res, _ = fill_held_axes(res, source, target, matched=None if hm is True else hm)
    if settings["outlines"] and settings["dof"] == "translation" and settings["metric"] == "point_to_plane":
        # one oblique weak direction: held alone, the rest solved, moved to the outlines' estimate
        res = refine_weak_direction(res, src, tgt, dict(settings, options=options), icp)
    checks = check_other_classes(source, target, res, sel, class_shift, **_class_settings(settings, options))
    msg = f"{res.message}; points: {sel.reason}"
    moved = [str(c.code) for c in checks if not c.agree]
    if checks:
        msg += (f"; classes left out tested against the shift: {', '.join(moved)} moved" if moved
                else "; the classes left out agree with the shift")
    return replace(res, selection=sel, correspondences=corr, message=msg, class_checks=checks)


def _class_settings(settings, options):
    """The caller's settings for the check of one left-out class: one level, no group test, no progress."""
    out = {k: v for k, v in settings.items()
           if k not in ("initial", "coarse_to_fine", "reach", "progress", "height_model", "outlines")}
    return dict(out, options=options, coarse_to_fine=False, consistency_alpha=None)


def _squared_norms(p):
    """``(p**2).sum(axis=1)`` of the points p (n, 3): the same sums, (x^2 + y^2) + z^2, in one compiled pass (numpy's
    reduction over a row of three is slow)."""
    if not have_numba():  # pragma: no cover - depends on the environment
        return (p**2).sum(axis=1)
    return compiled(_squared_norms_kernel)(np.ascontiguousarray(p, dtype=np.float64))


def _squared_norms_kernel(p):  # pragma: no cover - compiled
    out = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        out[i] = (p[i, 0] * p[i, 0] + p[i, 1] * p[i, 1]) + p[i, 2] * p[i, 2]
    return out


def _smallest_std(adj):
    """The smallest finite formal standard deviation of the shift (m; 0 when none is finite)."""
    with np.errstate(invalid="ignore"):
        std = adj.sigma0 * np.sqrt(np.diag(adj.Qxx)[-3:])
    std = std[np.isfinite(std)]
    return float(std.min()) if std.size else 0.0


def _require_surface(points, name):
    """Identical or collinear points have no surface: no normals, and a shift along the line is free."""
    sub = points[:: max(1, len(points) // 20000)]
    centre = sub.mean(axis=0)
    s = np.linalg.svd(sub - centre, compute_uv=False) / np.sqrt(len(sub))  # rms spread per axis
    identical = s[0] <= 1e-12 * max(1.0, float(np.abs(centre).max()))  # rounding of large coordinates
    if identical or s[1] <= 1e-9 * s[0]:
        what = "identical" if identical else "collinear"
        raise LabkitError(
            f"the {name} points are {what}: ICP needs a surface (points spread in two directions) "
            "to find normals and correspondences"
        )


def _initial_local(initial, origin):
    """(R, t) in the local frame from a 4x4 in the caller's frame: t_l = R0 o + t0 - o."""
    if initial is None:
        return np.eye(3), np.zeros(3)
    T = check_transform(initial)
    R0 = T[:3, :3]
    return R0.copy(), R0 @ origin + T[:3, 3] - origin


def _record(it, R, t, adj, step):
    return IterationRecord(
        iteration=it, translation=t.copy(), rms=adj.rms, n_used=adj.corr.n_accepted, step=step,
        rotation_deg=np.degrees(angles_from_rotation(R)), scale=adj.scale, n_deleted=adj.n_deleted,
    )
