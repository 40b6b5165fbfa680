"""The public detection: ``ransac_sphere`` (checks, working sets, search, refit and verification)."""

from __future__ import annotations

import math
import numbers
from dataclasses import replace

import numpy as np

from ..core.checks import as_points, choice, count, numeric_array, positive, probability
from ..core.frame import local_origin, reduce
from ..core.errors import LabkitError
from ._ball import reduced
from .config import COARSE_POINTS, FINAL_ATTEMPTS, LOCAL_MAX_PAIRS, LOCAL_MAX_SHARE, LOCAL_REACH, S, Config
from .refit import refit_sphere
from .result import RansacResult, not_found
from .sampling import LocalSampler, UniformSampler, mean_neighbourhood_share, pick_sampling, working_set
from .search import adaptive_search
from .verify import Verifier


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
        hold for any t between about 1 and 5 sigma. The exercise sheet (notebook 02) sets t = sigma.
    p : float
        Probability that at least one outlier-free sample is drawn (eq. 27).
    rng : int or numpy.random.Generator, optional
        Seed or generator. The result records a seed that reproduces the run.
    radius_range : (r_min, r_max), optional
        Admissible radii (m). Hypotheses outside are rejected (they still count
        as samples); the radius is checked again after the refit. Default:
        ``nominal_radius`` +- 10 %, otherwise any radius up to the diagonal of
        the bounding box of the working set (``preliminary_size`` points) - and a sphere is then still only "found" when it passes the
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
        Sphere through each sample: batched closed form (fast) or the exercise's
        Gauss-Helmert adjustment of the 4 points (slow, for teaching).
    local_optimization : bool
        LO-RANSAC: refine each new best by least squares on its inliers.
    preliminary_size : int or None
        Hypotheses are drawn from and scored on a random reduction to this many
        points (the exercise uses 1000); the final inliers come from the full cloud.
        None uses every point.
    sampling : {'auto', 'uniform', 'local'}
        'uniform': 4 random points. 'local': a random first point and three
        more from its neighbourhood of radius r_max + t (needs a radius range or
        nominal radius); N is then computed with the local inlier shares.
        'auto': local when r_max is known, the working set is more than
        10 r_max wide (bounding-box diagonal), a neighbourhood holds on average
        at most 25 % of it and the neighbour pairs number at most 8 million.
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

    References
    ----------
    .. [1] Seed 000, section 2: minimal samples, inliers by eqs. (25-26), N by
       eq. (27), refit of the best sphere in the Gauss-Helmert model.
    .. [2] M. A. Fischler, R. C. Bolles (1981): Random sample consensus: a
       paradigm for model fitting with applications to image analysis and
       automated cartography. Communications of the ACM 24(6), 381-395,
       doi:10.1145/358669.358692.
    .. [3] R. Hartley, A. Zisserman (2004): Multiple View Geometry in Computer
       Vision, 2nd edition, Cambridge University Press, section 4.7.
    .. [4] P. H. S. Torr, A. Zisserman (2000): MLESAC: a new robust estimator
       with application to estimating image geometry. Computer Vision and Image
       Understanding 78(1), 138-156 (the MSAC score, ``scoring='msac'``).
    .. [5] O. Chum, J. Matas, J. Kittler (2003): Locally optimized RANSAC.
       Pattern Recognition (DAGM 2003), LNCS 2781, 236-243 (``local_optimization``).
    .. [6] W. Baarda (1968): A testing procedure for use in geodetic networks.
       Netherlands Geodetic Commission, Publications on Geodesy 2(5) (data snooping).

    Examples
    --------
    >>> from labkit.ransac import ransac_sphere
    >>> from labkit.synthetic import sphere_on_tripod
    >>> scene = sphere_on_tripod(n_sphere=400, rng=1)
    >>> result = ransac_sphere(scene.points, threshold=0.003, rng=0, radius_range=(0.05, 0.1))
    >>> result.found, round(result.radius, 3), scene.sphere.round(4).tolist()
    (True, 0.072, [0.0, 0.0, 1.4525, 0.0725])
    >>> bool(abs(result.radius - scene.sphere[3]) < 3 * result.fit.std[3])
    True
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
    max_iterations = count(max_iterations, "max_iterations", minimum=1)
    min_inliers = count(min_inliers, "min_inliers", minimum=S + 1)
    sigma = _check_sigma(sigma, len(xyz))
    station = _check_station(station)

    cfg = Config(t, p, r_min, r_max, known, scoring, minimal_solver, sampling, max_iterations,
                  bool(local_optimization), min_inliers, bool(snooping), sigma, alpha,
                  float(nominal_radius) if hold_radius else None, station)

    # Search a random reduction of the cloud; if nothing is found there, a 4x and a 16x larger one
    origin = local_origin(xyz)
    # (a cloud the coarse test reads whole is also stored by axis, written in the same pass)
    whole = len(xyz) < 2 * COARSE_POINTS
    X, by_axis = reduced(xyz, origin, by_axis=True) if whole else (reduced(xyz, origin), None)
    verifier = Verifier(X, None if station is None else station - origin, cfg, by_axis)
    tried = []
    for size in _reduction_sizes(len(xyz), preliminary_size):
        result, had_best = _detect(xyz, origin, working_set(len(xyz), size, gen), cfg, seed, gen, verifier)
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
    extent = float(np.linalg.norm(np.ptp(np.ascontiguousarray(W.T), axis=1)))  # (numpy's ptp over rows is slow)
    if not cfg.known:  # no sphere larger than the scan (a cropped cap is as wide as about its radius)
        cfg = replace(cfg, r_max=max(extent, 1e-9))
    sampling = pick_sampling(cfg.sampling, cfg.known, cfg.r_max, extent)
    if cfg.sampling == "auto" and sampling == "local":
        share = mean_neighbourhood_share(W, LOCAL_REACH * cfg.r_max + cfg.threshold)
        if share > LOCAL_MAX_SHARE or share * len(W) ** 2 > LOCAL_MAX_PAIRS:
            # the neighbourhoods hold much of the scene: local sampling gains little and costs O(m^2) pairs
            sampling = "uniform"
    sampler = LocalSampler(W, LOCAL_REACH * cfg.r_max + cfg.threshold) if sampling == "local" else UniformSampler(len(W))

    # Adaptive search (eqs. 25-27) on the working set; a best whose final refit fails the checks is
    # rejected and the search runs again without it (at most FINAL_ATTEMPTS times)
    shift = np.append(origin, 0.0)
    for attempt in range(FINAL_ATTEMPTS):
        verifier.start(cfg)
        search = adaptive_search(W, sampler, cfg, gen, verifier)
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
            return not_found(len(xyz), reason, **common), verifier.n_rejected > 0 or search.had_range

        # Final inliers from the full cloud (robust band), Gauss-Helmert refit, data snooping, checks
        final = refit_sphere(xyz, search.x, cfg, verifier.X, shift, verifier.near_shell)
        reason = final.reason
        if not reason:
            reason = verifier.final_check(final.fit.x - shift, final.band)
        if not reason:
            return RansacResult(
                fit=final.fit, inliers=final.inliers, found=True, outlier_ratio=1.0 - np.count_nonzero(final.inliers) / len(xyz),
                reason=search.reason, n_snooped=final.n_snooped, sigma=final.sigma, band=final.band, **common,
            ), True
        verifier.reject(search.x, None if final.fit is None else final.fit.x - shift)
    return not_found(len(xyz), f"{reason} (the final refit of the best failed in {FINAL_ATTEMPTS} searches)",
                      n_snooped=final.n_snooped, sigma=final.sigma, band=final.band, **common), True


def _reduction_sizes(n, preliminary_size):
    """Working-set sizes to try: the preliminary size, then 4x and 16x (capped at n)."""
    if preliminary_size is None:
        return [n]
    size = count(preliminary_size, "preliminary_size", minimum=S)
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
    arr = numeric_array(sigma, "sigma", finite=False)
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
