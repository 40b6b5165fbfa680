"""Local geometry of point clouds by PCA of neighbourhoods (seed 003, step 4; notebook 04).

For every point p_i the m points of its neighbourhood (k nearest neighbours, or
all points within a radius) are reduced to their centroid and summarised by the
3x3 covariance matrix. Its sorted eigen decomposition gives the normal (the
eigenvector of the smallest eigenvalue), the local noise (the spread along the
normal) and the eigenvalue features used to select and weight correspondences.

Notation (notebook 04):

- (eq. 1) centroid           p_bar = 1/m sum_j p_j
- (eq. 2) covariance         C = 1/m sum_j (p_j - p_bar)(p_j - p_bar)^T
- (eq. 3) eigen decomposition C = V diag(l1, l2, l3) V^T with l1 >= l2 >= l3 >= 0
- (eq. 4) normal             n = v3 (eigenvector of the smallest eigenvalue)
- (eq. 5) local noise        sigma_n = sqrt(m l3 / (m - 3)) (redundancy m - 3 of a fitted plane)
- (eq. 6-8) eigenvalue features on e_i = l_i / (l1 + l2 + l3), see :func:`eigen_features`
- (eq. 9) plane through three points n = (p2 - p1) x (p3 - p1) (robust normals)

The seed warns that ``np.linalg.eig`` does not sort its eigenvalues; this module
uses an eigh (symmetric matrices: real, ascending; ``labkit._eigh3.eigh3``, the
same decomposition as ``np.linalg.eigh`` compiled for stacks of 3x3 matrices) and
reverses the order once, in :func:`_sorted_eigh`.

The kd-tree (``labkit._kdtree``, compiled): on the real TLS scan (523,000
points, clustered density) scipy's ``cKDTree`` query was 85-90 % of the time of
:func:`normals`. The compiled tree merges exact duplicates while it is built
(issue 16: a copy is not a second observation of the surface; they share a leaf,
so finding them costs O(leafsize^2) per leaf) and answers the self-queries of the
local PCA directly on its leaf-ordered points. What mattered most, with either
tree, was the ORDER of the queries: asking in the tree's own leaf order (earlier
measurement with cKDTree: 5.4-6.2 s down to 1.7-2.6 s at 10^6 points) keeps the
visited leaves in cache. Every search here walks the points in leaf order, chunk
by chunk, and each chunk writes its own output rows.

Degenerate neighbourhoods (fewer than 3 distinct points, or all on one line) do
not determine a plane: their normal is NaN and ``LocalPCA.valid`` is False.
"""

from __future__ import annotations

import itertools
import numbers
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ._checks import as_points, as_rng, choice, positive, probability
from ._eigh3 import HAVE_NUMBA, eigh3
from ._kdtree import KDTree

if HAVE_NUMBA:
    import numba

    _njit_cov = numba.njit(cache=True, nogil=True)
else:  # pragma: no cover - numpy route in _covariances
    def _njit_cov(f):
        return f
from ._frame import local_origin, reduce
from ._report import ReportMixin, fmt
from .errors import LabkitError
from .progress import progress_steps

CHUNK_SIZE = 20_000  # points per chunk (measured: 25 % less CPU than 100k, whose 50 MB temporaries
#                      always come from fresh mmap pages; about 10 MB of temporaries per chunk at k = 20)
LEAFSIZE = 16  # cKDTree of the radius searches
DUPLICATES = ("merge", "keep")
ORIENTATIONS = ("up", "viewpoint", "none")


# --------------------------------------------------------------------------- neighbourhoods


@dataclass(frozen=True, eq=False, repr=False)
class Neighbourhoods(ReportMixin):
    """Neighbour indices of every point in compressed rows: point i owns ``indices[offsets[i]:offsets[i+1]]``.

    kNN neighbourhoods include the point itself and are sorted by distance.
    """

    indices: np.ndarray
    offsets: np.ndarray
    k: int | None
    radius: float | None

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __repr__(self) -> str:
        return f"Neighbourhoods({len(self)} points, {_scale_text(self.k, self.radius)})"

    def __getitem__(self, i: int) -> np.ndarray:
        return self.indices[self.offsets[i] : self.offsets[i + 1]]

    @property
    def counts(self) -> np.ndarray:
        """Number of neighbours m of every point, shape (n,)."""
        return np.diff(self.offsets)

    def dense(self) -> np.ndarray:
        """Indices as an (n, m) array; only when every point has the same m (always for kNN)."""
        counts = self.counts
        if len(counts) and (counts != counts[0]).any():
            raise LabkitError("radius neighbourhoods have different sizes; use indices/offsets")
        return self.indices.reshape(len(self), -1)

    def _report(self):
        c = self.counts
        rows = [("points", str(len(self))), ("search", _scale_text(self.k, self.radius))]
        if len(c):
            rows.append(("neighbours min / median / max", f"{c.min()} / {np.median(c):.0f} / {c.max()}"))
        return "Neighbourhoods", [("", rows)]


