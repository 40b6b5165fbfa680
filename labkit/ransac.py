"""RANSAC detection of a sphere in a cluttered point cloud (notebook 02).

The seed's section 2: draw minimal samples of s = 4 points that are not
coplanar, compute the sphere through each, count the points whose orthogonal
distance satisfies d_i^2 < t^2 (eqs. 25-26), stop after the adaptive number
of samples N of eq. (27), and refit the best sphere in the Gauss-Helmert model
on all its inliers. Added for real scans: a radius range or nominal radius,
MSAC scoring, local optimization (LO-RANSAC), preliminary scoring on a random
reduction of the cloud, local sampling for tiny spheres in large scenes, and a
final data-snooping pass with Baarda's w-test.

Added for ring-structured (multi-beam) and cluttered real scans: every
hypothesis that would become the best is verified on the full cloud
(:class:`_Verifier`: free space inside the sphere, shell contrast, plane pieces,
cap spread, and from the scanner station: facing side, scan lines, points
behind the sphere); a rejected one is skipped and the search continues. The
final inliers come from a robust band k sigma_hat around the refit, not from
the search threshold t, so the stated precision holds for any t.

Hypotheses are generated and scored in vectorized batches; the batch is then
replayed in sample order, so the bookkeeping (new bests, N after each new best,
the stopping sample) is exactly that of the one-sample-at-a-time loop.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq
from scipy.spatial import cKDTree
from scipy.special import ndtr

from ._checks import as_points, choice, positive, probability
from ._frame import local_origin, reduce
from ._report import ReportMixin, fmt
from .errors import LabkitError
from .sphere import algebraic_sphere, circumspheres, sphere_residuals

S = 4  # minimal sample size of a sphere
_FIRST_BATCH = 128
_MIN_BATCH = 64
_CELLS_PER_BATCH = 4_000_000  # hypotheses x points scored at once (about 32 MB)
_LO_STEPS = 4
_SNOOP_ROUNDS = 10
_PLANE_RATIO = 3.0  # a sphere must fit its inliers clearly better than a plane
_BAND_K = 3.0  # final inliers: |d| < k sigma_hat (robust scale), whatever the search threshold t
_INTERIOR_SHARE = 0.1  # points clearly inside a solid sphere, per inlier (true spheres: ~0)
_SHADOW_SHARE = 0.1  # points behind the sphere seen from the station, per inlier (true spheres: ~0)
_BACKFACE_SHARE = 0.2  # inliers on the side turned away from the station (true spheres: ~0)
_CONTRAST = 5.0  # inliers on the shell per point in the shell just outside it, t..3t (true spheres: > 14,
# spheres fitted to a cylinder or to pieces of planes: 2-3)
_TWO_PLANES_SHARE = 0.9  # inliers on one or two planes: plane pieces cut by the sphere
_MIN_LEVELS = 3  # a cap spans at least three scan lines (elevation levels) seen from the station
_MIN_SPREAD = 0.01  # smallest variance of the inliers' normals across the cap (units of 1; a ring: ~0)
_LOCAL_REACH = 1.0  # local sampling: the other three points lie within LOCAL_REACH r_max + t of the first
_LOCAL_MAX_SHARE = 0.25  # 'auto' samples locally only where a neighbourhood holds less of the working set
_LOCAL_MAX_PAIRS = 8_000_000  # ... and the neighbour pairs stay affordable
_FINAL_ATTEMPTS = 3  # searches per working set when the final refit of the best fails its checks
_VERIFY_PER_BATCH = 16  # candidates verified per batch at most (the best-scoring ones)
_VERIFY_MAX = 400  # candidates verified per search at most


def required_iterations(outlier_ratio, p=0.99, s=S):
    """Number of samples N for success probability ``p`` (eq. 27), rounded up.

    ``N = log(1 - p) / log(1 - (1 - eps)^s)``.

    Parameters
    ----------
    outlier_ratio : float or array_like
        eps = n_outliers / n, in [0, 1].
    p : float
        Probability that at least one sample is free of outliers, in (0, 1).
    s : int
        Sample size (4 for a sphere).

    Returns
    -------
    int or float or ndarray
        An int for a scalar ratio (``math.inf`` when eps = 1); a float array
        for array input.
    """
    eps = np.asarray(outlier_ratio, dtype=np.float64)
    if not np.all((eps >= 0) & (eps <= 1)):
        raise LabkitError(f"outlier_ratio must lie in [0, 1], got {outlier_ratio!r}")
    p = probability(p, "p")
    if isinstance(s, bool) or int(s) != s or s < 1:
        raise LabkitError(f"s must be a whole number >= 1, got {s!r}")
    w_s = (1.0 - eps) ** int(s)  # probability that one sample is outlier-free
    with np.errstate(divide="ignore", invalid="ignore"):
        N = np.log1p(-p) / np.log1p(-w_s)  # (eq. 27)
    N = np.where(w_s <= 0, np.inf, np.where(w_s >= 1, 1.0, np.ceil(N * (1 - 1e-12))))
    N = np.maximum(N, 1.0)
    if N.ndim == 0:
        return math.inf if np.isinf(N) else int(N)
    return N


def _required_from_probability(w, p):
    """N of eq. (27) written with the outlier-free sample probability w directly."""
    if w <= 0:
        return math.inf
    if w >= 1:
        return 1
    return max(1, int(np.ceil(np.log1p(-p) / np.log1p(-w) * (1 - 1e-12))))


@dataclass(frozen=True, eq=False, repr=False)
class RansacResult(ReportMixin):
    """Outcome of :func:`ransac_sphere`.

    Attributes
    ----------
    fit : SphereFit or None
        Gauss-Helmert adjustment on the final inliers (None when not found).
    inliers : ndarray of bool (n,)
        Final inliers over the input points (all False when not found).
    found : bool
    iterations : int
        Valid samples drawn (degenerate samples do not count).
    n_required_history : ndarray (k, 2)
        [iteration, required N] after each new best hypothesis (eq. 27).
    outlier_ratio : float
        Estimated share of outliers, 1 - n_inliers / n (NaN when not found).
    seed : int
        Seed that reproduces the run: ``ransac_sphere(..., rng=result.seed)``.
    reason : str
        Why the search stopped and, when not found, why.
    n_invalid : int
        Degenerate (coplanar or duplicate) samples drawn and not counted.
    n_snooped : int
        Points removed by the final data snooping.
    sigma : float or None
        A priori standard deviation used for the w-test (given or estimated).
    sampling, scoring, minimal_solver : str
        The strategies used.
    threshold, p : float
        The inlier threshold t (m) and success probability.
    n_required : float
        The required N at the end of the search.
    n_working : int
        Size of the working set the (last) search drew and scored on.
    n_rejected : int
        Candidate spheres the verification rejected during the search (each
        would have been the best by its score): pieces of planes, corners,
        round furniture, rings.
    band : float
        Half-width of the final inlier band, k sigma_hat (m): set by the
        robust scale of the residuals, not by the threshold t.
    station : ndarray (3,) or None
        Scanner position used by the visibility checks (None: not used).
    """

    fit: object
    inliers: np.ndarray
    found: bool
    iterations: int
    n_required_history: np.ndarray
    outlier_ratio: float
    seed: int
    reason: str
    n_invalid: int = 0
    n_snooped: int = 0
    sigma: float | None = None
    sampling: str = "uniform"
    scoring: str = "ransac"
    minimal_solver: str = "closed_form"
    threshold: float = float("nan")
    p: float = float("nan")
    n_required: float = float("inf")
    n_working: int = 0
    n_rejected: int = 0
    band: float = float("nan")
    station: np.ndarray | None = None

    @property
    def center(self):
        return None if self.fit is None else self.fit.x[:3]

    @property
    def radius(self):
        return None if self.fit is None else float(self.fit.x[3])

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def _report(self):
        rows = [("found", "yes" if self.found else "no"), ("reason", self.reason)]
        if self.found:
            std = np.sqrt(np.diag(self.fit.Sigma_xx))
            rows += [
                ("centre", fmt(self.fit.x[:3], 5, "m")),
                ("std centre", fmt(std[:3] * 1e3, 3, "mm")),
                ("radius", fmt(self.fit.x[3], 5, "m")),
                ("std radius", fmt(std[3] * 1e3, 3, "mm")),
                ("sigma0", fmt(self.fit.sigma0, 3)),
                ("inliers", f"{self.n_inliers} of {self.inliers.size}"),
                ("outlier ratio", fmt(self.outlier_ratio, 3)),
            ]
        search = [
            ("sampling / solver", f"{self.sampling} / {self.minimal_solver}"),
            ("scoring", self.scoring),
            ("threshold t (search)", fmt(self.threshold * 1e3, 2, "mm")),
            ("p", fmt(self.p, 4)),
            ("working set", f"{self.n_working} points"),
            ("valid samples", f"{self.iterations}"),
            ("required N (eq. 27)", f"{self.n_required:.0f}"),
            ("degenerate samples", f"{self.n_invalid}"),
            ("new bests", f"{len(self.n_required_history)}"),
            ("seed", f"{self.seed}"),
        ]
        checks = [
            ("final inlier band", fmt(self.band * 1e3, 2, "mm") + f" ({_BAND_K:g} x robust sigma)"),
            ("candidates rejected", f"{self.n_rejected} (not a sphere cap: verification)"),
            ("station", "not given (no visibility checks)" if self.station is None else fmt(self.station, 3, "m")),
            ("removed by data snooping", f"{self.n_snooped}"),
        ]
        if self.sigma is not None:
            checks.append(("sigma a priori (w-test)", fmt(self.sigma * 1e3, 3, "mm")))
        if self.found:
            checks.append(("global test passed", str(getattr(self.fit.global_test, "passed", self.fit.global_test))))
        return "RANSAC sphere detection", [("", rows), ("Search", search), ("Checks", checks)]


@dataclass(frozen=True)
class _Config:
    threshold: float
    p: float
    r_min: float
    r_max: float
    known: bool  # r_max given by the caller (radius range or nominal radius)
    scoring: str
    minimal_solver: str
    sampling: str
    max_iterations: int
    local_optimization: bool
    min_inliers: int
    snooping: bool
    sigma: object
    alpha: float
    hold_radius: float | None  # the nominal radius to hold in the refit, or None
    station: np.ndarray | None = None  # scanner position (input frame), or None


def ransac_sphere(
    points,
    threshold,
    p=0.99,
    rng=None,
    radius_range=None,
    *,
    nominal_radius=None,
    hold_radius=False,
    scoring="ransac",
    minimal_solver="closed_form",
    local_optimization=True,
    preliminary_size=1000,
    sampling="auto",
    max_iterations=100_000,
    min_inliers=10,
    snooping=True,
    sigma=None,
    alpha=0.001,
    station=None,
) -> RansacResult:
    """Detect a sphere with RANSAC and adjust it in the Gauss-Helmert model.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        The scan, n >= 4 (any frame; UTM coordinates are reduced internally).
    threshold : float
        Inlier threshold t in metres for the search: a point supports a
        hypothesis if d_i^2 < t^2 (eqs. 25-26). t decides which hypotheses win
        and how many samples are needed (eq. 27); it does NOT decide the final
        inliers or the statistics: those come from a band |d| < 3 sigma_hat
        around the refitted sphere, with sigma_hat a robust (truncation-
        consistent MAD) scale of the residuals, iterated to a fixed point (or
        3 sigma when ``sigma`` is given). So the stated standard deviations
        hold for any t between about 1 and 5 sigma. The seed sets t = sigma.
    p : float
        Probability that at least one outlier-free sample is drawn (eq. 27).
    rng : int or numpy.random.Generator, optional
        Seed or generator. The result records a seed that reproduces the run.
    radius_range : (r_min, r_max), optional
        Admissible radii (m). Hypotheses outside are rejected (they still count
        as samples); the radius is checked again after the refit. Default:
        ``nominal_radius`` +- 10 %, otherwise radii up to the extent of the
        cloud - and a sphere is then still only "found" when it passes the
        verification below (no points inside it, a surface rather than a
        volume of points), which walls, floors or random points do not.
        Without a range the search is slower (uniform sampling only) and
        larger round objects compete: give one.
    nominal_radius : float, optional
        Known radius of the target (m).
    hold_radius : bool
        Hold the radius at ``nominal_radius`` in the final adjustment.
    scoring : {'ransac', 'msac'}
        Count inliers, or MSAC: maximise sum over inliers of (t^2 - d_i^2).
    minimal_solver : {'closed_form', 'ghm'}
        Sphere through each sample: batched closed form (fast) or the seed's
        Gauss-Helmert adjustment of the 4 points (slow, for teaching).
    local_optimization : bool
        LO-RANSAC: refine each new best by least squares on its inliers.
    preliminary_size : int or None
        Hypotheses are drawn from and scored on a random reduction to this many
        points (the seed uses 1000); the final inliers come from the full cloud.
        None uses every point.
    sampling : {'auto', 'uniform', 'local'}
        'uniform': 4 random points. 'local': a random first point and three
        more from its neighbourhood of radius 2 r_max (needs a radius range or
        nominal radius); N is then computed with the local inlier shares.
        'auto': local when r_max is known, the cloud is > 10 r_max wide and a
        neighbourhood holds on average at most 10 % of the working set.
    max_iterations : int
        Upper bound on valid samples.
    min_inliers : int
        Fewer inliers in the full cloud means "not found".
    snooping : bool
        Remove points failing Baarda's w-test (level ``alpha``) and refit.
    sigma : float or array_like, optional
        A priori standard deviation of the coordinates for the adjustment and
        the w-test: a scalar, one per point (n,) or (n, 3, 3) covariances.
        Default: estimated robustly (1.4826 MAD of the inlier distances).
    alpha : float
        Significance level of the w-test (two-sided).
    station : array_like (3,), optional
        Scanner position in the frame of ``points`` (for a scanner-centred
        file: the origin). Enables the visibility checks: no inliers on the
        side of the sphere turned away from the station, no points behind the
        sphere (free-space violation), station outside the sphere. Default
        None: these checks are skipped (the others still run).

    Returns
    -------
    RansacResult
        ``found=False`` with a reason when no sphere is found; never a guess.

    Raises
    ------
    LabkitError
        Fewer than 4 points, NaN/inf, threshold <= 0, p outside (0, 1), an
        invalid radius range or option, sigma <= 0 or not finite.

    Notes
    -----
    Verification (a candidate must pass it to become the best hypothesis;
    otherwise the search goes on with the next best). Checks that hold on
    ring-structured multi-beam scans, where a k-neighbourhood is one or two
    scan lines and its PCA normal says little:

    - at least ``min_inliers`` points on the shell |d| < t in the full cloud;
    - no points clearly inside the (solid) sphere, and at least five times as
      many points on the shell as in the shell just outside it, t..3t (a
      spherical surface, not a cylinder, a volume or planes cut by it);
    - not nearly all inliers on one or two planes (a floor, a wall, an edge);
    - the inliers are not flat (plane rms >= 3 x sphere rms) and their model
      normals (p - c)/r spread in two directions over the cap (not a ring);
    - with ``station``: the station lies outside the sphere, the inliers face
      the station, and no points lie behind the sphere along the rays.
    """
    # Check the input, fix the seed
    xyz = as_points(points, min_points=S)
    t = positive(threshold, "threshold")
    p = probability(p, "p")
    alpha = probability(alpha, "alpha")
    seed, gen = _seed_and_generator(rng)
    scoring = choice(scoring, ("ransac", "msac"), "scoring")
    minimal_solver = choice(minimal_solver, ("closed_form", "ghm"), "minimal_solver")
    sampling = choice(sampling, ("auto", "uniform", "local"), "sampling")
    r_min, r_max, known = _radius_limits(radius_range, nominal_radius, hold_radius)
    max_iterations = _whole(max_iterations, "max_iterations", 1)
    min_inliers = _whole(min_inliers, "min_inliers", S + 1)
    sigma = _check_sigma(sigma, len(xyz))
    station = _check_station(station)

    cfg = _Config(t, p, r_min, r_max, known, scoring, minimal_solver, sampling, max_iterations,
                  bool(local_optimization), min_inliers, bool(snooping), sigma, alpha,
                  float(nominal_radius) if hold_radius else None, station)

    # Search a random reduction of the cloud; if nothing is found there, a 4x and a 16x larger one
    origin = local_origin(xyz)
    verifier = _Verifier(reduce(xyz, origin), None if station is None else station - origin, cfg)
    tried = []
    for size in _reduction_sizes(len(xyz), preliminary_size):
        result, had_best = _detect(xyz, origin, _working_set(len(xyz), size, gen), cfg, seed, gen, verifier)
        tried.append(size)
        if result.found or not had_best:
            break  # (without any hypothesis in range, a larger working set would not help)
    if len(tried) > 1:
        sizes = ", ".join(f"{k}" for k in tried)
        result = replace(result, reason=f"{result.reason} [searched reductions to {sizes} points]")
    return result


def _detect(xyz, origin, idx, cfg, seed, gen, verifier):
    """One detection: adaptive search on the working set xyz[idx], refit and checks on the full cloud.

    Returns the RansacResult and whether the search had a best hypothesis at all.
    """
    # The working set, reduced to the local origin, and its sampler
    W = reduce(xyz[idx], origin)
    extent = float(np.linalg.norm(np.ptp(W, axis=0)))
    if not cfg.known:  # no sphere larger than the scan (a cropped cap is as wide as about its radius)
        cfg = replace(cfg, r_max=max(extent, 1e-9))
    sampling = _pick_sampling(cfg.sampling, cfg.known, cfg.r_max, extent)
    if cfg.sampling == "auto" and sampling == "local":
        share = _mean_neighbourhood_share(W, _LOCAL_REACH * cfg.r_max + cfg.threshold)
        if share > _LOCAL_MAX_SHARE or share * len(W) ** 2 > _LOCAL_MAX_PAIRS:
            # the neighbourhoods hold much of the scene: local sampling gains little and costs O(m^2) pairs
            sampling = "uniform"
    sampler = _LocalSampler(W, _LOCAL_REACH * cfg.r_max + cfg.threshold) if sampling == "local" else _UniformSampler(len(W))

    # Adaptive search (eqs. 25-27) on the working set; a best whose final refit fails the checks is
    # rejected and the search runs again without it (at most _FINAL_ATTEMPTS times)
    shift = np.append(origin, 0.0)
    for attempt in range(_FINAL_ATTEMPTS):
        verifier.start(cfg)
        search = _search(W, sampler, cfg, gen, verifier)
        common = dict(
            iterations=search.iterations, n_required_history=search.history, seed=seed, n_invalid=search.n_invalid,
            sampling=sampling, scoring=cfg.scoring, minimal_solver=cfg.minimal_solver, threshold=cfg.threshold,
            p=cfg.p, n_required=float(search.N), n_working=len(W), n_rejected=verifier.n_rejected,
            station=cfg.station,
        )
        if search.x is None:
            reason = search.reason
            if verifier.n_rejected:
                reason = (f"{reason}; {verifier.n_rejected} candidate(s) rejected by the verification, "
                          f"the best-scoring because {verifier.best_rejection}")
            return _not_found(len(xyz), reason, **common), verifier.n_rejected > 0 or search.had_range

        # Final inliers from the full cloud (robust band), Gauss-Helmert refit, data snooping, checks
        final = _refit(xyz, search.x + shift, cfg)
        reason = final.reason
        if not reason:
            reason = verifier.final_check(final.fit.x - shift, final.band)
        if not reason:
            return RansacResult(
                fit=final.fit, inliers=final.inliers, found=True, outlier_ratio=1.0 - final.inliers.mean(),
                reason=search.reason, n_snooped=final.n_snooped, sigma=final.sigma, band=final.band, **common,
            ), True
        verifier.reject(search.x, None if final.fit is None else final.fit.x - shift)
    return _not_found(len(xyz), f"{reason} (the final refit of the best failed in {_FINAL_ATTEMPTS} searches)",
                      n_snooped=final.n_snooped, sigma=final.sigma, band=final.band, **common), True


def _reduction_sizes(n, preliminary_size):
    """Working-set sizes to try: the preliminary size, then 4x and 16x (capped at n)."""
    if preliminary_size is None:
        return [n]
    size = _whole(preliminary_size, "preliminary_size", S)
    sizes = []
    for k in (size, 4 * size, 16 * size):
        if not sizes or sizes[-1] < min(k, n):
            sizes.append(min(k, n))
    return sizes


# ----------------------------------------------------------------- arguments
def _seed_and_generator(rng):
    """A reproducible int seed and the generator built from it."""
    if isinstance(rng, np.random.Generator):
        seed = int(rng.integers(0, 2**63 - 1))
    elif rng is None:
        seed = int(np.random.SeedSequence().entropy)
    elif isinstance(rng, numbers.Integral) and not isinstance(rng, bool) and rng >= 0:
        seed = int(rng)
    else:
        raise LabkitError(f"rng must be a non-negative int, a numpy.random.Generator or None, got {rng!r}")
    return seed, np.random.default_rng(seed)


def _whole(value, name, minimum):
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or int(value) != value or value < minimum:
        raise LabkitError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def _radius_limits(radius_range, nominal_radius, hold_radius):
    """(r_min, r_max, known): the admissible radii; known=False means no limit was given."""
    r0 = None if nominal_radius is None else positive(nominal_radius, "nominal_radius")
    if hold_radius and r0 is None:
        raise LabkitError("hold_radius=True needs nominal_radius")
    if radius_range is None:
        if r0 is None:
            return 0.0, math.inf, False
        return 0.9 * r0, 1.1 * r0, True
    try:
        r_min, r_max = (float(v) for v in radius_range)
    except (TypeError, ValueError):
        raise LabkitError(f"radius_range must be a pair (r_min, r_max) in metres, got {radius_range!r}") from None
    if not (np.isfinite(r_min) and np.isfinite(r_max) and 0 <= r_min < r_max):
        raise LabkitError(f"radius_range must satisfy 0 <= r_min < r_max (finite), got {radius_range!r}")
    if r0 is not None and not r_min <= r0 <= r_max:
        raise LabkitError(f"nominal_radius {r0} lies outside radius_range {radius_range!r}")
    return r_min, r_max, True


def _check_sigma(sigma, n):
    """The a priori sigma: None, a finite scalar > 0, (n,) > 0 or (n, 3, 3); checked before any search."""
    if sigma is None or np.ndim(sigma) == 0:
        return None if sigma is None else positive(sigma, "sigma")
    try:
        arr = np.asarray(sigma, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"sigma must be numeric, got {type(sigma).__name__}") from None
    if arr.shape not in ((n,), (n, 3, 3)):
        raise LabkitError(f"sigma must be a scalar, shape ({n},) or ({n}, 3, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise LabkitError("sigma contains NaN or infinite values")
    if arr.ndim == 1 and (arr <= 0).any():
        raise LabkitError("sigma (standard deviations) must be > 0 for every point")
    return arr


def _check_station(station):
    if station is None:
        return None
    try:
        s = np.asarray(station, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"station must be 3 numbers (x, y, z) in metres, got {station!r}") from None
    if s.shape != (3,) or not np.isfinite(s).all():
        raise LabkitError(f"station must be 3 finite numbers (x, y, z) in metres, got {station!r}")
    return s


def _working_set(n, size, gen):
    """Indices of the random reduction used for sampling and scoring (the seed: 1000 points)."""
    return np.arange(n) if size >= n else np.sort(gen.choice(n, size=size, replace=False))


def _pick_sampling(sampling, known, r_max, extent):
    if sampling == "local" and not known:
        raise LabkitError("sampling='local' needs radius_range or nominal_radius (the neighbourhood is 2 r_max)")
    if sampling == "auto":
        return "local" if known and extent > 10.0 * r_max else "uniform"
    return sampling


def _mean_neighbourhood_share(W, radius):
    """Mean share of the working set within ``radius`` of a point (counted in C, no lists)."""
    counts = cKDTree(W).query_ball_point(W, radius, return_length=True)
    return float(counts.mean()) / len(W)


# ----------------------------------------------------------------- sampling
class _UniformSampler:
    """Four points drawn uniformly; N follows eq. (27) with eps = 1 - k/m."""

    def __init__(self, m):
        self.m = m

    def draw(self, gen, size):
        # rows with a repeated index are degenerate and do not count
        return gen.integers(0, self.m, size=(size, S))

    def required(self, inlier_mask, p):
        return required_iterations(1.0 - inlier_mask.sum() / self.m, p)


class _LocalSampler:
    """A uniform first point and three distinct points within ``radius`` of it.

    The probability that a sample is outlier-free becomes
    ``w = (1/m') sum_{i in I} C(k_i, 3) / C(d_i, 3)``: the first point must be an
    inlier and the other three inliers of its neighbourhood, where d_i is the
    neighbourhood size (without i), k_i the inliers in it and m' the number of
    points with d_i >= 3 (the only admissible first points). N then follows
    eq. (27) with (1 - eps)^4 replaced by w.
    """

    def __init__(self, W, radius):
        # all pairs closer than radius as one integer array (no per-point Python lists), both directions,
        # grouped by their first point: the neighbours of i are flat[offsets[i]:offsets[i + 1]]
        pairs = cKDTree(W).query_pairs(radius, output_type="ndarray").astype(np.int64)
        owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
        other = np.concatenate([pairs[:, 1], pairs[:, 0]])
        key = owner.astype(np.int16) if len(W) < 2**15 else owner  # 16-bit keys: numpy's stable sort is a radix sort
        order = np.argsort(key, kind="stable")
        self.flat = other[order]
        self.deg = np.bincount(owner, minlength=len(W))
        self.offsets = np.concatenate([[0], np.cumsum(self.deg)])
        self.first = np.flatnonzero(self.deg >= 3)
        self._W, self.radius, self._blocks = W, radius, None

    @property
    def blocks(self):
        if self._blocks is None:
            self._blocks = _Blocks(self._W, self.radius)
        return self._blocks

    def draw(self, gen, size):
        if self.first.size == 0:
            return np.zeros((size, S), dtype=np.int64)  # all duplicates: degenerate
        i = self.first[gen.integers(0, self.first.size, size)]
        d = self.deg[i]
        u = gen.random((size, 3))
        a = (u[:, 0] * d).astype(np.int64)  # three distinct positions in 0..d-1
        b = (u[:, 1] * (d - 1)).astype(np.int64)
        c = (u[:, 2] * (d - 2)).astype(np.int64)
        b += b >= a
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        c += c >= lo
        c += c >= hi
        base = self.offsets[i]
        return np.column_stack([i, self.flat[base + a], self.flat[base + b], self.flat[base + c]])

    def required(self, inlier_mask, p):
        cum = np.concatenate([[0], np.cumsum(inlier_mask[self.flat])])
        k = (cum[self.offsets[1:]] - cum[self.offsets[:-1]]).astype(np.float64)
        d = self.deg.astype(np.float64)
        ok = inlier_mask & (self.deg >= 3)
        share = k[ok] * (k[ok] - 1) * (k[ok] - 2) / (d[ok] * (d[ok] - 1) * (d[ok] - 2))
        w = share.sum() / max(self.first.size, 1)
        return _required_from_probability(w, p)


class _Blocks:
    """Grid of the working set for scoring local hypotheses on the points that can be their inliers.

    A local hypothesis passes through its first point f and three points within
    rho = LOCAL_REACH r_max + t of f; for r <= r_max every point with |d| < t
    lies within 2 (r_max + t) of f. With grid cells of that size, those points
    are in the 3 x 3 x 3 cells around f's cell: scoring there gives exactly the
    scores over the whole working set, at a fraction of the cost.
    """

    def __init__(self, W, radius):
        self.W = W
        self.size = 2.0 * radius + 1e-9  # >= 2 (r_max + t) as LOCAL_REACH <= 1
        cells = np.floor(W / self.size).astype(np.int64)
        self.cells = cells
        keys, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.ravel()
        order = np.argsort(inv, kind="stable")
        bounds = np.searchsorted(inv[order], np.arange(len(keys) + 1))
        self._members = {tuple(k): order[bounds[j]:bounds[j + 1]] for j, k in enumerate(keys)}
        self._block_cache = {}
        self._offsets = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])

    def _block(self, cell):
        key = tuple(cell)
        if key not in self._block_cache:
            parts = [self._members.get(tuple(c)) for c in cell + self._offsets]
            self._block_cache[key] = np.concatenate([q for q in parts if q is not None])
        return self._block_cache[key]

    def score(self, W, Wsq, X, first, cfg):
        """Scores of hypotheses X (B, 4) with first points ``first`` (B,), equal to _score on all of W."""
        scores = np.empty(len(X))
        cell_ids, inv = np.unique(self.cells[first], axis=0, return_inverse=True)
        inv = inv.ravel()
        for j, cell in enumerate(cell_ids):  # a loop over grid cells, not over points
            sel = np.flatnonzero(inv == j)
            pts = self._block(cell)
            scores[sel] = _score(W[pts], Wsq[pts], X[sel], cfg.threshold, cfg.scoring)[0]
        return scores


# ----------------------------------------------------------------- hypotheses and scores
def _hypotheses(samples, solver):
    """Spheres [xc, yc, zc, r] (B, 4) through samples (B, 4, 3) and a validity mask."""
    if solver == "closed_form":
        centers, radii, valid = circumspheres(samples)
        return np.column_stack([centers, radii]), valid
    return _ghm_hypotheses(samples)


def _ghm_hypotheses(samples):
    """The seed's way: a Gauss-Helmert adjustment of each 4-point sample (a Python loop)."""
    from .adjustment import gauss_helmert_model

    X = np.full((len(samples), 4), np.nan)
    valid = np.zeros(len(samples), dtype=bool)
    for j, sample in enumerate(samples):
        try:
            fit = gauss_helmert_model(sample)
        except LabkitError:  # singular N (the seed's det test), coplanar or duplicate points
            continue
        if fit.converged and np.all(np.isfinite(fit.x)):
            X[j], valid[j] = fit.x, True
    return X, valid


def _squared_center_distances(W, Wsq, C):
    """|w_i - c_b|^2 for all points and hypotheses, (m, B), via one matrix product."""
    return Wsq[:, None] - 2.0 * (W @ C.T) + np.einsum("ij,ij->i", C, C)[None, :]


def _score(W, Wsq, X, t, scoring):
    """Score (higher is better) and inlier count of each hypothesis X (B, 4) on W (eqs. 25-26)."""
    D2 = _squared_center_distances(W, Wsq, X[:, :3])
    r = X[:, 3]
    if scoring == "ransac":
        # d_i^2 < t^2  <=>  (r - t)^2 < |w_i - c|^2 < (r + t)^2   (eq. 26)
        inside = (D2 > np.maximum(r - t, 0.0) ** 2) & (D2 < (r + t) ** 2)
        count = inside.sum(axis=0)
        return count.astype(np.float64), count
    d2 = (np.sqrt(np.maximum(D2, 0.0)) - r) ** 2  # (eq. 25)
    gain = np.maximum(t * t - d2, 0.0)  # MSAC: t^2 - min(d_i^2, t^2)
    return gain.sum(axis=0), (gain > 0).sum(axis=0)


def _inlier_mask(W, x, t):
    diff = W - x[:3]
    d = np.sqrt(np.einsum("ij,ij->i", diff, diff)) - x[3]  # (eq. 25)
    return d * d < t * t  # (eq. 26)


def _local_optimization(W, Wsq, x, score, cfg):
    """LO-RANSAC: iterate (inliers -> orthogonal least-squares sphere) while the score improves."""
    improved = False
    for _ in range(_LO_STEPS):
        mask = _inlier_mask(W, x, cfg.threshold)
        if mask.sum() <= S:
            break
        x_new = _orthogonal_fit(W[mask], x)
        if x_new is None or not cfg.r_min <= x_new[3] <= cfg.r_max:
            break
        s_new, _ = _score(W, Wsq, x_new[None, :], cfg.threshold, cfg.scoring)
        if s_new[0] <= score:
            break
        x, score, improved = x_new, s_new[0], True
    return x, score, improved


def _orthogonal_fit(P, x, steps=3):
    """A few Gauss-Newton steps of the orthogonal-distance sphere fit, from x; None if it fails."""
    try:
        x = algebraic_sphere(P) if x is None else np.array(x, dtype=np.float64)
    except LabkitError:
        return None
    P = P - x[:3]  # work relative to the current centre (UTM-safe)
    shift, x = x[:3].copy(), np.array([0.0, 0.0, 0.0, x[3]])
    n = len(P)
    for _ in range(steps):
        diff = P - x[:3]
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        if np.any(dist == 0):
            return None
        # Jacobian rows J_i = -[u_i, 1] (u_i the unit radial vector); J^T J and J^T d
        # in blocks, without forming the n x 4 matrix J
        u = diff / dist[:, None]
        d = dist - x[3]
        su = u.sum(axis=0)
        JtJ = np.empty((4, 4))
        JtJ[:3, :3], JtJ[:3, 3], JtJ[3, :3], JtJ[3, 3] = u.T @ u, su, su, n
        Jtd = -np.append(u.T @ d, d.sum())
        eig = np.linalg.eigvalsh(JtJ)
        if eig[0] <= 1e-12 * eig[-1]:
            return None
        x = x + np.linalg.solve(JtJ, -Jtd)
    x[:3] += shift
    return x if np.all(np.isfinite(x)) and x[3] > 0 else None


# ----------------------------------------------------------------- adaptive search
@dataclass(frozen=True)
class _Search:
    x: np.ndarray | None
    iterations: int
    N: float
    history: np.ndarray
    n_invalid: int
    reason: str
    had_range: bool = False


def _search(W, sampler, cfg, gen, verifier=None):
    """The adaptive RANSAC loop on the working set W, in replayed vectorized batches."""
    Wsq = np.einsum("ij,ij->i", W, W)
    best = _Best(x=None, score=-np.inf)
    n_valid = n_drawn = n_invalid = 0
    N = math.inf  # the seed starts with N = infinity
    history: list[tuple[int, float]] = []
    cap = max(_MIN_BATCH, _CELLS_PER_BATCH // len(W))
    batch = min(_FIRST_BATCH, cap) if cfg.minimal_solver == "closed_form" else _MIN_BATCH
    had_range = False
    while n_valid < min(N, cfg.max_iterations):
        if n_drawn >= 10 * cfg.max_iterations or (n_drawn >= 2000 and n_valid == 0):
            break
        if best.x is None and verifier is not None and verifier.exhausted:
            break  # every candidate so far failed the verification and its budget is spent
        # Draw and solve a batch; degenerate samples do not count
        idx = sampler.draw(gen, batch)
        X, valid = _hypotheses(W[idx], cfg.minimal_solver)
        position = np.flatnonzero(valid)[: cfg.max_iterations - n_valid]  # batch position of each valid sample
        X = X[position]

        # Score hypotheses inside the radius range (the others count but cannot win)
        scores = np.full(len(X), -np.inf)
        ok = (X[:, 3] >= cfg.r_min) & (X[:, 3] <= cfg.r_max)
        if ok.any():
            if isinstance(sampler, _LocalSampler):  # inliers lie near the first point: score its block only
                scores[ok] = sampler.blocks.score(W, Wsq, X[ok], idx[position[ok], 0], cfg)
            else:
                scores[ok] = _score(W, Wsq, X[ok], cfg.threshold, cfg.scoring)[0]
            had_range = True

        # Replay in sample order: new bests (verified, with LO), N after each (eq. 27), stop at N
        keep, stopped, best, N, events = _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg, verifier)
        history += [(n_valid + j + 1, N_j) for j, N_j in events]
        drawn = int(position[keep - 1]) + 1 if stopped else batch  # samples the sequential loop drew
        n_drawn += drawn
        n_invalid += drawn - keep
        n_valid += keep
        batch = _next_batch(N, cfg, n_valid, n_drawn, cap)
    return _Search(
        x=best.x, iterations=n_valid, N=N, n_invalid=n_invalid,
        history=np.array(history, dtype=np.float64).reshape(-1, 2),
        reason=_search_reason(best.x, n_valid, n_drawn, N, cfg, had_range), had_range=had_range,
    )


@dataclass(frozen=True)
class _Best:
    x: np.ndarray | None
    score: float


def _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg, verifier=None):
    """Sequential bookkeeping of one batch, exactly as the one-sample-at-a-time loop.

    Walks through the samples that beat the running best in order; each must
    pass the verification to become the new best (a rejected one is skipped,
    the search goes on with the next); each new best is refined by LO (if
    enabled) and sets the required N. Returns the number of valid samples the
    loop used, whether it stopped inside the batch, the best hypothesis, the
    current N and the (position, N) events.
    """
    candidates = np.flatnonzero((scores > best.score) & np.isfinite(scores))
    if verifier is not None and len(candidates):
        # known failures cost no check (looked up for the best-scoring few only)
        top = candidates[np.argsort(-scores[candidates], kind="stable")[: 4 * _VERIFY_PER_BATCH]]
        candidates = np.sort(top[~verifier.near_rejected(X[top])])
    if verifier is not None and len(candidates) > _VERIFY_PER_BATCH:
        # too many to verify: the running maxima (the new bests of the plain loop) and the
        # best-scoring others, still walked in sample order
        prefix = np.flatnonzero(scores > np.maximum.accumulate(np.concatenate([[best.score], scores]))[:-1])
        top = candidates[np.argsort(-scores[candidates], kind="stable")[:_VERIFY_PER_BATCH]]
        candidates = np.union1d(prefix, top)
    events = []
    it = n_valid + np.arange(1, len(X) + 1)  # iteration number of each valid sample
    for j in candidates:
        if it[j] > N:
            break  # the loop stopped at sample N, before sample j
        if scores[j] <= best.score:
            continue  # beaten by an earlier (or LO-refined) best meanwhile
        if verifier is not None and not verifier.accepts(X[j], scores[j]):
            continue  # not a sphere cap: the next best may be
        best = _Best(X[j], scores[j])
        N = sampler.required(_inlier_mask(W, best.x, cfg.threshold), cfg.p)  # (eq. 27)
        events.append((int(j), N))
        if cfg.local_optimization:
            x, score, improved = _local_optimization(W, Wsq, best.x, best.score, cfg)
            if improved:
                best = _Best(x, score)
                N = min(N, sampler.required(_inlier_mask(W, x, cfg.threshold), cfg.p))
                events.append((int(j), N))
    keep = int(min(len(X), max(N - n_valid, 0))) if np.isfinite(N) else len(X)
    if events:  # a new best at sample j is always used, even if its N is already exceeded
        keep = max(keep, events[-1][0] + 1)
    stopped = keep < len(X) or (keep > 0 and n_valid + keep >= min(N, cfg.max_iterations))
    return keep, stopped, best, N, events


