"""Iterative closest point with rejection, robust weights and a degeneracy report (notebook 05).

The registration study's ``ICP`` and ``Optimierung`` (seed 003, step 2): in every iteration
the correspondences of :func:`labkit.registration.match` are cleaned by iterative
deletion beyond k robust standard deviations and down-weighted by Huber or Tukey,
then one weighted least-squares adjustment gives the update of the
transformation. Equation numbers refer to notebook 05.

This module holds the loop; each step lives in a module named after it:

- robust weights and deletion: :mod:`labkit.registration._icp_weights`
- one adjustment (design, solve, degeneracy): :mod:`labkit.registration._icp_adjustment`
- information after re-matching (eq. 5.12b): :mod:`labkit.registration._icp_information`
- cluster-robust covariance and held priors: :mod:`labkit.registration._icp_covariance`
- update, damping and stopping rules: :mod:`labkit.registration._icp_iteration`
- result, message and consistency test: :mod:`labkit.registration._icp_result`
- coarse-to-fine pyramid: :mod:`labkit.registration.pyramid`

(The module is not called ``icp``: ``labkit.registration.icp`` is the function.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from .._checks import as_points, choice, count, non_negative, positive
from .._crs import check_same_crs
from .._frame import local_origin
from .._report import ReportMixin, fmt
from ..errors import LabkitError
from ..progress import IterationSteps
from ..transforms import angles_from_rotation, check_transform
from ._icp_adjustment import NAMES, IcpSettings, adjust, default_max_std, held_shift_std
from ._icp_information import TiltVariance
from ._icp_iteration import cycle_converged, cycle_period, step_damping, update_transform, within_precision
from ._icp_result import icp_result
from .matching import prepare
from .options import FIELDS, MatchOptions, takes_match_options
from .pyramid import RETRY_REACH, pyramid_icp, retry_with_pyramid, use_pyramid
from .result import RegistrationResult
from .selection import SELECT, check_other_classes, select_points


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
    rng=None,
    progress=False,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` by ICP (seed: ``ICP``).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        The clouds in one frame (UTM allowed). The result maps source onto target.
    dof : {'translation', 'rigid'}
        Estimate (tx, ty, tz) only (the registration study's default) or also three small angles.
    metric : {'point_to_plane', 'point_to_point'}
        Residual per correspondence: eq. (5.2) or the three components of eq. (5.1).
    max_iterations : int
    tol : float
        Convergence when the update is smaller than ``tol`` metres (at the cloud's radius for
        rotations) or than 5 % of every component's standard deviation, when the last four iterates
        lie within 5 % of every component's standard deviation, or when the iteration cycles between a
        few sets of correspondences with updates below ``100 tol`` or within 25 % of every standard
        deviation. A step that points back against the previous one is halved (down to 1/8).
    robust : {None, 'huber', 'tukey'}
        IRLS weights on the standardized residuals (eq. 5.9).
    reject_sigma : float or None
        Iterative deletion of correspondences beyond ``reject_sigma`` robust
        standard deviations (1.4826 MAD, eq. 5.8); None: no deletion.
    robust_start : float
        Deletion and robust weights start once an update is smaller than this (m):
        while the clouds are still far apart the residuals are not yet centred on
        the noise, and a robust scale would throw away whole surfaces.
    initial : ndarray (4, 4), optional
        Initial transformation in the caller's frame.
    rel_threshold : float
        Numerical floor only: the groups of the consistency test determine the eigen-directions
        of their normal matrix above ``rel_threshold`` times the largest one. Whether a component
        of the result is determined is decided by its precision (``max_std``), not by a ratio of
        eigenvalues.
    max_std : float, optional
        Precision limit (m) of determinability (eq. 5.12a): an eigen-direction of the normal
        matrix whose standard deviation ``sigma0 / sqrt(lambda)`` exceeds it is undetermined, and
        the parameters that take part in it are held and reported with std inf. The eigenvalues
        count only the information that survives the re-matching: the part of N that the noise
        of the target normals fakes (a flat field's random normal tilts) is removed first
        (eq. 5.12b). Default: a tenth of ``max_distance`` (0.1 m without a distance gate): a
        component that the data know only to a sizeable fraction of the matching distance (a
        3-sigma interval of more than 0.3 of it) is not determined by them. Rotations count in metres at the cloud's radius.
    held_rotation_std_deg : float
        Prior standard deviation (degrees) of a rotation that ICP holds at its initial value
        (``dof='rigid'``, weak direction). The translation is then conditional on that value; this
        prior's effect on the other parameters, B sigma^2 B^T with B = N_ff^-1 N_fh, is added to
        their stated covariance (eq. 5.15). 0 states the conditional covariance alone.
    covariance : {'formal', 'block'}
        ``'formal'``: sigma0^2 N^-1 of the last adjustment (eq. 5.11). ``'block'``: a
        cluster-robust sandwich J^-1 M J^-1 (eq. 5.13) over square cells of the correspondences:
        M from the sums of the scores a_i p_i v_i per cell (errors may be heteroscedastic,
        wrongly weighted and correlated within a cell), J the derivative of the estimating
        equations including the robust weights and the moving deletion boundary. It is the
        limit of a spatial block bootstrap of the final linear system (no re-matching).
    block_size : float
        Edge of the cells for ``covariance='block'`` in metres (about the diameter of the
        k-neighbourhoods, whose shared points correlate neighbouring correspondences).
    consistency_alpha : float or None
        Level of the test whether all groups of the final correspondences support one
        transformation (eq. 5.16), in up to three groupings: by class (vegetation at either end,
        buildings, ground/road, other) when the pairs fall in two or more of them, by terciles of the
        source points' local noise (vegetation is rough) and by the four spatial quadrants (a changed
        part of the area). When one rejects, the result says so (``consistent`` False, message,
        summary) and its covariance includes the spread between the groups of the grouping that
        disagrees most (a delete-a-group jackknife, eq. 5.17), so that a shift pulled by a changed
        surface does not look confident. On the real Autzen epochs 2010/2023 (a BMX track rebuilt in
        between) the quadrants disagree (T = 118 at 5 dof) and X, Y, Z are stated at +-(0.54, 0.32,
        0.06) m, within 0.6, 0.2, 1.2 combined std of maximum consensus. None: no test.
    min_correspondences : int
        Fewer correspondences after rejection raise :class:`EmptyRegionError`.
    options : MatchOptions, optional
        The matching options in one object (:class:`labkit.registration.MatchOptions`, which documents
        each of them; its defaults are those below). A keyword below given as well overrides its field.
    max_distance, max_angle_deg, classes, class_sigma, default_sigma, noise_weighting, max_noise, sample,
    unique, k, target_normals, source_normals, surface
        The matching options as keywords, see :class:`~labkit.registration.MatchOptions`. ICP matches a
        thinned source with the default ``sample='auto'`` (sources beyond 300,000 points), chooses the
        local surface with ``surface='auto'`` (``result.method`` names it; see Notes) and derives the
        defaults of ``max_std`` and of a held shift's prior from ``max_distance``.
    select : {'auto', 'all'}
        Which points take part (:func:`labkit.registration.selection.select_points`). 'auto' (default):
        on classified clouds the stable classes (ground, building, road surface,
        :data:`labkit.masks.STABLE_CLASSES`), on unclassified ones the surface points (volume scatter -
        vegetation - left out by its local noise and eigenvalues); ``result.selection`` says which and why.
        Given ``classes``, ``max_noise`` or per-point normals, the caller decides and 'auto' uses all points.
        With stable classes, every class left out (50 points or more in both clouds) is registered on its own
        from the result and tested against it: ``result.class_checks`` (which class agrees, which moved).
    rng : int or Generator, optional
        For the sampling.
    progress : bool, "bar", "lines" or callable
        One step per iteration with the current shift and number of pairs (:mod:`labkit.progress`).
    coarse_to_fine : {'auto', True, False}
        Run a voxel pyramid first (:mod:`labkit.registration.pyramid`): coarse levels on voxel-thinned
        clouds with the gate doubled per level, from twice ``reach`` down to ``max_distance``, each
        starting from the previous estimate; then this ICP on the full clouds. The result's covariance,
        degeneracy report and message come from the full clouds only. 'auto' (default): when ``reach``
        exceeds ``max_distance``, and as a retry (with a reach of 2.5 ``max_distance``) when one level
        left axes undetermined while more than 20 % of the searched source points had no partner within
        the gate (:func:`labkit.registration.pyramid.retry_with_pyramid`; a flat field or one-way ridges
        reject 0-0.3 % by distance and are not retried). Measured on real halves moved by 0.3-1.5 m (IGN
        ALS, roofs, conifer forest, Autzen ground at 0.6 pts/m^2, SfM; benchmarks/bench_reach.py): within
        the gate one level reached the same fixed point (within 1 mm or 0.1 std) 1.5-4 times faster; on
        the Autzen halves moved by 1.9-2.5 m one level held X and Y at 0 (undetermined, 28-39 % beyond the
        gate), the pyramid recovered them.
    reach : float, optional
        Largest expected shift (m) for the pyramid; default ``max_distance``. A reach beyond the gate
        switches the pyramid on (with ``coarse_to_fine='auto'``); with ``coarse_to_fine=False`` it is an error.

    Returns
    -------
    RegistrationResult
        ``translation``, ``rotation`` (about ``origin``), ``covariance`` of the last
        adjustment (see ``covariance``) with ``inf`` variances for undetermined parameters, the degeneracy report of N (eq. 5.12), the history of
        :class:`IterationRecord` and the final ``correspondences``.

    Raises
    ------
    EmptyRegionError
        Too few correspondences survive the rejection rules (e.g. no overlap).

    Notes
    -----
    Sampling (``sample='auto'``) keeps the covariance honest: the block covariance (eq. 5.13) takes its
    variance from the residuals of the pairs used (Monte Carlo spread / stated in
    tests/test_icp_sampling.py); distances and the moved cloud are computed for every point by the
    caller, and ``result.message`` states how many pairs were used out of how many source points.

    Local surface (``surface='auto'``): on the real ALS halves at full density (2.7 pts/m^2, mostly
    ground) the plane's X was 13 mm off at a stated 3.5 mm (3.8 std, the same sign over three random
    splits: the sagitta on gently curved ground, weighted by the slopes that determine X); the quadric
    gives -1.5, 3.2, 0.2 mm at a stated 2.9, 2.2, 0.12 mm. Monte Carlo spread / stated with the
    quadric: 1.16, 0.98, 0.99 on the sparse hills, 1.16, 1.19, 1.08 on the test scene with roofs (the
    plane's 1.15, 1.02, 0.98 and 1.15, 1.19, 1.08).

    Undetermined directions (a flat field leaves X and Y free) are those whose standard deviation
    exceeds ``max_std`` (eq. 5.12a), computed from the information that survives re-matching,
    N_sig = N minus the part faked by the random tilts of the target normals (eq. 5.12b; the tilt is
    the larger of its white-noise model and what the two epochs' normals of the pairs show, eq. 5.12c:
    flat ground whose fine relief is new in each epoch leaves X and Y undetermined); weak
    but precise directions (X and Y on gently sloped ALS terrain) are estimated. The parameters
    that take part in undetermined directions are held fixed and the others solved from the
    reduced normal equations; the undetermined components keep their initial value, their
    standard deviation is reported as inf, and the result's message names them. A held
    parameter's prior (``held_rotation_std_deg``, the matching distance for a shift) is carried
    into the covariance of the others (eq. 5.15). The update is N_sig^-1 A^T P l, a Newton step on
    the fixed point of the iteration, so that shifts up to ``max_distance`` converge on sparse
    terrain; the covariance is the sandwich with N_sig as bread. For ``metric='point_to_point'``
    only the components of the rows along the target normals count in N_sig: the offsets between
    two samplings along the surface carry no information about the shift.

    The formal covariance sigma0^2 N^-1 treats the correspondences of the last iteration as
    fixed, independent and correctly weighted. Monte Carlo runs of independent epoch pairs
    (tests/test_icp.py) show it optimistic: spread / stated 1.15, 1.17, 1.06 in X, Y, Z on the
    small test scene (200 pairs, 3-sigma deletion), 1.3-1.45 in X and Y and 1.2-1.3 in Z on the village at
    20 pts/m^2 and 1.15-1.45 with Tukey or Huber weights. Experiments traced this to the
    weights, not to shared neighbourhoods: the weights from local noise (eq. 5.6) are estimated
    from the same data and miss the larger errors at ridges, eaves and walls (with the true
    noise of each material as weights the village gives 1.8, 1.6, 1.1), and sigma0^2 N^-1
    ignores psi' of robust weights and the moving deletion limit. Not the cause: the target's
    plane-fit noise (a target 10 times less noisy leaves the ratio unchanged), k of the normals
    and the sampling density (no trend for k = 10-40 and 1000-16000 points), and the
    re-selection of the pairs by the estimate (the fixed-point map has a slope of about 0.01;
    on the village it adds about 6 % to the spread). The default ``covariance='block'``
    (eq. 5.13) estimates the variance from the residuals themselves, summed over 2 m cells
    (larger cells of 4-8 m were worse: the two faces of a roof have opposite scores); it gave
    1.11, 1.15, 0.97 on the test scene, 1.16, 1.13, 0.98 and 1.06, 1.18, 1.09 on two sets of
    village pairs, 1.12, 1.14, 1.0 with Tukey weights. The remaining 10-15 % in X and Y is not
    visible in the residuals of one registration (about 6 % on the village is the re-selection).

    References
    ----------
    .. [1] Notebook 05, eqs. 5.1-5.18; seed 003, step 2 (ICP with kd-tree matching, own adjustment)
       and step 4 (PCA normals, local noise as weights).
    .. [2] P. J. Besl, N. D. McKay (1992): A method for registration of 3-D shapes. IEEE
       Transactions on Pattern Analysis and Machine Intelligence 14(2), 239-256,
       doi:10.1109/34.121791.
    .. [3] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.
    .. [4] S. Rusinkiewicz, M. Levoy (2001): Efficient variants of the ICP algorithm. Proc. Third
       International Conference on 3-D Digital Imaging and Modeling (3DIM), 145-152.
    .. [5] P. J. Huber (1981): Robust Statistics. Wiley, New York.
    .. [6] A. E. Beaton, J. W. Tukey (1974): The fitting of power series, meaning polynomials,
       illustrated on band-spectroscopic data. Technometrics 16(2), 147-185.
    .. [7] H. White (1980): A heteroskedasticity-consistent covariance matrix estimator and a direct
       test for heteroskedasticity. Econometrica 48(4), 817-838.
    .. [8] K.-Y. Liang, S. L. Zeger (1986): Longitudinal data analysis using generalized linear
       models. Biometrika 73(1), 13-22 (the cluster-robust sandwich).
    .. [9] B. Efron (1982): The Jackknife, the Bootstrap and Other Resampling Plans. CBMS-NSF
       Regional Conference Series in Applied Mathematics 38, SIAM, Philadelphia.

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
    # 1. shared local origin, initial transformation in the local frame
    origin = local_origin(as_points(target, min_points=3, name="target"))
    for cloud, name in ((source, "source"), (target, "target")):
        _require_surface(as_points(cloud, min_points=3, name=name), name)
    R, t = _initial_local(initial, origin)
    # 2. kd-tree of the target, sampling and exclusions: once
    matcher = prepare(source, target, options=options, rng=rng, origin=origin)
    L = max(float(np.sqrt((matcher.source**2).sum(axis=1).mean())), 1.0)
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
    return icp_result(R, t, origin, adj, history, converged, matcher, opts, time.perf_counter() - t_start)


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
    checks = check_other_classes(source, target, res, sel, icp, **_class_settings(settings, options))
    msg = f"{res.message}; points: {sel.reason}"
    moved = [str(c.code) for c in checks if not c.agree]
    if checks:
        msg += (f"; classes left out tested against the shift: {', '.join(moved)} moved" if moved
                else "; the classes left out agree with the shift")
    return replace(res, selection=sel, correspondences=corr, message=msg, class_checks=checks)


def _class_settings(settings, options):
    """The caller's settings for the check of one left-out class: one level, no group test, no progress."""
    out = {k: v for k, v in settings.items() if k not in ("initial", "coarse_to_fine", "reach", "progress")}
    return dict(out, options=options, coarse_to_fine=False, consistency_alpha=None)


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