def neighbourhoods(points, k: int | None = None, radius: float | None = None, *, chunk_size: int = CHUNK_SIZE):
    """The k nearest neighbours (including the point) or all points within ``radius`` of every point.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
    k : int, optional
        Number of neighbours including the point itself, 3 <= k <= n.
    radius : float, optional
        Search radius in metres (3D ball). Give exactly one of ``k`` and ``radius``.

    Returns
    -------
    Neighbourhoods
    """
    local, _ = _reduced(points)
    k, radius = _check_scale(k, radius, len(local))
    found = []  # (rows, counts, flat) per chunk, in any order
    plan = _Plan(local, merge=False)  # indices of the input points, duplicates included
    to_input = plan.tree.indices  # leaf position -> input row

    def work(rows, per_scale, _):
        counts, flat = per_scale[0]
        found.append((rows, counts, to_input[flat.reshape(-1)]))

    _run_chunks(plan, [(k, radius)], _check_chunk(chunk_size), work)
    rows, counts_leaf, flat = (np.concatenate(parts) for parts in zip(*found))
    # move every point's block from leaf order to input order
    counts = np.empty_like(counts_leaf)
    counts[rows] = counts_leaf
    offsets = np.concatenate([[0], np.cumsum(counts)])
    src_start = np.concatenate([[0], np.cumsum(counts_leaf)[:-1]])
    inv = np.empty_like(rows)
    inv[rows] = np.arange(len(rows))
    shift = src_start[inv] - offsets[:-1]  # per input point: source block start - target start
    indices = flat[np.arange(offsets[-1]) + np.repeat(shift, counts)]
    return Neighbourhoods(indices, offsets, k, radius)


# --------------------------------------------------------------------------- local PCA