def _next_batch(N, cfg, n_valid, n_drawn, cap):
    """Enough samples to reach N at the observed validity rate, growing at most geometrically."""
    if cfg.minimal_solver == "ghm":
        return _MIN_BATCH
    remaining = min(N, cfg.max_iterations) - n_valid
    rate = max(n_valid / max(n_drawn, 1), 0.05)
    wanted = remaining / rate if np.isfinite(remaining) else math.inf
    return int(np.clip(min(wanted, max(n_valid, _FIRST_BATCH)), _MIN_BATCH, cap))


def _search_reason(x, n_valid, n_drawn, N, cfg, had_range=True):
    if n_valid == 0:
        return f"every one of the {n_drawn} samples was degenerate (coplanar or repeated points)"
    if x is None and had_range:
        return f"no hypothesis in {n_valid} samples passed the verification (budget {_VERIFY_MAX} checks)"
    if x is None:
        return f"no hypothesis had a radius inside [{cfg.r_min:.4g}, {cfg.r_max:.4g}] m in {n_valid} samples"
    if n_valid >= N:
        return f"required N reached ({n_valid} samples, p = {cfg.p})"
    return f"stopped at max_iterations = {cfg.max_iterations} before the required N = {N:.0f} (p not reached)"


# ----------------------------------------------------------------- refit on the full cloud
@dataclass(frozen=True)
class _Final:
    fit: object
    inliers: np.ndarray
    n_snooped: int
    sigma: float | None
    reason: str
    band: float = float("nan")


