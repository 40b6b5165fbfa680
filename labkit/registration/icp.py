"""Iterative closest point with rejection, robust weights and a degeneracy report (notebook 05).

The seed's ``ICP`` and ``Optimierung`` (seed 003, step 2): in every iteration
the correspondences of :func:`labkit.registration.match` are cleaned by iterative
deletion beyond k robust standard deviations and down-weighted by Huber or Tukey,
then one weighted least-squares adjustment gives the update of the
transformation. Equation numbers refer to notebook 05.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.stats import chi2, norm

from .._checks import as_points, choice, positive
from .._frame import local_origin
from .._report import ReportMixin, fmt
from ..errors import EmptyRegionError, LabkitError
from ..progress import IterationSteps
from ..transforms import angles_from_rotation, check_transform
from .matching import Correspondences, prepare
from .pyramid import RETRY_REACH, pyramid_icp, retry_with_pyramid, use_pyramid
from .result import RegistrationResult, degeneracy_report, group_consistency

NAMES = {"translation": ("tx", "ty", "tz"), "rigid": ("rx", "ry", "rz", "tx", "ty", "tz")}
HUBER_C, TUKEY_C = 1.345, 4.685  # 95 % efficiency under normal errors
#: A parameter with this squared share in the undetermined eigen-directions is held fixed (and reported).
HELD_SHARE = 0.05
MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4)
#: The tilt information of eq. (5.12b) is summed over at most this many correspondences (an even subset).
TILT_ROWS = 8000
#: Groups of the consistency test by the classes (ASPRS) of a correspondence's two points, in order of
#: precedence (vegetation at either end makes it 'vegetation'); the rest is 'other'.
CLASS_GROUPS = (("vegetation", (3, 4, 5)), ("buildings", (6,)), ("ground/road", (2, 11)))
#: The stable classes suggested when the class groups disagree.
STABLE = (2, 6, 11)


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


@dataclass(frozen=True, eq=False)
class _Adjustment:
    """One weighted least-squares step (private)."""

    dx: np.ndarray  # update of the parameters (unscaled)
    N: np.ndarray  # normal matrix in scaled parameters
    Qxx: np.ndarray  # cofactor matrix of the unscaled parameters (inf where undetermined)
    block_cov: object  # () -> cluster-robust covariance (unscaled), covariance="block"; only the last one is used
    held_cov: np.ndarray  # effect of the held rotations' prior on the other parameters (unscaled)
    sigma0: float
    rms: float
    redundancy: int
    degeneracy: object
    corr: Correspondences
    scale: float
    n_deleted: int


def icp(
    source,
    target,
    *,
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
    rng=None,
    progress=False,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` by ICP (seed: ``ICP``).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        The clouds in one frame (UTM allowed). The result maps source onto target.
    dof : {'translation', 'rigid'}
        Estimate (tx, ty, tz) only (the seed's default) or also three small angles.
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
        transformation (eq. 5.16): groups by class (vegetation at either end, buildings,
        ground/road, other) when both clouds have a classification, else by terciles of the
        source points' local noise (vegetation is rough), else the four spatial quadrants. When it rejects, the result says so (``consistent`` False, message,
        summary) and its covariance includes the spread between the groups (a delete-a-group
        jackknife, eq. 5.17), so that a shift pulled by a changed surface does not look
        confident. None: no test.
    min_correspondences : int
        Fewer correspondences after rejection raise :class:`EmptyRegionError`.
    surface : {'auto', 'plane', 'quadric'}
        Local surface model of the matching (:func:`labkit.registration.match`). 'auto' (default):
        a local quadric through q_j where the target's k-neighbourhoods are wider than 1 m
        (sparse ALS), the PCA plane through q_j on denser clouds (TLS, dense ALS), where its
        sagitta is negligible.
        On the real ALS halves at full density (2.7 pts/m^2, mostly ground) the plane's X was
        13 mm off at a stated 3.5 mm (3.8 std, the same sign over three random splits: the
        sagitta on gently curved ground, weighted by the slopes that determine X); the quadric
        gives -1.5, 3.2, 0.2 mm at a stated 2.9, 2.2, 0.12 mm. Monte Carlo spread / stated with
        the quadric: 1.16, 0.98, 0.99 on the sparse hills, 1.16, 1.19, 1.08 on the test scene with
        roofs (the plane's 1.15, 1.02, 0.98 and 1.15, 1.19, 1.08). ``result.method`` names the
        model used.
    sample : None, 'auto', int or (method, value)
        Source points that form pairs (:func:`labkit.registration.match`). Default ``'auto'``: the
        whole source up to 300,000 points; a larger one is thinned to about 100,000 points spread
        evenly in space and over the normal directions, so that the shift of a 10-million-point
        cloud costs what that of a 100,000-point cloud costs. The covariance stays honest (the block
        covariance, eq. 5.13, takes its variance from the residuals of the pairs used; Monte Carlo
        spread / stated in tests/test_icp_sampling.py). Distances and the moved cloud are computed
        for every point by the caller. ``result.message`` states how many pairs were used out of
        how many source points. None: every source point.
    max_distance, max_angle_deg, classes, class_sigma, default_sigma, noise_weighting, max_noise, unique, k,
    target_normals, source_normals, rng
        Matching options, see :func:`labkit.registration.match`.
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
    Undetermined directions (a flat field leaves X and Y free) are those whose standard deviation
    exceeds ``max_std`` (eq. 5.12a), computed from the information that survives re-matching,
    N_sig = N minus the part faked by the random tilts of the target normals (eq. 5.12b); weak
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
    """
    reach = None if reach is None else positive(reach, "reach")
    if reach is not None and coarse_to_fine is False:
        raise LabkitError("reach= sets the coarsest level of the pyramid: give coarse_to_fine=True or 'auto' with it")
    if coarse_to_fine is not False:  # the voxel pyramid runs this function once per level (pyramid.py)
        options = {k: v for k, v in locals().items() if k not in ("source", "target", "coarse_to_fine", "reach")}
        choice(coarse_to_fine, (True, False, "auto"), "coarse_to_fine")
        if coarse_to_fine is True or use_pyramid(max_distance, reach):
            return pyramid_icp(source, target, icp_function=icp, reach=reach, **options)
        single = icp(source, target, coarse_to_fine=False, **options)  # 'auto': one level, the pyramid if
        if not retry_with_pyramid(single, max_distance):  # it left axes undetermined for want of partners
            return single
        res = pyramid_icp(source, target, icp_function=icp, reach=RETRY_REACH * max_distance, **options)
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
    held_rotation_std = np.radians(_non_negative(held_rotation_std_deg, "held_rotation_std_deg"))
    if consistency_alpha is not None and not 0 < consistency_alpha < 1:
        raise LabkitError(f"consistency_alpha must lie in (0, 1) or be None, got {consistency_alpha!r}")
    kval = None if reject_sigma is None else positive(reject_sigma, "reject_sigma")
    if max_std is not None:
        max_std = positive(max_std, "max_std")
    k = _whole(k, "k")
    max_iterations = _whole(max_iterations, "max_iterations")
    # 1. shared local origin, initial transformation in the local frame
    origin = local_origin(as_points(target, min_points=3, name="target"))
    for cloud, name in ((source, "source"), (target, "target")):
        _require_surface(as_points(cloud, min_points=3, name=name), name)
    R, t = _initial_local(initial, origin)
    # 2. kd-tree of the target, sampling and exclusions: once
    matcher = prepare(
        source, target, target_normals=target_normals, source_normals=source_normals,
        max_distance=max_distance, max_angle_deg=max_angle_deg, classes=classes,
        class_sigma=class_sigma, default_sigma=default_sigma, noise_weighting=noise_weighting,
        max_noise=max_noise, sample=sample, unique=unique, k=k, rng=rng, origin=origin, surface=surface,
    )  # fmt: skip
    L = max(float(np.sqrt((matcher.source**2).sum(axis=1).mean())), 1.0)
    opts = dict(
        origin=origin, dof=dof, metric=metric, robust=robust, k=kval, L=L, rel=rel_threshold,
        min_n=min_correspondences, covariance=covariance, block_size=block_size,
        held_rotation_std=held_rotation_std, alpha=consistency_alpha,
        max_std=_default_max_std(max_std, matcher.options["max_distance"]),
        held_shift_std=_held_shift_std(matcher.options["max_distance"]),
        tilt=_TiltVariance(matcher), sample=sample,
    )  # fmt: skip
    opts["cascade"] = True
    plain = dict(opts, robust=None, k=None, cascade=False)  # warm-up stage: no robust measures, no cascade
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
        adj = _adjust(corr, R, t, opts if robust_stage else plain)
        damping, previous = _damping(adj.dx, previous, damping, L, tol)
        R, t, step = _update(R, t, damping * adj.dx, dof, L)
        history.append(_record(it, R, t, adj, step))
        final_stage = robust_stage or (robust is None and kval is None)
        cycle = _cycle(history, 0.1 * tol)
        small = step < tol or _within_precision(adj)
        settled = len(history) >= 4 and _cycle_converged(history[-4:], adj, tol, share=0.05)  # damped chatter
        if final_stage and (small or settled or (cycle and _cycle_converged(history[-cycle:], adj, 100 * tol))):
            converged = True
            break
    steps.close(history)
    # 4. final report from the last adjustment
    return _result(R, t, origin, adj, history, converged, matcher, opts, time.perf_counter() - t_start)


