"""Normals robust to outliers inside the neighbourhood: RANSAC / LMedS planes per point (notebook 04, eq. 9).

For every neighbourhood, random triples of neighbours give plane hypotheses

- (eq. 9) plane through three points  n = (p2 - p1) x (p3 - p1),

each scored on all k neighbours (most inliers, or least median of squares); the
best plane's inliers are refitted by PCA (eqs. 1-4). The hypotheses of all points
of a chunk are drawn and scored at once, without a loop over points.

References
----------
Fischler, Bolles (1981): Random sample consensus. Comm. ACM 24(6), 381-395.
Rousseeuw, Leroy (1987): Robust Regression and Outlier Detection. Wiley, p. 202 (LMedS scale).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from ..core.checks import as_rng, positive, probability
from ..core.report import ReportMixin, fmt
from ..core.stats import MAD_TO_SIGMA
from ..core.errors import LabkitError
from ..neighbours.search import SearchPlan, check_chunk_size, check_scale, reduced, run_chunks
from ..neighbours.moments import masked_covariances
from ..ransac.iterations import required_iterations
from ._steps import check_at, check_duplicates, check_orientation, orient_normals, plane_noise, sorted_eigh


@dataclass(frozen=True, eq=False, repr=False)
class RobustNormals(ReportMixin):
    """Result of :func:`robust_normals`.

    Attributes
    ----------
    normals : ndarray (n, 3)
        Unit normals from PCA of each neighbourhood's plane inliers.
    inliers : ndarray (n,)
        Number of inliers of the chosen plane (of k).
    noise : ndarray (n,)
        sigma_n of the inliers (eq. 5), metres.
    iterations : int
        Plane hypotheses drawn per neighbourhood.
    threshold : float or None
        Fixed inlier distance, or None for the least-median-of-squares scale.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.features import robust_normals
    >>> from labkit.synthetic import flat_floor
    >>> rn = robust_normals(flat_floor(200, 0), k=30, rng=0)  # a floor z = 0 with 1 mm noise
    >>> rn.normals.shape, rn.inliers.shape, rn.k, bool(np.nanmedian(rn.noise) < 0.002)
    ((200, 3), (200,), 30, True)
    """

    normals: np.ndarray
    inliers: np.ndarray
    noise: np.ndarray
    k: int
    iterations: int
    threshold: float | None
    n_duplicates: int = 0

    def __repr__(self) -> str:
        return f"RobustNormals({len(self.inliers)} points, k = {self.k}, {self.iterations} hypotheses)"

    def _report(self):
        rows = [
            ("points", str(len(self.inliers))),
            ("k / hypotheses", f"{self.k} / {self.iterations}"),
            ("inlier threshold", fmt(self.threshold, 4, "m") if self.threshold else "LMedS scale per point"),
            ("inlier share median", fmt(np.median(self.inliers) / self.k, 3)),
            ("noise median (inliers)", fmt(np.nanmedian(self.noise), 4, "m")),
        ]
        return "Robust normals (RANSAC planes)", [("", rows)]


def robust_normals(
    points,
    k: int = 30,
    threshold: float | None = None,
    *,
    iterations: int | None = None,
    outlier_ratio: float = 0.5,
    p: float = 0.99,
    orient: str = "up",
    viewpoint=None,
    at=None,
    duplicates: str = "merge",
    chunk_size: int = 5_000,
    rng=None,
) -> RobustNormals:
    """Normals robust to outliers inside the neighbourhood: RANSAC planes, batched over all points.

    For every neighbourhood, ``iterations`` random triples of neighbours give plane
    hypotheses (eq. 9); each is scored on all k neighbours; the best plane's
    inliers are refitted by PCA (eq. 1-4).

    Parameters
    ----------
    k : int
        Neighbours including the point.
    threshold : float, optional
        Inlier distance to the plane (metres); the best plane has the most inliers
        (RANSAC). If None, the best plane has the least median squared distance (LMedS,
        no threshold needed, breakdown point 50 %), and inliers lie within
        2.5 s0 with Rousseeuw's scale s0 = 1.4826 (1 + 5 / (k - 3)) sqrt(median r^2).
    iterations : int, optional
        Hypotheses per neighbourhood; default from ``outlier_ratio`` and ``p``:
        log(1 - p) / log(1 - (1 - outlier_ratio)^3).
    outlier_ratio : float
        Expected share of outliers in a neighbourhood, for the default ``iterations``.
    p : float
        Probability that at least one outlier-free triple is drawn per neighbourhood (eq. 27),
        as in :func:`labkit.ransac.ransac_sphere`.
    at : array_like of int, optional
        Only at these points (neighbours from the whole cloud).
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.
    rng : int or numpy.random.Generator, optional

    References
    ----------
    .. [1] Notebook 04, section 10, eq. 9 and eqs. 1-4; the registration study, step 4 (normals robust by RANSAC,
       tested with several radii).
    .. [2] M. A. Fischler, R. C. Bolles (1981): Random sample consensus: a paradigm for model fitting
       with applications to image analysis and automated cartography. Communications of the ACM
       24(6), 381-395, doi:10.1145/358669.358692.
    .. [3] P. J. Rousseeuw, A. M. Leroy (1987): Robust Regression and Outlier Detection. Wiley, New
       York, p. 202 (LMedS scale).

    Examples
    --------
    >>> from labkit.synthetic import flat_floor
    >>> floor = flat_floor(200, 0)  # z = 0, 1 mm noise
    >>> floor[:20, 2] += 0.05  # 10 % gross errors, 5 cm above the floor
    >>> rn = robust_normals(floor, k=30, rng=0)
    >>> from labkit.features import normals
    >>> pca = normals(floor, k=30)  # least squares: tilted near the outliers
    >>> round(float(rn.normals[20:, 2].min()), 3), round(float(pca[20:, 2].min()), 3)  # n_z of the floor points
    (1.0, 0.996)
    """
    local, origin = reduced(points)
    k, _ = check_scale(k, None, len(local))
    if threshold is not None:
        threshold = positive(threshold, "threshold")
    T = _iterations(iterations, outlier_ratio, p)
    at = check_at(at, len(local))
    here = local if at is None else local[at]
    view = check_orientation(orient, viewpoint, len(here))
    rng = as_rng(rng)
    plan = SearchPlan(local, at, check_duplicates(duplicates))
    if plan.tree.n < k:
        raise LabkitError(f"robust_normals needs k = {k} distinct points, the cloud has {plan.tree.n}")
    n = plan.n_out
    nrm, inl, noise = np.empty((n, 3)), np.empty(n, dtype=np.intp), np.empty(n)
    pts = plan.points

    def work(rows, per_scale, chunk_rng):
        X = pts[per_scale[0][1]]
        X = X - X[:, :1]  # (c, k, 3) relative to the point itself, for well-conditioned residuals
        w = _best_plane_inliers(X, T, threshold, chunk_rng)  # (c, k) bool
        _, C = masked_covariances(X, w)
        lam, vec = sorted_eigh(C)
        m = w.sum(axis=1)
        nrm[rows], inl[rows], noise[rows] = vec[:, :, 2], m, plane_noise(lam[:, 2], m)

    run_chunks(plan, [(k, None)], check_chunk_size(chunk_size), work, rng=rng)
    nrm, inl, noise = plan.out(nrm), plan.out(inl), plan.out(noise)
    normals = orient_normals(nrm, here, orient, view, origin)
    return RobustNormals(normals, inl, noise, k, T, threshold, plan.n_duplicates)


def _iterations(iterations, outlier_ratio, p) -> int:
    if iterations is not None:
        if not isinstance(iterations, numbers.Integral) or iterations < 1:
            raise LabkitError(f"iterations must be an integer >= 1, got {iterations!r}")
        return int(iterations)
    eps = probability(outlier_ratio, "outlier_ratio")  # in (0, 1): T is finite
    return required_iterations(eps, probability(p, "p"), s=3)  # eq. 27 with 3-point planes


def _best_plane_inliers(X, T, threshold, rng) -> np.ndarray:
    """Inlier mask (c, k) of the best of T three-point planes per neighbourhood (eq. 9)."""
    c, k, _ = X.shape
    tri = _random_triples(rng, (c, T), k)  # (c, T, 3) distinct indices
    P = X[np.arange(c)[:, None, None], tri]  # (c, T, 3 points, 3)
    nrm = np.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0])  # (eq. 9)
    length = np.linalg.norm(nrm, axis=-1)
    ok = length > 1e-12 * np.max(length, axis=1, keepdims=True) + 1e-300
    nrm = nrm / np.where(ok, length, 1.0)[..., None]
    r = np.matmul(nrm, X.transpose(0, 2, 1)) - np.einsum("ctd,ctd->ct", nrm, P[:, :, 0])[..., None]  # (c, T, k)
    r2 = r * r
    if threshold is not None:
        score = np.where(ok, -(r2 < threshold**2).sum(axis=2), 1)  # most inliers
    else:
        h = min(k // 2 + 2, k) - 1  # LMedS order statistic for a 3-parameter model
        score = np.where(ok, np.partition(r2, h, axis=2)[:, :, h], np.inf)  # least median of squares
    best = np.argmin(score, axis=1)
    r2_best = r2[np.arange(c), best]  # (c, k)
    if threshold is not None:
        return r2_best < threshold**2
    s0 = MAD_TO_SIGMA * (1 + 5 / max(k - 3, 1)) * np.sqrt(np.median(r2_best, axis=1, keepdims=True))
    spread = np.sqrt(((X - X.mean(axis=1, keepdims=True)) ** 2).sum(axis=2).mean(axis=1, keepdims=True))
    s0 = np.maximum(s0, 1e-9 * spread)  # noise-free planes: a scale of zero keeps only rounding
    return r2_best <= (2.5 * s0) ** 2


def _random_triples(rng, shape, k) -> np.ndarray:
    """Three distinct integers in [0, k) for every entry of ``shape`` (sorted, without loops)."""
    a = rng.integers(0, k, shape)
    b = rng.integers(0, k - 1, shape)
    c = rng.integers(0, k - 2, shape)
    b = b + (b >= a)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c = c + (c >= lo)
    c = c + (c >= hi)
    return np.stack([a, b, c], axis=-1)