@dataclass(frozen=True, eq=False, repr=False)
class LocalPCA(ReportMixin):
    """Result of :func:`local_pca`: per point eigenvalues, eigenvectors, normal and centroid.

    Attributes
    ----------
    eigenvalues : ndarray (n, 3)
        l1 >= l2 >= l3 >= 0 of the covariance (eq. 2-3), m^2.
    eigenvectors : ndarray (n, 3, 3)
        Column j belongs to ``eigenvalues[:, j]``; column 2 equals ``normals``.
    normals : ndarray (n, 3)
        Unit normals (eq. 4), oriented as requested.
    centroids : ndarray (n, 3)
        Neighbourhood centroids (eq. 1) in the input frame.
    counts : ndarray (n,)
        Number of neighbours m (including the point), distinct points when duplicates are merged.
    k, radius : search used.
    n_duplicates : int
        Input points that were exact copies of another point and were merged into it
        before the PCA (``duplicates='merge'``); they get the result of their kept copy.
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    normals: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray
    k: int | None
    radius: float | None
    n_duplicates: int = 0

    def __repr__(self) -> str:
        return f"LocalPCA({len(self.counts)} points, {_scale_text(self.k, self.radius)})"

    @property
    def noise(self) -> np.ndarray:
        """Local noise sigma_n (eq. 5), metres; NaN where m <= 3 or the normal is undetermined."""
        return np.where(self.valid, _noise(self.eigenvalues[:, 2], self.counts), np.nan)

    @property
    def features(self) -> "EigenFeatures":
        """Eigenvalue features (eq. 6-8) of every neighbourhood."""
        return eigen_features(self.eigenvalues)

    @property
    def valid(self) -> np.ndarray:
        """True where the normal is determined: m >= 3 and the neighbourhood is not a line or a point.

        Where False the normal (and eigenvector column 2) is NaN.
        """
        return _determined(self.eigenvalues, self.counts)

    @property
    def verticality(self) -> np.ndarray:
        """1 - |n_z|: 0 for horizontal surfaces, 1 for walls."""
        return 1.0 - np.abs(self.normals[:, 2])

    def _report(self):
        noise, f = self.noise, self.features
        rows = [
            ("points", str(len(self.counts))),
            ("search", _scale_text(self.k, self.radius)),
            ("neighbours median", f"{np.median(self.counts):.0f}"),
            ("normal undetermined", str(int((~self.valid).sum()))),
            ("exact duplicates merged", str(self.n_duplicates)),
            ("local noise median", fmt(np.nanmedian(noise) if np.isfinite(noise).any() else np.nan, 4, "m")),
        ]
        rows += [(f"{name} median", fmt(np.nanmedian(v), 3)) for name, v in f.items() if np.isfinite(v).any()]
        return "Local PCA", [("", rows)]


def local_pca(
    points,
    k: int | None = 20,
    radius: float | None = None,
    *,
    orient: str = "up",
    viewpoint=None,
    at=None,
    duplicates: str = "merge",
    chunk_size: int = CHUNK_SIZE,
    progress=False,
) -> LocalPCA:
    """PCA of the neighbourhood of every point (eq. 1-4), vectorized and chunked.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        UTM-sized coordinates are fine: the algebra runs on a local origin.
    k : int, optional
        Nearest neighbours including the point (3 <= k <= n). Ignored if ``radius`` is given.
    radius : float, optional
        Ball radius in metres instead of kNN; points with fewer than 3 neighbours get NaN.
    orient : {'up', 'viewpoint', 'none'}
        'up': n_z >= 0 (ALS); 'viewpoint': toward ``viewpoint`` (3,) or per point (n, 3) (TLS
        scanner position, ALS trajectory); 'none': the sign eigh returns.
    at : array_like of int, optional
        Compute only at these points (neighbours still come from the whole cloud); the
        results then have ``len(at)`` rows and a per-point viewpoint has shape (len(at), 3).
    duplicates : {'merge', 'keep'}
        'merge' (default): exact duplicates (identical coordinates) count once, so that
        k means k distinct points; a duplicate is a second copy, not a second observation
        of the surface, and copies bias the plane toward themselves (issue 16). The
        number merged is ``n_duplicates``. 'keep': every row counts.
    chunk_size : int
        Points per chunk; memory grows with chunk_size * k, not with n * k.
    progress : bool, "bar", "lines" or callable
        Report the chunks done (see :mod:`labkit.progress`); default silent.

    Returns
    -------
    LocalPCA
        Where the neighbourhood is degenerate (fewer than 3 distinct points, all on one
        line) the normal is NaN and ``valid`` is False.

    Raises
    ------
    LabkitError
        Bad points (NaN, wrong shape), k < 3 or k > n, radius <= 0, bad orientation.
    """
    # Reduce to a local origin and check the arguments
    local, origin = _reduced(points)
    k, radius = _check_scale(k, radius, len(local))
    at = _check_at(at, len(local))
    here = local if at is None else local[at]  # the points that get a PCA
    view = _check_orientation(orient, viewpoint, len(here))
    merge = _check_duplicates(duplicates)
    # Exact duplicates merged into one point (issue 16), kd-tree, output rows
    plan = _Plan(local, at, merge)
    # Per chunk (in leaf order): neighbours, centroid, covariance, sorted eigh
    n = plan.n_out
    lam, vec = np.empty((n, 3)), np.empty((n, 3, 3))
    cen, counts = np.empty((n, 3)), np.empty(n, dtype=np.intp)
    pts = plan.points
    cols = pts.T.copy()  # coordinate columns: contiguous gathers (see _covariances)

    def work(rows, per_scale, _):
        seg_counts, flat = per_scale[0]
        c, C = _covariances(pts, seg_counts, flat, cols)
        lam[rows], vec[rows] = _sorted_eigh(C)
        cen[rows], counts[rows] = c, seg_counts

    with progress_steps(progress, plan.n_query, "normals", "pts") as step:
        _run_chunks(plan, [(k, radius)], _check_chunk(chunk_size), work, step=step)
    lam, vec, cen, counts = plan.out(lam), plan.out(vec), plan.out(cen), plan.out(counts)
    # Degenerate neighbourhoods (a point, a line) have no normal: NaN, valid=False
    _undetermined(lam, vec, counts)
    # Orient the normals; results in the input frame
    normals = _orient(vec[:, :, 2], here, orient, view, origin)
    vec[:, :, 2] = normals
    return LocalPCA(lam, vec, normals, cen + origin, counts, k, radius, plan.n_duplicates)


def normals(
    points, k: int = 20, orient: str = "up", viewpoint=None, *, radius=None, at=None, duplicates="merge",
    chunk_size=CHUNK_SIZE, progress=False,
):
    """Unit normals (n, 3): eigenvector of the smallest eigenvalue of each neighbourhood (eq. 4).

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
    k : int
        Neighbours including the point itself (3 <= k <= n).
    orient : {'up', 'viewpoint', 'none'}
        'up' gives n_z >= 0 (ALS convention); 'viewpoint' points the normals toward
        ``viewpoint``; 'none' leaves eigh's arbitrary sign.
    viewpoint : array_like (3,) or (n, 3), optional
        Sensor position(s) in the frame of ``points``; only with orient='viewpoint'.
    radius : float, optional
        Radius neighbourhood instead of kNN.
    at : array_like of int, optional
        Only at these points (neighbours from the whole cloud); shape (len(at), 3).
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.
    progress : bool, "bar", "lines" or callable
        Report the chunks done (see :mod:`labkit.progress`); default silent.

    Returns
    -------
    ndarray (n, 3)
        NaN rows where the neighbourhood is degenerate (a point or a line).

    See Also
    --------
    local_pca : eigenvalues, centroids and counts as well.
    """
    pca = local_pca(points, k, radius, orient=orient, viewpoint=viewpoint, at=at, duplicates=duplicates,
                    chunk_size=chunk_size, progress=progress)
    return pca.normals


def local_noise(points, k: int = 20, radius: float | None = None, *, chunk_size: int = CHUNK_SIZE) -> np.ndarray:
    """Local noise sigma_n = sqrt(m l3 / (m - 3)) (eq. 5): spread of the neighbourhood along its normal, metres.

    l3 is the mean squared orthogonal residual of the best-fitting plane through the
    m neighbours; a plane has u = 3 parameters (two angles, one distance), so the
    redundancy is m - 3. ``points`` may also be a :class:`LocalPCA` (no new search).
    """
    pca = points if isinstance(points, LocalPCA) else local_pca(points, k, radius, orient="none", chunk_size=chunk_size)
    return pca.noise


# --------------------------------------------------------------------------- eigenvalue features


@dataclass(frozen=True, eq=False, repr=False)
class EigenFeatures(ReportMixin):
    """Eigenvalue features on normalized eigenvalues e_i = l_i / sum(l) (eq. 6-8).

    Linearity, planarity and scattering sum to 1; the largest says whether a
    neighbourhood looks like a line, a plane or a volume. Values are NaN where all
    eigenvalues are zero (all neighbours coincide).
    """

    linearity: np.ndarray  # (e1 - e2) / e1
    planarity: np.ndarray  # (e2 - e3) / e1
    scattering: np.ndarray  # e3 / e1 (sphericity)
    omnivariance: np.ndarray  # (e1 e2 e3)^(1/3)
    anisotropy: np.ndarray  # (e1 - e3) / e1
    eigenentropy: np.ndarray  # -sum e_i ln e_i
    change_of_curvature: np.ndarray  # e3 (surface variation)
    sum: np.ndarray  # l1 + l2 + l3, m^2

    NAMES = (
        "linearity", "planarity", "scattering", "omnivariance",
        "anisotropy", "eigenentropy", "change_of_curvature", "sum",
    )  # fmt: skip

    def __repr__(self) -> str:
        return f"EigenFeatures({np.shape(self.sum)}: {', '.join(self.NAMES)})"

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.NAMES:
            raise KeyError(f"no feature {name!r}; have {', '.join(self.NAMES)}")
        return getattr(self, name)

    def keys(self):
        return self.NAMES

    def items(self):
        return [(name, getattr(self, name)) for name in self.NAMES]

    def dominant(self) -> np.ndarray:
        """0 (line), 1 (plane) or 2 (volume): the largest of linearity, planarity, scattering."""
        return np.argmax(np.stack([self.linearity, self.planarity, self.scattering], axis=-1), axis=-1)

    def _report(self):
        rows = [(name, fmt(np.nanmedian(v), 4)) for name, v in self.items() if np.isfinite(v).any()]
        return "Eigenvalue features (medians)", [("", rows)]


def eigen_features(eigenvalues) -> EigenFeatures:
    """Dimensionality features of sorted eigenvalues (..., 3), l1 >= l2 >= l3 (eq. 6-8).

    References
    ----------
    Weinmann, Jutzi, Hinz, Mallet (2015): Semantic point cloud interpretation based on
    optimal neighborhoods, relevant features and efficient classifiers. ISPRS J. 105, 286-304.
    """
    lam = np.asarray(eigenvalues, dtype=np.float64)
    if lam.shape[-1:] != (3,):
        raise LabkitError(f"eigenvalues must have shape (..., 3), got {lam.shape}")
    if np.any(np.diff(lam, axis=-1) > 1e-12 * np.abs(lam[..., :1]) + 1e-300):
        raise LabkitError("eigenvalues must be sorted in descending order (l1 >= l2 >= l3)")
    total = lam.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.clip(lam, 0.0, None) / total[..., None]  # (eq. 6)
        e1, e2, e3 = e[..., 0], e[..., 1], e[..., 2]
        plogp = np.where(e > 0, e * np.log(np.where(e > 0, e, 1.0)), 0.0)
        return EigenFeatures(
            linearity=(e1 - e2) / e1,  # (eq. 7)
            planarity=(e2 - e3) / e1,
            scattering=e3 / e1,
            omnivariance=np.cbrt(e1 * e2 * e3),  # (eq. 8)
            anisotropy=(e1 - e3) / e1,
            eigenentropy=np.where(total > 0, -plogp.sum(axis=-1), np.nan),
            change_of_curvature=e3,
            sum=total,
        )


# --------------------------------------------------------------------------- several scales


@dataclass(frozen=True, eq=False, repr=False)
class MultiScaleFeatures(ReportMixin):
    """Local PCA at several scales and, per point, the scale of least eigenentropy.

    Attributes
    ----------
    scales : tuple
        The k values (by='k') or radii (by='radius').
    eigenvalues : ndarray (n, s, 3)
        Sorted eigenvalues at every scale.
    best : ndarray (n,)
        Index into ``scales`` with minimal eigenentropy (Weinmann et al. 2015).
    pca : LocalPCA
        The PCA of every point at its chosen scale (``k``/``radius`` fields are None).
    """

    scales: tuple
    by: str
    eigenvalues: np.ndarray
    best: np.ndarray
    pca: LocalPCA

    def __repr__(self) -> str:
        return f"MultiScaleFeatures({len(self.best)} points, {self.by} = {self.scales})"

    @property
    def entropy(self) -> np.ndarray:
        """Eigenentropy (n, s) at every scale."""
        return eigen_features(self.eigenvalues).eigenentropy

    @property
    def features(self) -> EigenFeatures:
        """Eigenvalue features at each point's chosen scale."""
        return self.pca.features

    def _report(self):
        share = np.bincount(self.best, minlength=len(self.scales)) / max(len(self.best), 1)
        rows = [(f"{self.by} = {s}", f"chosen for {100 * p:.1f} % of the points") for s, p in zip(self.scales, share)]
        return "Multi-scale local PCA (least eigenentropy)", [("", rows)]