def _whole(value, name):
    """An integer parameter given as an int or an integral float; 20.5 is an error, not 20."""
    try:
        ok = float(value) == int(value)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if isinstance(value, (bool, str)) or not ok:
        raise LabkitError(f"{name} must be a whole number, got {value!r}")
    return int(value)


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


def _default_max_std(max_std, max_distance):
    """The precision limit of determinability: given, or a tenth of the matching distance."""
    if max_std is not None:
        return float(max_std)
    return 0.1 * max_distance if np.isfinite(max_distance) else 0.1


def _held_shift_std(max_distance):
    """Prior std of a held translation: its true value can lie anywhere within the matching distance."""
    return float(max_distance) if np.isfinite(max_distance) else 1.0


class _TiltVariance:
    """Covariance of the random tilt of each target point's PCA normal, computed once per point (private).

    A plane fitted to k neighbours with noise sigma_n has, along each tangent eigen-direction e_j of
    the neighbours' spread lambda_j, a slope error of variance sigma_n^2 / (k lambda_j): the error
    of a regression slope. The tilt covariance is sum_j e_j e_j^T sigma_n^2 / (k lambda_j), with
    sigma_n^2 = k lambda_0 / (k - 3) (notebook 04, eq. 5). With ``surface='quadric'`` the normal is
    the quadric's (at the foot point near q_j), whose slopes are fitted together with the
    curvatures and tilt more: the covariance of the slopes at q_j from the quadric's fit is used.
    """

    def __init__(self, matcher):
        self.points, self.tree, self.k = matcher.target, matcher.tree, matcher.options["k"]
        self.slot = np.full(len(self.points), -1, dtype=np.int64)  # row in C of each computed point
        self.C = np.empty((0, 3, 3))  # only the points ever asked for (a few of a large target)
        quadric = matcher.options.get("surface") == "quadric"
        self.geometry = matcher.geometry if quadric else None
        self.stored = getattr(getattr(matcher, "geometry", None), "plane_tilt", None)  # kept with the normals

    def __call__(self, j):
        if self.geometry is not None:  # the quadric's slopes (computed with the matching)
            C = self.geometry.tilt(j)
            bad = np.isnan(C[:, 0, 0])
            if bad.any():
                C[bad] = self._plane(j[bad])
            return C
        return self._plane(j)

    def _plane(self, j):
        if self.stored is not None:
            return self.stored(j)
        todo = np.unique(j[self.slot[j] < 0])
        if todo.size:
            new = [self._compute(todo[a : a + 50000]) for a in range(0, todo.size, 50000)]  # bounded gathers
            self.slot[todo] = len(self.C) + np.arange(todo.size)
            self.C = np.concatenate([self.C, *new])
        return self.C[self.slot[j]]

    def _compute(self, index):
        k = self.k
        nb = self.tree.query(self.points[index], k=k, workers=-1 if len(index) > 2000 else 1)[1]
        X = self.points[nb]
        X = X - X.mean(axis=1, keepdims=True)
        lam, V = np.linalg.eigh(np.einsum("cki,ckj->cij", X, X) / k)  # ascending
        s2 = np.clip(lam[:, 0], 0, None) * k / (k - 3)
        t = np.clip(lam[:, 1:], 1e-300, None)
        w = np.clip(s2[:, None] / (k * t), 0.0, 1.0)  # tilt variance along e_1, e_2
        return np.einsum("cj,cij,ckj->cik", w, V[:, :, 1:], V[:, :, 1:])