def _refit(xyz, x0, cfg):
    """Final inliers from a robust band on the full cloud, Gauss-Helmert refit, then data snooping.

    The band |d| < k sigma_hat (k = 3) replaces the search threshold t: sigma_hat
    is the truncation-consistent MAD of the residuals inside the band (or the
    given sigma), band and sphere are iterated to a fixed point. Inliers cut
    at t ~ sigma would have residuals that understate sigma0 (and so every
    standard deviation) by a factor of up to 4-5. The refit is repeated (at
    most 3 times) only while more than 1 % of the inliers change with the
    adjusted sphere; the returned fit always belongs to exactly the returned inliers.
    """
    from .adjustment import gauss_helmert_model

    sigma, min_inliers = cfg.sigma, cfg.min_inliers

    def adjust(mask, x_start, sig):
        sig = sig[mask] if isinstance(sig, np.ndarray) else sig
        return gauss_helmert_model(xyz[mask], x0=x_start, sigma=sig, radius=cfg.hold_radius, alpha_w=cfg.alpha)

    # Robust band and sphere at their fixed point (eqs. 25-26 with t -> k sigma_hat); with a
    # per-point sigma the band is k sigma_i for each point
    unit = _point_sigma(sigma)
    x0, band, sigma_hat = _robust_band(xyz, x0, cfg, unit)
    if unit is not None:
        band = _BAND_K * unit
    inliers = _inlier_mask(xyz, x0, band)
    if sigma is None:  # a priori sigma for the adjustment and the w-test: the robust scale
        sigma = sigma_hat
    fit = None
    for round_ in range(3):
        if inliers.sum() < min_inliers:
            return _Final(None, inliers, 0, None, f"only {inliers.sum()} inliers (< min_inliers = {min_inliers})", band)
        try:
            fit = adjust(inliers, x0 if fit is None else fit.x, sigma)
        except LabkitError as exc:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit failed: {exc}", band)
        if not fit.converged:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit did not converge: {fit.reason}", band)
        new = _inlier_mask(xyz, fit.x, band)
        if np.count_nonzero(new != inliers) <= 0.01 * inliers.sum() or round_ == 2:
            break  # (the fit always belongs to exactly these inliers)
        inliers = new
    band = float(band) if np.ndim(band) == 0 else float(np.median(band))  # reported: the typical band
    if not cfg.snooping:
        return _Final(fit, inliers, 0, _sigma_scalar(sigma), "", band)
    return replace(_snoop(fit, inliers, sigma, min_inliers, adjust), band=band)


