"""RANSAC detection of a sphere in a cluttered point cloud (notebook 02).

The seed's section 2: draw minimal samples of s = 4 points that are not
coplanar, compute the sphere through each, count the points whose orthogonal
distance satisfies d_i^2 < t^2 (eqs. 25-26), stop after the adaptive number
of samples N of eq. (27), and refit the best sphere in the Gauss-Helmert model
on all its inliers. Added for real scans: a radius range or nominal radius,
MSAC scoring, local optimization (LO-RANSAC), preliminary scoring on a random
reduction of the cloud, local sampling for tiny spheres in large scenes, and a
final data-snooping pass with Baarda's w-test.

Hypotheses are generated and scored in vectorized batches; the batch is then
replayed in sample order, so the bookkeeping (new bests, N after each new best,
the stopping sample) is exactly that of the one-sample-at-a-time loop.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

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
_MAX_NORMAL_ANGLE = 20.0  # deg: inlier normals must point to the centre (true spheres: < 10)


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
            ("threshold t", fmt(self.threshold * 1e3, 2, "mm")),
            ("p", fmt(self.p, 4)),
            ("working set", f"{self.n_working} points"),
            ("valid samples", f"{self.iterations}"),
            ("required N (eq. 27)", f"{self.n_required:.0f}"),
            ("degenerate samples", f"{self.n_invalid}"),
            ("new bests", f"{len(self.n_required_history)}"),
            ("seed", f"{self.seed}"),
        ]
        checks = [("removed by data snooping", f"{self.n_snooped}")]
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
) -> RansacResult:
    """Detect a sphere with RANSAC and adjust it in the Gauss-Helmert model.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        The scan, n >= 4 (any frame; UTM coordinates are reduced internally).
    threshold : float
        Inlier threshold t in metres: inlier if d_i^2 < t^2 (eqs. 25-26).
        The seed sets t = sigma; 2-3 sigma keeps more of the true surface.
    p : float
        Probability that at least one outlier-free sample is drawn (eq. 27).
    rng : int or numpy.random.Generator, optional
        Seed or generator. The result records a seed that reproduces the run.
    radius_range : (r_min, r_max), optional
        Admissible radii (m). Hypotheses outside are rejected (they still count
        as samples); the radius is checked again after the refit. Default:
        ``nominal_radius`` +- 10 %, otherwise radii up to the extent of the cloud.
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

    Returns
    -------
    RansacResult
        ``found=False`` with a reason when no sphere is found; never a guess.

    Raises
    ------
    LabkitError
        Fewer than 4 points, NaN/inf, threshold <= 0, p outside (0, 1), an
        invalid radius range or option.
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

    cfg = _Config(t, p, r_min, r_max, known, scoring, minimal_solver, sampling, max_iterations,
                  bool(local_optimization), min_inliers, bool(snooping), sigma, alpha,
                  float(nominal_radius) if hold_radius else None)

    # Search a random reduction of the cloud; if nothing is found there, a 4x and a 16x larger one
    origin = local_origin(xyz)
    tried = []
    for size in _reduction_sizes(len(xyz), preliminary_size):
        result, had_best = _detect(xyz, origin, _working_set(len(xyz), size, gen), cfg, seed, gen)
        tried.append(size)
        if result.found or not had_best:
            break  # (without any hypothesis in range, a larger working set would not help)
    if len(tried) > 1:
        sizes = ", ".join(f"{k}" for k in tried)
        result = replace(result, reason=f"{result.reason} [searched reductions to {sizes} points]")
    return result