def multiscale_features(
    points, scales=(10, 20, 40), *, by: str = "k", orient: str = "up", viewpoint=None, duplicates: str = "merge",
    chunk_size: int = CHUNK_SIZE,
) -> MultiScaleFeatures:
    """Local PCA at several neighbourhood sizes; per point keep the scale of least eigenentropy.

    A small scale sees only noise, a large one mixes surfaces; the scale whose
    eigenvalues are most "decided" (least eigenentropy, eq. 8) is kept per point.
    For ``by='k'`` a single search with the largest k serves all scales (kNN
    neighbourhoods are nested).

    Parameters
    ----------
    scales : sequence of int (by='k') or float (by='radius')
    by : {'k', 'radius'}
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.
    """
    local, origin = _reduced(points)
    choice(by, ("k", "radius"), "by")
    scales = tuple(sorted(scales))
    if not scales:
        raise LabkitError("scales must contain at least one k or radius")
    checked = [_check_scale(s, None, len(local)) if by == "k" else _check_scale(None, s, len(local)) for s in scales]
    view = _check_orientation(orient, viewpoint, len(local))
    plan = _Plan(local, None, _check_duplicates(duplicates))  # exact duplicates merged (issue 16)
    n, s = plan.n_out, len(scales)
    lam_all = np.empty((n, s, 3))
    vec, cen, counts = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty(n, dtype=np.intp)
    best = np.empty(n, dtype=np.intp)
    pts = plan.points
    cols = pts.T.copy()

    def work(rows, per_scale, _):
        # per scale: eigenvalues; keep the eigenvectors of the least-entropy scale
        results = [(_covariances(pts, c, f, cols), c) for c, f in per_scale]
        eig = [_sorted_eigh(C) for (_, C), _ in results]
        lam_all[rows] = np.stack([lam for lam, _ in eig], axis=1)
        h = eigen_features(lam_all[rows]).eigenentropy
        b = np.argmin(np.where(np.isfinite(h), h, np.inf), axis=1)
        pick = np.arange(len(rows))
        best[rows] = b
        vec[rows] = np.stack([v for _, v in eig], axis=1)[pick, b]
        cen[rows] = np.stack([c for (c, _), _ in results], axis=1)[pick, b]
        counts[rows] = np.stack([m for _, m in results], axis=1)[pick, b]

    _run_chunks(plan, checked, _check_chunk(chunk_size), work)
    lam_all, best, vec, cen, counts = (plan.out(a) for a in (lam_all, best, vec, cen, counts))
    lam = lam_all[np.arange(len(local)), best]
    _undetermined(lam, vec, counts)
    normals = _orient(vec[:, :, 2], local, orient, view, origin)
    vec[:, :, 2] = normals
    pca = LocalPCA(lam, vec, normals, cen + origin, counts, None, None, plan.n_duplicates)
    return MultiScaleFeatures(scales, by, lam_all, best, pca)