def _point_sigma(sigma):
    """Per-point standard deviation (n,) for a per-point band, or None for a scalar / no sigma."""
    if sigma is None or np.ndim(sigma) == 0:
        return None
    s = np.asarray(sigma, dtype=np.float64)
    return s if s.ndim == 1 else np.sqrt(np.trace(s, axis1=1, axis2=2) / 3.0)


def _robust_band(xyz, x, cfg, unit=None, max_rounds=12):
    """Fixed point of (band -> inliers -> orthogonal fit -> sigma_hat -> band = k sigma_hat), from t.

    Returns the sphere, the band half-width and sigma_hat. With an a priori
    sigma the band is k sigma at once (k sigma_i per point for ``unit``, the
    per-point sigma); only the sphere is iterated.
    """
    t = cfg.threshold
    known = cfg.sigma if cfg.sigma is not None and np.ndim(cfg.sigma) == 0 else None
    band = _BAND_K * known if known is not None else t
    sigma_hat = known if known is not None else t / _BAND_K
    # only points that can ever be in a band matter: a generous neighbourhood of the hypothesis
    reach = max(8.0 * t, 8.0 * band) if unit is None else max(8.0 * t, 3.0 * _BAND_K * float(unit.max()))
    d = sphere_residuals(xyz, x)
    near = np.flatnonzero(np.abs(d) < reach)
    P = xyz[near]
    if unit is not None:
        known, band = True, _BAND_K * unit[near]
        sigma_hat = float(np.median(unit))
    d = sphere_residuals(P, x)
    for _ in range(max_rounds):
        inl = np.abs(d) < band
        if inl.sum() <= S:
            break
        x_new = _orthogonal_fit(P[inl], x, steps=2)
        x = x if x_new is None else x_new
        d = sphere_residuals(P, x)
        inl_new = np.abs(d) < band
        if known is not None:  # band fixed by the given sigma: iterate the sphere until the inliers settle
            if np.array_equal(inl_new, inl):
                break
            continue
        if inl_new.sum() <= S:
            break
        sigma_hat = _truncated_mad_scale(np.abs(d[inl_new]), band)
        new_band = min(_BAND_K * sigma_hat, 2.0 * band, reach)  # grow at most 2x per round
        converged = abs(new_band - band) <= 0.005 * band
        band = new_band
        if converged:
            break
    return x, (float(band) if np.ndim(band) == 0 else band), float(sigma_hat)