def _detect(xyz, origin, idx, cfg, seed, gen):
    """One detection: adaptive search on the working set xyz[idx], refit and checks on the full cloud.

    Returns the RansacResult and whether the search had a best hypothesis at all.
    """
    # The working set, reduced to the local origin, and its sampler
    W = reduce(xyz[idx], origin)
    extent = float(np.linalg.norm(np.ptp(W, axis=0)))
    if not cfg.known:
        cfg = replace(cfg, r_max=max(extent, 1e-9))  # no sphere larger than the scan
    sampling = _pick_sampling(cfg.sampling, cfg.known, cfg.r_max, extent)
    if cfg.sampling == "auto" and sampling == "local" and _mean_neighbourhood_share(W, 2.0 * cfg.r_max + cfg.threshold) > 0.1:
        sampling = "uniform"  # the neighbourhoods hold much of the scene: local sampling gains little, costs O(m^2)
    sampler = _LocalSampler(W, 2.0 * cfg.r_max + cfg.threshold) if sampling == "local" else _UniformSampler(len(W))

    # Adaptive search (eqs. 25-27) on the working set
    search = _search(W, sampler, cfg, gen)
    common = dict(
        iterations=search.iterations, n_required_history=search.history, seed=seed, n_invalid=search.n_invalid,
        sampling=sampling, scoring=cfg.scoring, minimal_solver=cfg.minimal_solver, threshold=cfg.threshold,
        p=cfg.p, n_required=float(search.N), n_working=len(W),
    )
    if search.x is None:
        return _not_found(len(xyz), search.reason, **common), False

    # Final inliers from the full cloud, Gauss-Helmert refit, data snooping, checks
    x0 = search.x + np.append(origin, 0.0)
    final = _refit(xyz, x0, cfg)
    reason = final.reason or _check_sphere(xyz[final.inliers], final.fit, cfg.r_min, cfg.r_max, gen)
    if reason:
        return _not_found(len(xyz), reason, n_snooped=final.n_snooped, sigma=final.sigma, **common), True
    return RansacResult(
        fit=final.fit, inliers=final.inliers, found=True, outlier_ratio=1.0 - final.inliers.mean(),
        reason=search.reason, n_snooped=final.n_snooped, sigma=final.sigma, **common,
    ), True


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
    if sigma is None or np.ndim(sigma) == 0:
        return None if sigma is None else positive(sigma, "sigma")
    arr = np.asarray(sigma, dtype=np.float64)
    if arr.shape not in ((n,), (n, 3, 3)):
        raise LabkitError(f"sigma must be a scalar, shape ({n},) or ({n}, 3, 3), got {arr.shape}")
    return arr


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


def _search(W, sampler, cfg, gen):
    """The adaptive RANSAC loop on the working set W, in replayed vectorized batches."""
    Wsq = np.einsum("ij,ij->i", W, W)
    best = _Best(x=None, score=-np.inf)
    n_valid = n_drawn = n_invalid = 0
    N = math.inf  # the seed starts with N = infinity
    history: list[tuple[int, float]] = []
    cap = max(_MIN_BATCH, _CELLS_PER_BATCH // len(W))
    batch = min(_FIRST_BATCH, cap) if cfg.minimal_solver == "closed_form" else _MIN_BATCH
    while n_valid < min(N, cfg.max_iterations):
        if n_drawn >= 10 * cfg.max_iterations or (n_drawn >= 2000 and n_valid == 0):
            break
        # Draw and solve a batch; degenerate samples do not count
        idx = sampler.draw(gen, batch)
        X, valid = _hypotheses(W[idx], cfg.minimal_solver)
        position = np.flatnonzero(valid)[: cfg.max_iterations - n_valid]  # batch position of each valid sample
        X = X[position]

        # Score hypotheses inside the radius range (the others count but cannot win)
        scores = np.full(len(X), -np.inf)
        ok = (X[:, 3] >= cfg.r_min) & (X[:, 3] <= cfg.r_max)
        if ok.any():
            scores[ok] = _score(W, Wsq, X[ok], cfg.threshold, cfg.scoring)[0]

        # Replay in sample order: new bests (with LO), N after each (eq. 27), stop at N
        keep, stopped, best, N, events = _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg)
        history += [(n_valid + j + 1, N_j) for j, N_j in events]
        drawn = int(position[keep - 1]) + 1 if stopped else batch  # samples the sequential loop drew
        n_drawn += drawn
        n_invalid += drawn - keep
        n_valid += keep
        batch = _next_batch(N, cfg, n_valid, n_drawn, cap)
    return _Search(
        x=best.x, iterations=n_valid, N=N, n_invalid=n_invalid,
        history=np.array(history, dtype=np.float64).reshape(-1, 2),
        reason=_search_reason(best.x, n_valid, n_drawn, N, cfg),
    )


@dataclass(frozen=True)
class _Best:
    x: np.ndarray | None
    score: float


def _replay(X, scores, best, n_valid, N, W, Wsq, sampler, cfg):
    """Sequential bookkeeping of one batch, exactly as the one-sample-at-a-time loop.

    Walks through the samples that beat the running best in order; each new
    best is refined by LO (if enabled) and sets the required N. Returns the
    number of valid samples the loop used, whether it stopped inside the batch,
    the best hypothesis, the current N and the (position, N) events.
    """
    candidates = np.flatnonzero(scores > np.maximum.accumulate(np.concatenate([[best.score], scores]))[:-1])
    events = []
    it = n_valid + np.arange(1, len(X) + 1)  # iteration number of each valid sample
    for j in candidates:
        if it[j] > N:
            break  # the loop stopped at sample N, before sample j
        if scores[j] <= best.score:
            continue  # beaten by an LO-refined best meanwhile
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