# --------------------------------------------------------------------------- robust normals


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
    confidence: float = 0.99,
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
        Hypotheses per neighbourhood; default from ``outlier_ratio`` and ``confidence``:
        log(1 - confidence) / log(1 - (1 - outlier_ratio)^3).
    at : array_like of int, optional
        Only at these points (neighbours from the whole cloud).
    duplicates : {'merge', 'keep'}
        Exact duplicates count once (default), see :func:`local_pca`.
    rng : int or numpy.random.Generator, optional

    References
    ----------
    Fischler, Bolles (1981), Comm. ACM 24(6): 381-395. Rousseeuw, Leroy (1987):
    Robust Regression and Outlier Detection, Wiley, p. 202 (LMedS scale).
    """
    local, origin = _reduced(points)
    k, _ = _check_scale(k, None, len(local))
    if threshold is not None:
        threshold = positive(threshold, "threshold")
    T = _iterations(iterations, outlier_ratio, confidence)
    at = _check_at(at, len(local))
    here = local if at is None else local[at]
    view = _check_orientation(orient, viewpoint, len(here))
    rng = as_rng(rng)
    plan = _Plan(local, at, _check_duplicates(duplicates))
    if plan.tree.n < k:
        raise LabkitError(f"robust_normals needs k = {k} distinct points, the cloud has {plan.tree.n}")
    n = plan.n_out
    nrm, inl, noise = np.empty((n, 3)), np.empty(n, dtype=np.intp), np.empty(n)
    pts = plan.points

    def work(rows, per_scale, chunk_rng):
        X = pts[per_scale[0][1]]
        X = X - X[:, :1]  # (c, k, 3) relative to the point itself, for well-conditioned residuals
        w = _best_plane_inliers(X, T, threshold, chunk_rng)  # (c, k) bool
        _, C = _weighted_covariances(X, w)
        lam, vec = _sorted_eigh(C)
        m = w.sum(axis=1)
        nrm[rows], inl[rows], noise[rows] = vec[:, :, 2], m, _noise(lam[:, 2], m)

    _run_chunks(plan, [(k, None)], _check_chunk(chunk_size), work, rng=rng)
    nrm, inl, noise = plan.out(nrm), plan.out(inl), plan.out(noise)
    normals = _orient(nrm, here, orient, view, origin)
    return RobustNormals(normals, inl, noise, k, T, threshold, plan.n_duplicates)


def _iterations(iterations, outlier_ratio, confidence) -> int:
    if iterations is not None:
        if not isinstance(iterations, numbers.Integral) or iterations < 1:
            raise LabkitError(f"iterations must be an integer >= 1, got {iterations!r}")
        return int(iterations)
    eps = probability(outlier_ratio, "outlier_ratio")
    p = probability(confidence, "confidence")
    return int(np.ceil(np.log(1 - p) / np.log(1 - (1 - eps) ** 3)))


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
    s0 = 1.4826 * (1 + 5 / max(k - 3, 1)) * np.sqrt(np.median(r2_best, axis=1, keepdims=True))
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


# --------------------------------------------------------------------------- private steps


def _scale_text(k, radius) -> str:
    if k is not None:
        return f"k = {k}"
    return f"radius = {fmt(radius, 3, 'm')}" if radius is not None else "k or radius per point (multi-scale)"


def _reduced(points):
    xyz = as_points(points, min_points=3)
    origin = local_origin(xyz)
    return reduce(xyz, origin), origin


def _check_scale(k, radius, n):
    if radius is not None:
        return None, positive(radius, "radius")
    if k is None:
        raise LabkitError("give k (number of neighbours) or radius")
    if isinstance(k, bool) or not isinstance(k, numbers.Integral):
        raise LabkitError(f"k must be an integer, got {k!r}")
    if not 3 <= k <= n:
        raise LabkitError(f"k must be between 3 and the number of points ({n}), got {k}")
    return int(k), None


def _check_at(at, n):
    """None, or a 1-D integer index array into the n points."""
    if at is None:
        return None
    idx = np.asarray(at)
    if idx.ndim == 1 and len(idx) == 0:
        raise LabkitError("at is empty: give at least one point index")
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise LabkitError(f"at must be a 1-D array of point indices, got shape {idx.shape} and dtype {idx.dtype}")
    if len(idx) == 0:
        raise LabkitError("at is empty: give at least one point index")
    if idx.min() < -n or idx.max() >= n:
        raise LabkitError(f"at contains indices outside 0..{n - 1}")
    return np.where(idx < 0, idx + n, idx).astype(np.intp)


def _check_duplicates(duplicates) -> bool:
    return choice(duplicates, DUPLICATES, "duplicates") == "merge"


def _determined(lam, counts) -> np.ndarray:
    """True where a plane is determined: m >= 3 and l2 > 1e-12 l1 (not a point, not a line).

    ``lam`` descending (n, 3). A line has l2 = 0 up to rounding, which is about
    eps^2 of l1 on reduced coordinates; 1e-12 means a width below 1e-6 of the length.
    """
    l1, l2 = lam[:, 0], lam[:, 1]
    with np.errstate(invalid="ignore"):
        return (counts >= 3) & (l2 > 1e-12 * l1) & np.isfinite(l1)


def _undetermined(lam, vec, counts) -> None:
    """NaN normals (eigenvector column 2) where :func:`_determined` is False (in place)."""
    bad = ~_determined(lam, counts)
    if bad.any():
        vec[bad, :, 2] = np.nan


def _check_chunk(chunk_size) -> int:
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, numbers.Integral) or chunk_size < 1:
        raise LabkitError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    return int(chunk_size)


def _check_orientation(orient, viewpoint, n):
    choice(orient, ORIENTATIONS, "orient")
    if orient != "viewpoint":
        if viewpoint is not None:
            raise LabkitError("viewpoint is only used with orient='viewpoint'")
        return None
    if viewpoint is None:
        raise LabkitError("orient='viewpoint' needs viewpoint: shape (3,) or (n, 3)")
    v = np.asarray(viewpoint, dtype=np.float64)
    if v.shape not in ((3,), (n, 3)) or not np.isfinite(v).all():
        raise LabkitError(f"viewpoint must be finite with shape (3,) or ({n}, 3), got {v.shape}")
    return v


class _Plan:
    """Where the PCA runs: the kd-tree (exact duplicates merged or not) and the output rows (private).

    Without ``at`` the queries are the tree's (distinct) points in leaf order and every
    chunk writes the input rows of its points (``tree.indices``); :meth:`out` then copies
    the result of each kept point to the duplicates merged into it. With ``at`` the
    queries are the requested points in leaf order and the output rows their positions
    in ``at``.
    """

    def __init__(self, local, at=None, merge=True):
        self.tree = KDTree(local, merge_duplicates=merge)
        self.points = self.tree.data  # neighbour indices refer to these (leaf order)
        self.copies = None
        rep = self.tree.representative  # leaf position of the kept copy of every input point
        if at is None:
            self.n_out, self.n_query = len(local), self.tree.n
            self.query_pos, self.order = None, None
            if self.tree.n_duplicates:
                kept = self.tree.indices[rep]
                dup = np.flatnonzero(kept != np.arange(len(local)))
                self.copies = (dup, kept[dup])
        else:
            if rep is None:
                rep = np.empty(len(local), dtype=np.intp)
                rep[self.tree.indices] = np.arange(len(local))
            self.n_out = self.n_query = len(at)
            self.query_pos = rep[at]  # leaf position of every requested point
            self.order = np.argsort(self.query_pos, kind="stable")  # positions in ``at``, in leaf order

    @property
    def n_duplicates(self) -> int:
        return self.tree.n_duplicates

    def out(self, values):
        """Per input point (or per ``at`` entry): merged copies get the result of their kept point."""
        if self.copies is not None:
            dup, kept = self.copies
            values[dup] = values[kept]
        return values


def _run_chunks(plan, scales, chunk_size, work, rng=None, step=None) -> None:
    """Call ``work(rows, per_scale, chunk_rng)`` for chunks of query points in the tree's leaf order.

    ``rows`` index the output (see :class:`_Plan`); the neighbour indices refer to
    ``plan.points``. ``per_scale`` holds ``(counts, neighbours)`` for every (k, radius)
    in ``scales``: an (c, k) index array for kNN (one search with the largest k serves
    all k, since kNN neighbourhoods are nested), a flat index array for a radius. Chunks
    run in one thread per core; the kNN kernel, gathers, matmul and eigh release the
    GIL. Every chunk writes only its own rows. With ``rng``, each chunk gets its own
    child generator (reproducible for a given chunk_size, independent of thread timing).
    ``step(n)`` (a progress reporter) hears of every finished chunk, from the calling thread.
    """
    tree = plan.tree
    n_q = plan.n_query
    threads = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    # chunks of at most chunk_size, their number a multiple of the threads so that all threads get
    # the same share (5 chunks on 2 threads would leave one thread idle for a fifth of the time)
    n_chunks = -(-n_q // max(1, chunk_size))
    n_chunks = max(1, -(-n_chunks // threads) * threads) if n_q >= threads else 1
    size = max(1, -(-n_q // n_chunks))
    starts = range(0, n_q, size)
    rngs = as_rng(rng).spawn(len(starts)) if rng is not None else [None] * len(starts)
    ball = [None]
    if any(r is not None for _, r in scales):
        ball[0] = cKDTree(plan.points, leafsize=LEAFSIZE, balanced_tree=False, compact_nodes=False)

    def job(i):
        a, b = starts[i], min(starts[i] + size, n_q)
        if plan.order is None:
            rows = tree.indices[a:b]
            q = plan.points[a:b]
        else:
            rows = plan.order[a:b]
            q = plan.points[plan.query_pos[rows]]
        work(rows, _query(tree, ball[0], q, scales), rngs[i])
        return b - a

    report = step if step is not None else (lambda n: None)
    if len(starts) == 1:
        report(job(0))
        return
    with ThreadPoolExecutor(threads) as pool:
        for n in pool.map(job, range(len(starts))):  # in order; re-raises a failure of any chunk
            report(n)


def _query(tree, ball, q, scales):
    """(counts, neighbours) of the query points q for every (k, radius) in ``scales`` (leaf positions)."""
    ks = [k for k, r in scales if r is None]
    k_max = min(max(ks), tree.n) if ks else 0  # merged duplicates may leave fewer points than k
    idx = tree._run(q, k_max, np.inf, 1)[1] if ks else None
    out = []
    for k, r in scales:
        if r is None:
            k = min(k, tree.n)
            out.append((np.full(len(q), k, dtype=np.intp), idx[:, :k]))
            continue
        lists = ball.query_ball_point(q, r, return_sorted=False)
        counts = np.fromiter(map(len, lists), dtype=np.intp, count=len(lists))
        out.append((counts, np.fromiter(itertools.chain.from_iterable(lists), dtype=np.intp, count=int(counts.sum()))))
    return out


def _covariances(local, counts, flat, cols=None):
    """Centroids (c, 3) (eq. 1) and covariances (c, 3, 3) (eq. 2) of one chunk of neighbourhoods.

    ``cols`` = ``local.T`` as a contiguous (3, n) array. For kNN the coordinates are then
    gathered per axis into contiguous (c, k) blocks and the six distinct products summed
    along k: measured 4-5x faster than a batched (3 x k) @ (k x 3) matmul on (c, k, 3).
    """
    if flat.ndim == 2:
        if cols is None:
            return _weighted_covariances(local[flat], None)  # (c, k, 3), only one chunk at a time
        if HAVE_NUMBA:
            cen, C = np.empty((len(flat), 3)), np.empty((len(flat), 3, 3))
            _knn_covariances(cols, flat, cen, C)
            return cen, C
        k = flat.shape[1]
        cen = np.empty((len(flat), 3))
        D = []
        for a in range(3):
            g = cols[a][flat]  # (c, k)
            cen[:, a] = g.mean(axis=1)  # (eq. 1)
            g -= cen[:, a, None]
            D.append(g)
        C = np.empty((len(flat), 3, 3))
        for a in range(3):
            for b in range(a, 3):
                C[:, a, b] = C[:, b, a] = np.einsum("ck,ck->c", D[a], D[b]) / k  # (eq. 2)
        return cen, C
    # ragged radius neighbourhoods: segment sums with bincount
    seg = np.repeat(np.arange(len(counts)), counts)
    m = np.maximum(counts, 1)
    X = local[flat]
    cen = np.stack([np.bincount(seg, X[:, a], len(counts)) for a in range(3)], axis=1) / m[:, None]  # (eq. 1)
    D = X - cen[seg]
    C = np.empty((len(counts), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            C[:, a, b] = C[:, b, a] = np.bincount(seg, D[:, a] * D[:, b], len(counts)) / m  # (eq. 2)
    C[counts < 3] = np.nan  # too few neighbours: no plane
    return cen, C


@_njit_cov
def _knn_covariances(cols, idx, cen, C):  # pragma: no cover - compiled
    """Compiled (eq. 1, 2) for kNN: centroid, then the mean outer product of the deviations,
    in one pass over each point's neighbours (no (c, k, 3) temporaries). Same two-pass
    arithmetic as the numpy route, so both agree to rounding."""
    m, k = idx.shape
    x, y, z = cols[0], cols[1], cols[2]
    for i in range(m):
        sx = sy = sz = 0.0
        for j in range(k):
            q = idx[i, j]
            sx += x[q]
            sy += y[q]
            sz += z[q]
        cx, cy, cz = sx / k, sy / k, sz / k
        xx = xy = xz = yy = yz = zz = 0.0
        for j in range(k):
            q = idx[i, j]
            dx, dy, dz = x[q] - cx, y[q] - cy, z[q] - cz
            xx += dx * dx
            xy += dx * dy
            xz += dx * dz
            yy += dy * dy
            yz += dy * dz
            zz += dz * dz
        cen[i, 0], cen[i, 1], cen[i, 2] = cx, cy, cz
        C[i, 0, 0], C[i, 1, 1], C[i, 2, 2] = xx / k, yy / k, zz / k
        C[i, 0, 1] = C[i, 1, 0] = xy / k
        C[i, 0, 2] = C[i, 2, 0] = xz / k
        C[i, 1, 2] = C[i, 2, 1] = yz / k


def _weighted_covariances(X, w):
    """Centroids and covariances of neighbourhoods X (c, k, 3), optionally with a 0/1 mask w (c, k)."""
    if w is None:
        cen = X.mean(axis=1)  # (eq. 1)
        D = X - cen[:, None, :]
        return cen, np.matmul(D.transpose(0, 2, 1), D) / X.shape[1]  # (eq. 2)
    wf = w.astype(np.float64)
    m = wf.sum(axis=1)
    cen = np.einsum("ck,ckd->cd", wf, X) / m[:, None]
    D = (X - cen[:, None, :]) * wf[..., None]
    return cen, np.matmul(D.transpose(0, 2, 1), D) / m[:, None, None]


def _sorted_eigh(C):
    """Eigenvalues (c, 3) descending and eigenvectors (c, 3, 3) in the same column order (eq. 3).

    ``np.linalg.eigh`` returns ascending eigenvalues of a symmetric matrix; we reverse
    once. (``np.linalg.eig`` would return them in no particular order: the seed's pitfall.)
    :func:`labkit._eigh3.eigh3` is the same decomposition compiled for stacks of 3x3
    matrices (3x faster); matrices with NaN (too few neighbours) give NaN rows.
    """
    lam, V = eigh3(C)  # ascending, like np.linalg.eigh
    return np.clip(lam[:, ::-1], 0.0, None), V[:, :, ::-1]


def _noise(l3, m):
    """sigma_n = sqrt(m l3 / (m - 3)) (eq. 5); NaN for m <= 3."""
    m = np.asarray(m, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(m > 3, np.sqrt(m * l3 / (m - 3)), np.nan)


def _orient(nrm, local, orient, view, origin):
    """Flip normals to n_z >= 0 ('up') or to n . (viewpoint - p) >= 0 ('viewpoint')."""
    if orient == "none":
        return np.ascontiguousarray(nrm)
    if orient == "up":
        flip = nrm[:, 2] < 0
    else:
        flip = np.einsum("nd,nd->n", nrm, (view - origin) - local) < 0
    return np.where(flip[:, None], -nrm, nrm)