def _within_precision(adj, share=0.05):
    """True when every component of the update is below ``share`` of its formal standard deviation.

    In a weak direction the nearest neighbours keep changing and the iteration jitters about its
    fixed point by a small fraction of that direction's precision; an absolute ``tol`` would wait
    for it in vain.
    """
    with np.errstate(invalid="ignore"):
        std = adj.sigma0 * np.sqrt(np.diag(adj.Qxx))
    ok = np.isfinite(std)
    return bool(ok.any() and np.all(np.abs(adj.dx[ok]) <= share * std[ok]))


def _damping(dx, previous, damping, L, tol, floor=0.125):
    """Halve the step length (down to ``floor``) when a step reverses the previous one.

    The update N_sig^-1 A^T P l (eq. 5.12b) moves a weak direction the whole way in one step; where the
    tilt noise removed from N is most of a direction's information, the step overshoots and ICP
    oscillates about the fixed point (synthetic forest ALS vs DIM, X known to about 0.1 m: a 4-cycle
    of 75 mm that never converged). A reversal is a step pointing back by more than 120 degrees
    (rotations in metres at the radius L); damping changes the path, not the fixed point.
    """
    s = np.array(dx, dtype=np.float64)
    s[:-3] *= L
    size = np.linalg.norm(s)
    if previous is not None and size > 10 * tol and s @ previous < -0.5 * size * np.linalg.norm(previous):
        damping = max(0.5 * damping, floor)
    return damping, s


def _cycle_converged(cycle, adj, atol, share=0.25):
    """A cycle between a few sets of pairs is converged when its steps are below ``atol`` or when it
    moves every component by at most ``share`` of that component's standard deviation (real ALS halves:
    a 2-cycle of 1.08 mm steps, 0.2 std in X, ran to max_iterations). With ``share=0.05`` over the last
    four iterations the same test ends the damped chatter between two sets of pairs, which never
    repeats exactly (sparse hills: 0.15 mm steps at a stated 26 mm for 35 iterations)."""
    if max(h.step for h in cycle) < atol:
        return True
    with np.errstate(invalid="ignore"):
        std = adj.sigma0 * np.sqrt(np.diag(adj.Qxx))
    span = np.ptp([h.translation for h in cycle], axis=0)
    if len(std) == 6:  # rigid: rx, ry, rz (rad), tx, ty, tz
        span = np.r_[np.radians(np.ptp([h.rotation_deg for h in cycle], axis=0)), span]
    free = np.isfinite(std)
    return bool(free.any() and np.all(span[free] <= share * std[free]) and np.all(span[~free] <= atol))


def _cycle(history, atol, longest=10):
    """Period p if the state repeats the one p iterations ago within ``atol`` (nearest neighbours
    can alternate between a few sets), else 0."""
    x = history[-1]
    for p in range(2, longest + 1):
        if len(history) > p:
            y = history[-1 - p]
            same_t = np.allclose(x.translation, y.translation, rtol=0, atol=atol)
            if same_t and np.allclose(x.rotation_deg, y.rotation_deg, rtol=0, atol=np.degrees(atol) / 100):
                return p
    return 0