def _truncated_mad_scale(abs_d, band):
    """sigma of N(0, sigma^2) whose |d|, truncated at ``band``, has the observed median.

    Solves (2 Phi(m / sigma) - 1) / (2 Phi(b / sigma) - 1) = 1/2 for sigma. A
    median of b/2 or more means no peak inside the band (flat): returns 2 b / k,
    which doubles the band.
    """
    m = float(np.median(abs_d))
    q = m / band
    if q >= 0.499:
        return 2.0 * band / _BAND_K
    if q <= 1e-9:
        return max(m, 1e-12)
    g = lambda z: 2.0 * (2.0 * ndtr(q * z) - 1.0) - (2.0 * ndtr(z) - 1.0)  # noqa: E731  (z = b / sigma)
    hi = 1.0
    while g(hi) < 0 and hi < 1e6:
        hi *= 2.0
    z = brentq(g, 1e-6, hi, xtol=1e-10)
    return band / z


def _snoop(fit, inliers, sigma, min_inliers, adjust):
    """Data snooping: drop points whose |w| exceeds the critical value, refit, repeat."""
    n_removed = 0
    for _ in range(_SNOOP_ROUNDS):
        flagged = fit.flagged  # |w_i| > critical value of level alpha (two-sided)
        if not flagged.any():
            break
        idx = np.flatnonzero(inliers)
        inliers = inliers.copy()
        inliers[idx[flagged]] = False
        n_removed += int(flagged.sum())
        if inliers.sum() < min_inliers:
            return _Final(None, inliers, n_removed, _sigma_scalar(sigma), "too few inliers left after data snooping")
        try:
            fit = adjust(inliers, fit.x, sigma)
        except LabkitError as exc:
            return _Final(None, inliers, n_removed, _sigma_scalar(sigma), f"refit after data snooping failed: {exc}")
    return _Final(fit, inliers, n_removed, _sigma_scalar(sigma), "")