def _search_reason(x, n_valid, n_drawn, N, cfg):
    if n_valid == 0:
        return f"every one of the {n_drawn} samples was degenerate (coplanar or repeated points)"
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


def _refit(xyz, x0, cfg):
    """Inliers from the full cloud, Gauss-Helmert refit on them, then data snooping.

    The refit is repeated (at most 3 times) only while more than 1 % of the
    inliers change with the adjusted sphere; the returned fit always belongs to
    exactly the returned inliers.
    """
    from .adjustment import gauss_helmert_model

    t, sigma, min_inliers = cfg.threshold, cfg.sigma, cfg.min_inliers

    def adjust(mask, x_start, sig):
        sig = sig[mask] if isinstance(sig, np.ndarray) else sig
        return gauss_helmert_model(xyz[mask], x0=x_start, sigma=sig, radius=cfg.hold_radius, alpha_w=cfg.alpha)

    # Inliers of the best hypothesis in the full cloud (eqs. 25-26), polished by
    # one orthogonal least-squares step so that they and sigma do not depend on
    # the small working set
    inliers = _inlier_mask(xyz, x0, t)
    if inliers.sum() > S:
        x1 = _orthogonal_fit(xyz[inliers], x0, steps=2)
        x0 = x0 if x1 is None else x1
    d = sphere_residuals(xyz, x0)
    inliers = d * d < t * t
    if sigma is None:  # a priori sigma for the w-test: robust from the inlier distances
        sigma = max(1.4826 * float(np.median(np.abs(d[inliers]))), 1e-12) if inliers.any() else None
    fit = None
    for _ in range(3):
        if inliers.sum() < min_inliers:
            return _Final(None, inliers, 0, None, f"only {inliers.sum()} inliers (< min_inliers = {min_inliers})")
        try:
            fit = adjust(inliers, x0 if fit is None else fit.x, sigma)
        except LabkitError as exc:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit failed: {exc}")
        if not fit.converged:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit did not converge: {fit.reason}")
        changed = np.count_nonzero(_inlier_mask(xyz, fit.x, t) != inliers)
        if changed <= 0.01 * inliers.sum():
            break
        inliers = _inlier_mask(xyz, fit.x, t)
    if not cfg.snooping:
        return _Final(fit, inliers, 0, _sigma_scalar(sigma), "")
    return _snoop(fit, inliers, sigma, min_inliers, adjust)


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


def _check_sphere(P, fit, r_min, r_max, gen):
    """Reasons to reject the refitted sphere: radius outside the range, no real curvature,
    or inliers that are pieces of other surfaces cut by the sphere's shell."""
    r = float(fit.x[3])
    if not r_min <= r <= r_max:
        return f"the adjusted radius {r:.5g} m lies outside [{r_min:.5g}, {r_max:.5g}] m"
    angle = _median_normal_angle(P, fit.x, gen)
    if angle > _MAX_NORMAL_ANGLE:
        return (
            f"the inliers' surface normals do not point to the centre (median angle {angle:.0f} deg): "
            "they are pieces of other surfaces cut by the sphere, not a sphere"
        )
    q = P - P.mean(axis=0)
    rms_plane = np.sqrt(np.linalg.eigvalsh(q.T @ q / len(q))[0])
    rms_sphere = np.sqrt(np.mean(sphere_residuals(P, fit.x) ** 2))
    if rms_plane < _PLANE_RATIO * rms_sphere:
        return (
            f"the inliers are nearly flat (plane rms {rms_plane * 1e3:.3g} mm vs sphere rms "
            f"{rms_sphere * 1e3:.3g} mm): no sphere, a plane patch"
        )
    return ""


def _median_normal_angle(P, x, gen, m=300, k=12):
    """Median angle (deg) between local PCA normals of the inliers and the sphere's radial direction.

    On a sphere both agree up to noise; where planes or edges merely cut
    through the shell |d| < t, the local normals are those of the planes.
    The normals come from k-neighbourhoods in a random subset of at most m
    inliers, so each patch spans a sizeable part of the cap (noise matters less).
    """
    if len(P) > m:
        P = P[gen.choice(len(P), m, replace=False)]
    _, idx = cKDTree(P).query(P, k=min(k, len(P)))
    nb = P[idx] - P[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normal = vecs[:, :, 0]  # smallest eigenvalue
    radial = P - x[:3]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ij,ij->i", normal, radial))
    return float(np.degrees(np.arccos(np.clip(np.median(cos), 0.0, 1.0))))


def _not_found(n, reason, **common) -> RansacResult:
    return RansacResult(
        fit=None, inliers=np.zeros(n, dtype=bool), found=False, outlier_ratio=float("nan"), reason=reason, **common
    )