def _initial_local(initial, origin):
    """(R, t) in the local frame from a 4x4 in the caller's frame: t_l = R0 o + t0 - o."""
    if initial is None:
        return np.eye(3), np.zeros(3)
    T = check_transform(initial)
    R0 = T[:3, :3]
    return R0.copy(), R0 @ origin + T[:3, 3] - origin


# ------------------------------------------------------------------ one adjustment


def _design(corr, R, t, opts):
    """Design rows A (m, r, u), observations l (m, r) and weights of the accepted rows."""
    ok = corr.accepted
    p = corr.source_xyz[ok] - opts["origin"]  # current source points, local frame
    d = corr.d[ok]
    n = corr.target_normal[ok]
    rigid = opts["dof"] == "rigid"
    if opts["metric"] == "point_to_plane":
        l = np.einsum("ij,ij->i", n, d)[:, None]  # l_i = n . (q - p)  (eq. 5.2)
        A = n[:, None, :]
        if rigid:  # n . (omega x p) = omega . (p x n)  (eq. 5.4)
            A = np.concatenate([np.cross(p, n)[:, None, :] / opts["L"], A], axis=2)
    else:
        l = d  # three components per correspondence (eq. 5.1)
        A = np.broadcast_to(np.eye(3), (len(d), 3, 3))
        if rigid:  # omega x p = -[p]x omega  (eq. 5.5)
            A = np.concatenate([-_skew(p) / opts["L"], A], axis=2)
    return A, l, corr.weight[ok]


def _skew(p):
    z = np.zeros(len(p))
    return np.stack(
        [np.stack([z, -p[:, 2], p[:, 1]], 1), np.stack([p[:, 2], z, -p[:, 0]], 1), np.stack([-p[:, 1], p[:, 0], z], 1)],
        axis=1,
    )


def _robust(corr, l, w, opts):
    """Iterative deletion (eq. 5.8) and IRLS weights (eq. 5.9) from standardized residuals."""
    e = np.sqrt(w)[:, None] * l
    centred = e - np.median(e, axis=0)
    r = centred.shape[1]
    size = np.linalg.norm(centred, axis=1)
    # robust scale of one component: MAD (r = 1) or the median of a chi distribution (r = 3)
    scale = np.median(size) / (np.sqrt(chi2.ppf(0.5, r)))
    scale = max(scale, 1e-12)
    u = size / scale
    keep = np.ones(len(u), dtype=bool)
    if opts["k"] is not None:
        limit = np.sqrt(chi2.ppf(1 - 2 * norm.sf(opts["k"]), r))  # k sigma, two-sided, r components
        keep = u <= limit
    if opts["robust"] == "huber":
        factor = np.minimum(1.0, HUBER_C / np.maximum(u, 1e-12))
    elif opts["robust"] == "tukey":
        factor = np.where(u < TUKEY_C, (1 - (u / TUKEY_C) ** 2) ** 2, 0.0)
    else:
        factor = np.ones(len(u))
    return keep, factor * keep, scale, u, centred


def _psi_prime(u, robust):
    """Derivative of the influence function psi(u) = u * factor(u) (Huber 1981)."""
    if robust == "huber":
        return (u <= HUBER_C).astype(np.float64)
    if robust == "tukey":
        q = (u / TUKEY_C) ** 2
        return np.where(u < TUKEY_C, (1 - q) * (1 - 5 * q), 0.0)
    return np.ones_like(u)


def _block_covariance(A, l, w, u, centred, keep, factor, dx_s, free, opts):
    """Cluster-robust sandwich J^-1 M J^-1 in the scaled parameters (eq. 5.13); inf where held.

    M = sum over cells c of g_c g_c^T with g_c = sum_(i in c) A_i^T p_i v_i (scores of the kept
    rows); J = -d(A^T P l)/dx: sum w A_i^T [psi'(u) e e^T + psi(u)/u (I - e e^T)] A_i over the kept
    rows minus psi(k) w A_i^T e e^T A_i times the density of |u| at the deletion limit k (the
    boundary moves with x, eq. 5.14); e = unit direction of the standardized residual.
    """
    p = A.shape[2]
    fixed = ~free
    cov = np.full((p, p), np.nan)
    cov[free, :] = cov[:, free] = np.inf
    P = w * factor
    v = np.einsum("mru,u->mr", A, dx_s) - l
    g = np.einsum("mru,m,mr->mu", A, P, v)[keep][:, fixed]  # score of each kept correspondence
    cells = np.floor(opts["xy"][keep] / opts["block_size"]).astype(np.int64)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    G = np.zeros((cell.max() + 1, g.shape[1]))
    np.add.at(G, cell.ravel(), g)
    n_cells, m = len(G), len(g)
    if n_cells < 2 * g.shape[1]:
        return cov  # too few cells for a sandwich: NaN, the caller falls back to the formal one
    M = G.T @ G * n_cells / (n_cells - 1)  # small-sample factor of the cluster sandwich
    e = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-300)
    Ae = np.einsum("mru,mr->mu", A, e)  # A^T e per row
    AA = np.einsum("mru,mrv->muv", A, A)
    dpsi = _psi_prime(u, opts["robust"])  # factor = psi(u) / u
    inner = factor[:, None, None] * AA + ((dpsi - factor)[:, None, None] * np.einsum("mu,mv->muv", Ae, Ae))
    J = np.einsum("m,muv->uv", (w * keep), inner)
    if opts["k"] is not None:  # rows crossing the deletion limit as x changes
        r = A.shape[1]
        limit = np.sqrt(chi2.ppf(1 - 2 * norm.sf(opts["k"]), r))
        h = 0.1 * limit
        near = np.abs(u - limit) < h
        psi_limit = limit * (np.median(factor[keep & near]) if (keep & near).any() else 1.0)
        J -= psi_limit / (2 * h) * np.einsum("m,mu,mv->uv", w * near, Ae, Ae)
    J = (J - opts["N_eps"])[np.ix_(fixed, fixed)]  # the bread: what survives re-matching (eq. 5.12b)
    try:
        c = cho_factor(0.5 * (J + J.T))
    except np.linalg.LinAlgError:
        return cov
    Ji = cho_solve(c, np.eye(len(J)))
    cov[np.ix_(fixed, fixed)] = Ji @ M @ Ji * m / max(m - g.shape[1], 1)
    return cov