def _sigma_scalar(sigma):
    return float(sigma) if np.ndim(sigma) == 0 else None


# ----------------------------------------------------------------- verification
class _Verifier:
    """Is a hypothesis a sphere cap seen by the scanner? Checks on the full cloud (reduced frame).

    ``accepts(x)`` is asked for every hypothesis that would become the best:
    it polishes x on its inliers of the full cloud (two rounds of inliers ->
    orthogonal fit) and runs :meth:`reasons`. Rejected spheres are remembered,
    and hypotheses close to one of them are rejected without a new check.
    """

    def __init__(self, X, station, cfg):
        self.X, self.station, self.cfg = X, station, cfg
        self._tree = None
        self.n_rejected, self.n_checked = 0, 0
        self.best_rejection = ""
        self._best_rejected_score = -np.inf
        self._rejected = []  # polished spheres that failed
        self._R = None  # the same as an array (cached)

    @property
    def tree(self):
        if self._tree is None:
            self._tree = cKDTree(self.X)
        return self._tree

    def start(self, cfg):
        self.cfg = cfg
        self.n_checked = 0  # the budget is per search (working set)

    @property
    def exhausted(self):
        return self.n_checked >= _VERIFY_MAX

    def accepts(self, x, score=0.0):
        cfg = self.cfg
        if self.near_rejected(x[None, :])[0] or self.exhausted:
            return False
        self.n_checked += 1
        coarse = self._coarse_reason(x, cfg.threshold)
        if coarse:  # clearly not a sphere (counted in C, no polishing): most large spheres end here
            self._remember(coarse, x, score)
            return False
        x_pol = self._polish(x, cfg.threshold)
        reason = "its inliers do not determine a sphere" if x_pol is None else self.reasons(x_pol, cfg.threshold)
        if reason:
            self._remember(reason, x if x_pol is None else x_pol, score)
        return not reason

    def _remember(self, reason, x, score=0.0):
        if not self.best_rejection or score > self._best_rejected_score:
            self.best_rejection, self._best_rejected_score = reason, score
        self.n_rejected += 1
        self._rejected.append(np.asarray(x, dtype=np.float64))

    def _coarse_reason(self, x, t):
        """A quick interior test on the raw hypothesis: many points deep inside (beyond 5 t)."""
        c, r = x[:3], float(x[3])
        if r <= 5.0 * t:
            return ""
        shell = self.tree.query_ball_point(c, r + t, return_length=True) - self.tree.query_ball_point(
            c, r - t, return_length=True)
        deep = self.tree.query_ball_point(c, r - 5.0 * t, return_length=True)
        if deep > max(5.0 * _INTERIOR_SHARE * shell, 20):
            return (f"{deep} points lie deep inside it (for {shell} on its shell): a solid sphere hides its "
                    "interior, so this is a cut through other surfaces or a volume of points, not a sphere")
        return ""

    def reject(self, *spheres):
        """Remember spheres that failed (e.g. in the final refit): hypotheses near them are not tried again."""
        self._rejected += [np.asarray(x, dtype=np.float64) for x in spheres if x is not None]
        self.n_rejected += 1

    def final_check(self, x, band):
        """Reasons to reject the final adjusted sphere (with the final band as shell half-width)."""
        return self.reasons(np.asarray(x, dtype=np.float64), max(band, self.cfg.threshold))

    def near_rejected(self, X):
        """For hypotheses X (B, 4): close to a sphere that already failed (centre and radius within
        max(t, 10 % of r))?"""
        if not self._rejected:
            return np.zeros(len(X), dtype=bool)
        if self._R is None or len(self._R) != len(self._rejected):
            self._R = np.array(self._rejected)
        R = self._R
        tol = np.maximum(self.cfg.threshold, 0.1 * R[:, 3])[None, :]
        dc2 = _squared_center_distances(X[:, :3], np.einsum("ij,ij->i", X[:, :3], X[:, :3]), R[:, :3])
        return ((dc2 < tol * tol) & (np.abs(X[:, None, 3] - R[None, :, 3]) < tol)).any(axis=1)

    def _local(self, x, reach):
        """Indices and residuals d (eq. 25) of the points within r + reach of the centre."""
        idx = np.asarray(self.tree.query_ball_point(x[:3], x[3] + reach), dtype=np.int64)
        diff = self.X[idx] - x[:3]
        return idx, np.sqrt(np.einsum("ij,ij->i", diff, diff)) - x[3]

    def _polish(self, x, t):
        """Inliers -> orthogonal fit, three rounds; the band widens to k sigma_hat when t is below the noise."""
        band = t
        for _ in range(3):
            idx, d = self._local(x, band)
            on = np.abs(d) < band
            if on.sum() <= S:
                return None
            x_new = _orthogonal_fit(self.X[idx[on]], x, steps=2)
            if x_new is None:
                return None
            x = x_new
            if not 0.5 * self.cfg.r_min <= x[3] <= 2.0 * self.cfg.r_max:
                return x  # far outside the radius range: more rounds will not bring it back (reasons() rejects)
            _, d = self._local(x, band)
            d = d[np.abs(d) < band]
            if len(d) > S:
                band = max(t, min(_BAND_K * _truncated_mad_scale(np.abs(d), band), 3.0 * t))
        return x

    def reasons(self, x, t):
        """'' for a plausible sphere cap, else why not (checks of ransac_sphere's Notes)."""
        cfg = self.cfg
        c, r = x[:3], float(x[3])
        if not cfg.r_min <= r <= cfg.r_max:
            return f"the adjusted radius {r:.5g} m lies outside [{cfg.r_min:.5g}, {cfg.r_max:.5g}] m"
        idx, d = self._local(x, 3.0 * max(t, 2.0 * _BAND_K * t))
        on = np.abs(d) < t
        n_in = int(on.sum())
        if n_in < cfg.min_inliers:
            return f"only {n_in} points on its shell |d| < {t:.3g} m in the full cloud (< min_inliers = {cfg.min_inliers})"
        sigma_hat = _truncated_mad_scale(np.abs(d[on]), t)  # robust, and consistent for the cut at t
        margin = max(t, 3.5 * sigma_hat)
        # the shell: at least the noise band k sigma_hat (a t below the noise must not thin it out)
        t = max(t, min(_BAND_K * sigma_hat, 2.0 * t))
        on = np.abs(d) < t
        n_in = int(on.sum())
        inside = int(np.count_nonzero(d < -margin))
        if inside > _INTERIOR_SHARE * n_in:
            return (f"{inside} points lie inside it (for {n_in} on its shell): a solid sphere hides its interior, "
                    "so this is a cut through other surfaces or a volume of points, not a sphere")
        outside = int(np.count_nonzero((d >= t) & (d < 3.0 * t)))
        if n_in < _CONTRAST * outside:
            return (f"too many points just outside the shell ({outside}, for {n_in} on it): no spherical surface "
                    "stands out, the points only pass through the shell (a cylinder, plane pieces, clutter)")
        P = self.X[idx[on]]
        q = P - P.mean(axis=0)
        rms_plane = np.sqrt(max(np.linalg.eigvalsh(q.T @ q / len(q))[0], 0.0))
        rms_sphere = np.sqrt(np.mean(d[on] ** 2))
        if rms_plane < _PLANE_RATIO * rms_sphere:
            return (f"the inliers are nearly flat (plane rms {rms_plane * 1e3:.3g} mm vs sphere rms "
                    f"{rms_sphere * 1e3:.3g} mm): a plane patch, not a sphere")
        planes = _two_plane_share(P, t)
        if planes >= _TWO_PLANES_SHARE:
            return (f"{planes:.0%} of its inliers lie on one or two planes: pieces of planes (a floor, a wall, "
                    "an edge) cut by the sphere, not a sphere")
        normals = (P - c) / np.linalg.norm(P - c, axis=1, keepdims=True)  # from the model, not from neighbours
        spread = _cap_spread(normals, None if self.station is None else self.station - c)
        if spread < _MIN_SPREAD:
            return (f"the inliers cover no cap (their normals spread over {np.degrees(np.sqrt(max(spread, 0))):.1f} deg "
                    "across): a ring or a strip, e.g. one scan line on a round object")
        if self.station is None:
            return ""
        return self._visibility(c, r, margin, normals, P, n_in)

    def _visibility(self, c, r, margin, normals, P, n_in):
        s = self.station
        if np.linalg.norm(s - c) <= r:
            return "the station lies inside it: a scanner cannot see a solid sphere from inside"
        view = s - P
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        back = float(np.mean(np.einsum("ij,ij->i", normals, view) < -0.1))
        if back > _BACKFACE_SHARE:
            return (f"{back:.0%} of its inliers lie on the side turned away from the station: "
                    "they cannot be a sphere the scanner saw")
        lines = _elevation_levels(P - s, 2.0 * np.arcsin(min(r / np.linalg.norm(s - c), 1.0)))
        if lines < _MIN_LEVELS:
            return (f"its inliers lie on only {lines} scan line(s) (elevation levels seen from the station): "
                    "two rings on a round object such as a cylinder fit such a sphere as well")
        shadow = _points_behind(self.X, s, c, r - margin, margin)
        if shadow > _SHADOW_SHARE * n_in:
            return (f"{shadow} points lie behind it seen from the station (for {n_in} on its shell): "
                    "the scanner looked through it, free space where a solid sphere would be")
        return ""