def _adjust(corr, R, t, opts):
    """One weighted LS step on the current correspondences (eqs. 5.7-5.12)."""
    _check_count(corr, opts)
    A, l, w = _design(corr, R, t, opts)
    keep, factor, scale, u, centred = _robust(corr, l, w, opts)
    ok_rows = np.flatnonzero(corr.accepted)
    corr = corr.with_outliers(np.isin(np.arange(len(corr)), ok_rows[~keep]))
    weights = np.zeros(len(corr))
    weights[ok_rows] = w * factor
    corr = corr.with_weights(weights)
    _check_count(corr, opts)
    P = (w * factor)[keep]
    A_all, l_all = A, l
    A, l = A[keep], l[keep]
    N = np.einsum("mru,m,mrv->uv", A, P, A)  # N = A^T P A  (eq. 5.7)
    nvec = np.einsum("mru,m,mr->u", A, P, l)  # n = A^T P l
    names = NAMES[opts["dof"]]
    N_eps = _tilt_information(corr, ok_rows[keep], P, opts)
    N_sig = _normal_information(A, P, corr.target_normal[ok_rows[keep]], N, opts) - N_eps  # (eq. 5.12b)
    deg = degeneracy_report(
        _sandwich_precision(N, N_sig), names, opts["rel"], slice(len(names) - 3, None), share_threshold=HELD_SHARE,
        hold_first=names[:-3], sigma0=scale, max_std=opts["max_std"],
    )  # rotations are given up before translations; precision limit (eq. 5.12a)  # fmt: skip
    dx_s, Q_s, step_s = _solve(N, nvec, deg, N_sig)
    shift_prior_only = {**opts, "held_rotation_std": 0.0}
    for _ in range(len(names) if opts["cascade"] else 0):  # once settled: a parameter left imprecise by
        # held shifts (prior: max_distance) is held too
        if deg.parameter_determined[-3:].all():  # no shift held: nothing spreads its prior
            break
        held_s = _held_rotation_covariance(N_sig, deg, shift_prior_only)
        with np.errstate(invalid="ignore"):
            std_s = np.sqrt(np.clip(scale**2 * np.diag(Q_s) + np.diag(held_s), 0, None))
        worse = deg.parameter_determined & (std_s > opts["max_std"])
        if not worse.any():
            break
        keep_det = deg.parameter_determined & ~worse
        deg = replace(deg, parameter_determined=keep_det, axis_determined=keep_det[-3:].copy())
        dx_s, Q_s, step_s = _solve(N, nvec, deg, N_sig)
    v = np.einsum("mru,u->mr", A, dx_s) - l  # residuals after the step
    vPv = float(np.einsum("mr,m,mr->", v, P, v))
    r = len(P) * A.shape[1] - int(deg.constrained.sum())  # redundancy
    sigma0 = np.sqrt(vPv / r) if r > 0 else np.nan  # (eq. 5.10)
    rms = float(np.sqrt(np.einsum("mr,m,mr->", l, P, l) / max(P.sum(), 1e-300)))
    S = np.ones(len(names))
    S[: len(names) - 3] = opts["L"]  # rotation columns were divided by L
    dx = step_s / S  # the update: Newton on the fixed point, whose slope is N_sig (eq. 5.12b)
    Qxx = Q_s / np.outer(S, S)
    held_cov = _held_rotation_covariance(N_sig, deg, opts) / np.outer(S, S)
    block = None
    if opts["covariance"] == "block":
        xy = corr.source_xyz[ok_rows, :2] - opts["origin"][:2]
        free = np.isinf(np.diag(Q_s))
        args = (A_all, l_all, w, u, centred, keep, factor, dx_s, free, {**opts, "xy": xy, "N_eps": N - N_sig})
        block = lambda: _block_covariance(*args) / np.outer(S, S)  # noqa: E731 - evaluated for the last step only
    return _Adjustment(dx, N, Qxx, block, held_cov, float(sigma0), rms, r, deg, corr, float(scale), int((~keep).sum()))


def _normal_information(A, P, n, N, opts):
    """The part of N along the target normals: what a shift changes after re-matching (eq. 5.12b).

    Point-to-plane rows already are that part (N itself). A point-to-point residual q - p also holds
    the offset between the two samplings along the surface; a shift along the surface re-matches the
    points and leaves that offset's mean unchanged, so only the rows' components along the normal,
    A^T n, carry information. Without this, point-to-point ICP on two samplings of one surface
    claimed millimetres in X and Y while 10-100 stated sigma off.
    """
    if opts["metric"] == "point_to_plane":
        return N
    a = np.einsum("mru,mr->mu", A, np.nan_to_num(n))  # A^T n per row
    return np.einsum("m,mu,mv->uv", P, a, a)


def _tilt_information(corr, rows, P, opts):
    """The part of N that the random tilt of the target normals fakes (eq. 5.12b), scaled parameters.

    A point-to-plane row a_i = G_i n_i (G = I, or [[p]x / L; I] for rigid) uses the estimated normal
    n = n0 + e with a tilt e of covariance C_i (see :class:`_TiltVariance`). E[a a^T] = G (n0 n0^T + C_e) G^T: the
    second part is information about the shift only while the correspondences stay fixed; after
    re-matching, a random tilt points elsewhere. On a flat field it is all that N contains, and it
    would make X and Y look determined to centimetres.
    """
    u = 6 if opts["dof"] == "rigid" else 3
    if len(rows) == 0:
        return np.zeros((u, u))
    if len(rows) > TILT_ROWS:  # an even subset estimates the sum (the tilts are computed once per point)
        stride = -(-len(rows) // TILT_ROWS)
        total = P.sum()
        rows, P = rows[::stride], P[::stride]
        P = P * (total / max(P.sum(), 1e-300))
    C = opts["tilt"](corr.target_index[rows])  # (m, 3, 3) tilt covariance of each target normal
    if opts["dof"] == "rigid":
        p = corr.source_xyz[rows] - opts["origin"]
        G = np.concatenate([_skew(p) / opts["L"], np.broadcast_to(np.eye(3), (len(p), 3, 3))], axis=1)
        return np.einsum("m,mai,mij,mbj->ab", P, G, C, G)
    return np.einsum("m,mij->ij", P, C)


def _sandwich_precision(N, N_sig):
    """(N_sig^-1 N N_sig^-1)^-1 = N_sig N^-1 N_sig with N_sig's negative eigenvalues set to 0 (eq. 5.12b).

    Its eigenvalues give sigma0 / sqrt(lambda) = the standard deviation of the fixed point along each
    direction; a direction that holds no information beyond the tilt noise gets 0.
    """
    lam, V = np.linalg.eigh(0.5 * (N_sig + N_sig.T))
    S = (V * np.clip(lam, 0, None)) @ V.T
    Pi = S @ np.linalg.lstsq(N, S, rcond=None)[0]
    return 0.5 * (Pi + Pi.T)


def _solve(N, nvec, deg, N_sig=None):
    """Least-squares step, cofactor matrix and update; the datum is fixed when N is degenerate (eq. 5.12).

    The step solves N (the linearization for the current correspondences); the cofactor
    matrix is the sandwich N_sig^-1 N N_sig^-1 with the information that survives re-matching
    (eq. 5.12b) as bread: the fixed point of the iteration moves with N_sig, not with N. The
    update N_sig^-1 A^T P l is Newton's step on that fixed point: a step with N would move a weak
    direction only by N_sig / N of the way in each iteration (slow on gently sloped terrain).

    Parameters with a real share in an undetermined eigen-direction are held at
    their current value (their column is removed), the others are solved from the
    reduced normal equations. A minimum-norm step along the constrained
    eigen-directions alone would let the undetermined parameters drift: those
    eigenvectors carry small components of every parameter (noise in the normals).
    """
    N_sig = N if N_sig is None else N_sig
    if deg.well_posed and deg.parameter_determined.all():
        try:
            c = cho_factor(N)
        except np.linalg.LinAlgError:
            raise LabkitError(
                "the normal equations of ICP are singular although every direction looked determined; "
                "check the clouds for degenerate (identical or collinear) neighbourhoods"
            ) from None
        Si = np.linalg.inv(0.5 * (N_sig + N_sig.T))
        return cho_solve(c, nvec), Si @ N @ Si, Si @ nvec
    free = ~deg.parameter_determined  # a real share in an undetermined direction: held (the report names them)
    fixed = ~free
    dx = np.zeros(len(N))
    step = np.zeros(len(N))
    Q = np.full((len(N), len(N)), np.nan)
    if fixed.any():
        Nr = N[np.ix_(fixed, fixed)]
        lam, V = np.linalg.eigh(0.5 * (Nr + Nr.T))
        ok = lam >= 1e-12 * max(lam[-1], 1e-300)  # numerical guard
        V, lam = V[:, ok], lam[ok]
        dx[fixed] = V @ ((V.T @ nvec[fixed]) / lam)
        Sr = N_sig[np.ix_(fixed, fixed)]
        lam_s, V_s = np.linalg.eigh(0.5 * (Sr + Sr.T))
        ok = lam_s > 1e-12 * max(lam_s[-1], 1e-300)
        Si = (V_s[:, ok] / lam_s[ok]) @ V_s[:, ok].T
        Q[np.ix_(fixed, fixed)] = Si @ Nr @ Si
        step[fixed] = Si @ nvec[fixed]
    Q[free, free] = np.inf
    return dx, Q, step


def _held_rotation_covariance(N, deg, opts):
    """B Sigma_h B^T in the scaled parameters: what the held rotations' prior does to the others.

    Holding h at its prior value h0 makes the free parameters conditional on it: their
    solution moves by -B (h - h0) with B = N_ff^-1 N_fh (eq. 5.15), so a prior standard deviation
    sigma_h of the rotation adds B sigma_h^2 B^T to their covariance. The scaled rotation is L omega.
    A held translation does the same with a prior std of the matching distance (its true value may
    lie anywhere within reach): on sloped ground a held X moves Z by slope times X (eq. 5.15).
    """
    p = len(N)
    out = np.zeros((p, p))
    if deg.parameter_determined is None:
        return out
    free = deg.parameter_determined.copy()
    is_rot = np.array([n.startswith("r") for n in deg.names])
    held = ~free
    if not held.any() or not free.any():
        return out
    prior = np.where(is_rot, opts["held_rotation_std"] * opts["L"], opts["held_shift_std"])[held]
    B = np.linalg.lstsq(N[np.ix_(free, free)], N[np.ix_(free, held)], rcond=None)[0]
    out[np.ix_(free, free)] = (B * prior**2) @ B.T
    return out


def _non_negative(value, name):
    if not np.isfinite(value) or value < 0:
        raise LabkitError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


def _check_count(corr, opts):
    n = corr.n_accepted
    if n < max(opts["min_n"], 6):
        counts = ", ".join(f"{name}: {c}" for name, c in corr.rejected if c)
        raise EmptyRegionError(
            f"only {n} correspondences left after rejection (needed: {max(opts['min_n'], 6)}; "
            f"rejected - {counts or 'none'}); do the clouds overlap? Check the frames, give an "
            "initial transformation or relax max_distance / max_angle_deg"
        )


# ------------------------------------------------------------------ update and result


def _rodrigues(omega):
    """Rotation matrix exp([omega]x), re-orthonormalized by SVD."""
    theta = np.linalg.norm(omega)
    if theta < 1e-15:
        return np.eye(3)
    k = omega / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    E = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
    U, _, Vt = np.linalg.svd(E)
    return U @ Vt


def _update(R, t, dx, dof, L):
    """Apply the step: R <- E R, t <- E t + dt with E = exp([omega]x) (eq. 5.3)."""
    dt = dx[-3:]
    if dof == "translation":
        return R, t + dt, float(np.linalg.norm(dt))
    omega = dx[:3]
    E = _rodrigues(omega)
    R_new = E @ R
    U, _, Vt = np.linalg.svd(R_new)  # keep R orthonormal over many iterations
    return U @ Vt, E @ t + dt, float(np.linalg.norm(dt) + L * np.linalg.norm(omega))


def _record(it, R, t, adj, step):
    return IterationRecord(
        it, t.copy(), adj.rms, adj.corr.n_accepted, step,
        np.degrees(angles_from_rotation(R)), adj.scale, adj.n_deleted,
    )  # fmt: skip


def _result(R, t, origin, adj, history, converged, matcher, opts, runtime):
    deg = adj.degeneracy
    cov = adj.sigma0**2 * adj.Qxx  # (eq. 5.11)
    block = None if adj.block_cov is None else adj.block_cov()
    if block is not None and np.isfinite(np.diag(block)).any():
        cov = block  # (eq. 5.13)
    cov = cov + adj.held_cov  # prior of held rotations (eq. 5.15); inf stays inf
    undetermined = deg.undetermined_axes
    msg = "converged" if converged else f"not converged after {len(history)} iterations (last step {history[-1].step:.2e} m)"
    if undetermined:
        msg += (
            f"; UNDETERMINED: {', '.join(undetermined)} - the data do not constrain these components, "
            "they are held (at their initial value, or where the iteration was when a held shift's prior "
            "left them too imprecise) and their standard deviation is inf"
        )
    rotations = [n for n in deg.undetermined_parameters if n.startswith("r")]
    if rotations:
        msg += (
            f"; rotations {', '.join(rotations)} undetermined (held at their initial value, see the degeneracy "
            "report): the other parameters are conditional on that value"
            + (
                f", their covariance includes a prior std of {np.degrees(opts['held_rotation_std']):g} deg for it"
                if opts["held_rotation_std"] > 0
                else " and so is their covariance (held_rotation_std_deg=0)"
            )
        )
    elif not deg.well_posed:
        msg += "; some directions are weak (see the degeneracy report)"
    if opts["metric"] == "point_to_point" and (undetermined or not converged):
        msg += (
            "; point_to_point: the offsets between the two samplings along the surface carry no "
            "information about the shift (only the components along the normals do), consider "
            "metric='point_to_plane'"
        )
    test = None if opts["alpha"] is None else _consistency(adj, matcher, opts)
    if test is not None and not test.agree:  # the groups' spread enters the stated precision (eq. 5.17)
        free = deg.parameter_determined
        S = np.where([n.startswith("r") for n in NAMES[opts["dof"]]], opts["L"], 1.0)[free]
        before = _translation_std(cov, opts)
        cov = cov.copy()
        cov[np.ix_(free, free)] += test.between / np.outer(S, S)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(np.isfinite(before), _translation_std(cov, opts) / before, 1.0)
        test = replace(test, std_ratio=ratio)
        msg += "; " + _disagreement(test, matcher.options["classes"])
    n_used = adj.corr.n_accepted
    if len(adj.corr) < adj.corr.n_source:  # the shift from a sample of the source (sample=)
        msg += (f"; pairs from a sample of {len(adj.corr):,} of {adj.corr.n_source:,} source points "
                f"(sample={opts['sample']!r}), {n_used:,} used")
    return RegistrationResult(
        translation=t.copy(), rotation=R.copy(), origin=origin, covariance=cov,
        parameter_names=NAMES[opts["dof"]], sigma0=adj.sigma0, n_used=n_used,
        share_used=n_used / max(len(adj.corr), 1), converged=converged, iterations=len(history),
        degeneracy=deg, method=f"icp ({opts['dof']}, {opts['metric']}, robust={opts['robust']}, surface={matcher.options.get('surface', 'plane')})",
        history=tuple(history), runtime_s=runtime, message=msg, correspondences=adj.corr,
        consistency=test,
    )  # fmt: skip


def _consistency(adj, matcher, opts):
    """Model test of the final correspondences: one transformation for every group? (eq. 5.16)"""
    corr = adj.corr
    ok = corr.accepted
    A, l, P = _design(corr, None, None, opts)
    free = adj.degeneracy.parameter_determined
    A = A[:, :, free]  # held parameters stay out of the test
    xy = corr.source_xyz[ok, :2] - opts["origin"][:2]
    cells = np.floor(xy / opts["block_size"]).astype(np.int64)
    _, cells = np.unique(cells, axis=0, return_inverse=True)
    if matcher.target_class is not None and matcher.source_class is not None:
        # a correspondence belongs to the first group that either of its points belongs to: a
        # source point on regrowth matched to old ground counts as vegetation
        rows = np.flatnonzero(ok)
        cls_t = matcher.target_class[corr.target_index[ok]]
        cls_s = matcher.source_class[rows]
        labels = np.full(len(rows), len(CLASS_GROUPS))
        for g, (_, codes) in reversed(list(enumerate(CLASS_GROUPS))):
            labels[np.isin(cls_t, codes) | np.isin(cls_s, codes)] = g
        names, grouping = [n for n, _ in CLASS_GROUPS] + ["other"], "class"
    elif np.ptp(sigma := matcher.source_sigma[np.flatnonzero(ok)]) > 0:
        # no classes: terciles of the source point's a priori sigma (local noise): vegetation is rough
        labels = np.searchsorted(np.quantile(sigma, [1 / 3, 2 / 3]), sigma, side="right")
        names, grouping = ["smooth third", "middle third", "rough third"], "local noise"
    else:
        above = (xy > np.median(xy, axis=0)).astype(int)
        labels = above[:, 0] + 2 * above[:, 1]
        names, grouping = ["block SW", "block SE", "block NW", "block NE"], "block"
    names_free = [n for n, f in zip(NAMES[opts["dof"]], free) if f]
    translation = [names_free.index(n) for n in ("tx", "ty", "tz") if n in names_free]
    test = group_consistency(
        A, l, P, labels, names, cells.ravel(), translation=translation, rel_threshold=opts["rel"],
        alpha=opts["alpha"], grouping=grouping,
    )  # fmt: skip
    if test is not None and len(translation) < 3:  # report offsets on all three axes (NaN where held)
        full = np.full((len(test.groups), 3), np.nan)
        axes = [k for k, n in enumerate(("tx", "ty", "tz")) if n in names_free]
        off, std = full.copy(), full.copy()
        off[:, axes], std[:, axes] = test.offset, test.offset_std
        test = replace(test, offset=off, offset_std=std)
    return test


def _translation_std(cov, opts):
    idx = [NAMES[opts["dof"]].index(n) for n in ("tx", "ty", "tz")]
    return np.sqrt(np.clip(np.diag(cov)[idx], 0, None))


def _disagreement(test, classes):
    """Warning text when the groups disagree."""
    g = int(np.argmax(test.contribution))
    off = [f"d{a} {1000 * o:+.0f} mm" for a, o in zip("XYZ", test.offset[g]) if np.isfinite(o)]
    if test.consistent:
        return (
            f"the {test.grouping} groups differ ('{test.worst}': {', '.join(off) or 'see the report'} from the "
            f"result, p = {test.p_value:.1g}), but the shift hardly depends on it (std widened by at most "
            f"{np.nanmax(test.std_ratio):.2f})"
        )
    text = (
        f"INCONSISTENT: the {test.grouping} groups disagree (T = {test.statistic:.0f}, dof = {test.dof}, "
        f"p = {test.p_value:.1g}); '{test.worst}' differs most ({', '.join(off) or 'see the report'} from the "
        f"result): changes between the epochs suspected, the covariance includes the spread between "
        "the groups"
    )
    if test.grouping == "class" and classes is None:
        return text + f"; consider classes={STABLE} (ground, buildings, roads)"
    return text + "; consider robust='tukey', classes= of stable surfaces, or leaving out the changed area"