def _cap_spread(normals, axis):
    """Smallest variance of the unit normals across the viewing axis (1/4 for a full hemisphere).

    The normals are projected onto the plane normal to ``axis`` (the direction
    to the station, or their mean direction when no station is known); a cap
    spreads in both directions, a ring or strip of one scan line in one only.
    """
    if axis is None:
        axis = normals.mean(axis=0)
        if np.linalg.norm(axis) < 0.2:
            return 1.0  # normals all round the sphere (several stations): no single cap to check
    a = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    uv = np.column_stack([normals @ e1, normals @ e2])
    return float(np.linalg.eigvalsh(np.cov(uv.T))[0]) if len(uv) > 2 else 0.0


def _two_plane_share(P, t, trials=256):
    """Largest share of the points P within t of one plane plus a second plane (greedy, sampled planes).

    A true cap puts at most one or two scan lines on any plane; a sphere
    through a floor and a wall (an edge) has nearly all its inliers on two.
    Planes through random point triples of a fixed-seed generator (deterministic).
    """
    n = len(P)
    if n < 6:
        return 1.0
    gen = np.random.default_rng(0)
    left = np.ones(n, dtype=bool)
    held = 0
    for _ in range(2):
        Q = P[left]
        if len(Q) < 3:
            held += len(Q)
            break
        tri = Q[gen.integers(0, len(Q), size=(trials, 3))]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(nrm, axis=1)
        ok = norm > 1e-12
        if not ok.any():
            break
        nrm = nrm[ok] / norm[ok, None]
        dist = np.abs(Q @ nrm.T - np.einsum("bk,bk->b", tri[ok][:, 0], nrm)[None, :])  # (m, b)
        on = dist < t
        best = int(np.argmax(on.sum(axis=0)))
        idx = np.flatnonzero(left)
        left[idx[on[:, best]]] = False
        held += int(on[:, best].sum())
    return held / n


def _elevation_levels(V, diameter):
    """Distinct elevation levels (z up) of the directions V from the station, in bins of 1/8 of the
    sphere's angular diameter: the scan lines of a multi-beam scanner, many for a TLS."""
    el = np.arcsin(np.clip(V[:, 2] / np.linalg.norm(V, axis=1), -1.0, 1.0))
    width = max(diameter / 8.0, 1e-9)
    return int(np.unique(np.floor(el / width)).size)


def _points_behind(X, s, c, r_inner, margin):
    """Points whose ray from the station s crosses the ball (c, r_inner) and ends beyond its entry."""
    if r_inner <= 0:
        return 0
    sc = c - s
    dist_c = np.linalg.norm(sc)
    # only rays within the cone that the ball subtends can cross it
    V = X - s
    rng_ = np.sqrt(np.einsum("ij,ij->i", V, V))
    cos_cone = np.sqrt(max(1.0 - (r_inner / dist_c) ** 2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        tc = (V @ sc) / rng_  # distance along the ray to the foot of the centre
        in_cone = tc > cos_cone * dist_c  # cos(angle between ray and centre) > cos(half cone)
    tc, rng_ = tc[in_cone], rng_[in_cone]
    h2 = r_inner**2 - (dist_c**2 - tc**2)
    entry = tc - np.sqrt(np.maximum(h2, 0.0))
    return int(np.count_nonzero((h2 > 0) & (rng_ > entry + margin)))


def _not_found(n, reason, **common) -> RansacResult:
    return RansacResult(
        fit=None, inliers=np.zeros(n, dtype=bool), found=False, outlier_ratio=float("nan"), reason=reason, **common
    )
