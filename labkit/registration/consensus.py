"""Maximum consensus over translations and the consensus cube (notebook 06, seed 003 step 3).

For a translation t the consensus is (eq. 6.1, 6.2)

    C(t) = sum_p w_p * [ exists q in target: pair (p, q) consistent at t ]

with "consistent" meaning |p + t - q| < eps (point-to-point) or
|n_q . (p + t - q)| < eps and |p + t - q| < radius (point-to-plane, eq. 6.3,
6.4), optionally with the angle between the normals of p and q below
``max_angle`` (eq. 6.4a). Each source point counts at most once per t. Normals
that the local PCA cannot determine (identical or collinear neighbours) are
dropped, never used.

Only the difference vectors d = q - p with d inside the search window (grown
by the search radius) can ever be consistent, so both the cube and the branch
and bound work on this list of pairs (:func:`_pairs`), never on 8 million
nearest-neighbour searches.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import chain

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .._checks import as_points, choice, positive
from .._frame import local_origin, reduce
from .._report import ReportMixin, fmt
from ..errors import DegenerateGeometryError, EmptyRegionError, LabkitError
from . import _consensus_kernels as K

CRITERIA = ("point_to_plane", "point_to_point")
MAX_CELLS = 100_000_000
PAIR_BUDGET = 1_000_000  # candidate pairs of max_consensus before the search target is thinned
EPS_RANGE = (0.005, 0.10)  # limits (m) of the tolerance derived from the local noise
AXES = ("X", "Y", "Z")


# --------------------------------------------------------------------------- result types
@dataclass(frozen=True, eq=False)
class PeakShape(ReportMixin):
    """Which translation directions the consensus peak determines.

    The cells whose count lies within ``level`` of the peak (relative to the
    peak-to-median contrast) and that are connected to the peak form the *top
    region*; a principal component analysis of their positions tells whether it
    is a point, a ridge (one free direction) or a plane (two free directions).
    The *summit* is the part of the top region within the counting noise of the
    peak (3 sqrt(peak) for counts); its centroid is the best grid estimate of the
    translation, because the consensus of an eps-tolerance is flat-topped and
    its single highest cell wanders over the plateau by chance.

    Attributes
    ----------
    kind : str
        'point', 'ridge', 'plane' or 'flat' (no peak at all: undetermined).
    spreads : ndarray (3,)
        Standard deviations (m) of the top region along its principal directions, ascending.
    directions : ndarray (3, 3)
        The principal directions in the columns, in the order of ``spreads``.
    free : ndarray of bool (3,)
        Per principal direction: spread at least ``free_spread`` (not determined).
    axis_constrained : ndarray of bool (3,)
        Per axis X, Y, Z: the free directions have less than half their weight on it.
    contrast : float
        (peak - median) / peak: near 0 for a consensus that barely distinguishes shifts.
    n_top : int
        Number of cells in the top region.
    free_spread : float
        Threshold (m) on the spread that separates determined from free directions.
    summit : ndarray (3,)
        Centroid (m) of the summit: the cells connected to the peak within the counting noise of it.
    n_summit : int
        Number of cells in the summit.
    """

    kind: str
    spreads: np.ndarray
    directions: np.ndarray
    free: np.ndarray
    axis_constrained: np.ndarray
    contrast: float
    n_top: int
    free_spread: float
    summit: np.ndarray
    n_summit: int

    @property
    def constrained_axes(self) -> tuple:
        """Names of the axes the peak determines, e.g. ('X', 'Z')."""
        return tuple(a for a, ok in zip(AXES, self.axis_constrained) if ok)

    def describe(self) -> str:
        """One line in words: the shape and the translation direction(s) it leaves free.

        A free direction within 10 degrees of a coordinate axis is named by that axis ("free along ty"),
        otherwise by its azimuth and elevation; a plane of free directions by its normal.
        """
        if self.kind == "flat":
            return "flat: no peak, the translation is undetermined"
        free = [np.asarray(self.directions)[:, i] for i in np.flatnonzero(self.free)]
        if not free:
            return f"{self.kind}: all three directions determined"
        if len(free) == 1:
            return f"{self.kind}: free along {_direction_words(free[0])}"
        if len(free) == 2:
            return f"{self.kind}: free in the plane normal to {_direction_words(np.cross(free[0], free[1]))}"
        return f"{self.kind}: free in all directions"

    def _report(self):
        rows = [
            ("shape", self.describe()),
            ("constrained axes", ", ".join(self.constrained_axes) or "none"),
            ("spreads of the top region", fmt(self.spreads, 4, "m")),
            ("contrast (peak - median) / peak", fmt(self.contrast, 3)),
            ("cells in the top region / summit", f"{self.n_top} / {self.n_summit}"),
        ]
        return "Consensus peak", [("", rows)]


def _direction_words(v) -> str:
    """A unit direction in words: the axis it is within 10 degrees of, else azimuth and elevation."""
    v = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    a = int(np.argmax(np.abs(v)))
    angle = float(np.degrees(np.arccos(min(1.0, abs(v[a])))))
    if angle <= 10.0:
        return f"t{'xyz'[a]}" + (f" (within {angle:.0f} deg)" if angle >= 1.0 else "")
    v = v if v[2] >= 0 else -v
    azimuth = float(np.degrees(np.arctan2(v[1], v[0])))
    elevation = float(np.degrees(np.arcsin(np.clip(v[2], -1.0, 1.0))))
    return f"a direction at azimuth {azimuth:.0f} deg, elevation {elevation:.0f} deg"


@dataclass(frozen=True, eq=False)
class ConsensusCube(ReportMixin):
    """The consensus C(t) on a regular grid of translations (eq. 6.5).

    Attributes
    ----------
    counts : ndarray (nx, ny, nz)
        Consensus per cell: number of source points (int) or their weight sum (float).
    axes : tuple of three ndarrays
        Translations (m) along X, Y, Z; ``counts[i, j, k]`` belongs to
        ``(axes[0][i], axes[1][j], axes[2][k])``.
    best_translation : ndarray (3,)
        Centre of the summit of the peak (see :class:`PeakShape`), NaN in every axis the
        peak does not determine.
    argmax_translation : ndarray (3,)
        Translation of the highest cell (the first one on a plateau), without that caution.
    best_count : float
        The highest consensus.
    peak : PeakShape
        Shape of the peak: which directions are constrained.
    criterion : str
        'point_to_plane' or 'point_to_point'.
    eps : float
        Distance tolerance (m).
    radius : float
        Search radius (m) around target points (point-to-plane); eps for point-to-point.
    max_angle : float or None
        Largest angle (degrees) between source and target normals.
    n_source, n_pairs : int
        Source points and candidate pairs considered.
    step : float
        Grid step (m).
    kernel : str
        'numba' or 'numpy'.
    runtime_s : float
        Wall-clock time (s).
    """

    counts: np.ndarray
    axes: tuple
    best_translation: np.ndarray
    argmax_translation: np.ndarray
    best_count: float
    peak: PeakShape
    criterion: str
    eps: float
    radius: float
    max_angle: float | None
    n_source: int
    n_pairs: int
    step: float
    kernel: str
    runtime_s: float

    @property
    def peak_index(self) -> tuple:
        """Index (i, j, k) of the highest cell."""
        return tuple(int(i) for i in np.unravel_index(np.argmax(self.counts), self.counts.shape))

    @property
    def undetermined(self) -> bool:
        """True when the consensus has no peak at all."""
        return self.peak.kind == "flat"

    def count_at(self, translation) -> float:
        """Count of the cell nearest to ``translation`` (3,)."""
        idx = [int(np.clip(np.rint((t - a[0]) / self.step), 0, a.size - 1)) for t, a in zip(translation, self.axes)]
        return float(self.counts[tuple(idx)])

    def _report(self):
        shape = "x".join(str(n) for n in self.counts.shape)
        rows = [
            ("criterion", f"{self.criterion}, eps = {self.eps:.3f} m"
             + (f", radius = {self.radius:.3f} m" if self.criterion == "point_to_plane" else "")
             + (f", max angle = {self.max_angle:.1f} deg" if self.max_angle is not None else "")),
            ("grid", f"{shape} = {self.counts.size:,} translations, step {self.step * 100:.2f} cm"),
            ("range", ", ".join(f"{a}: {ax[0]:+.3f}..{ax[-1]:+.3f} m" for a, ax in zip(AXES, self.axes))),
            ("best translation", fmt(self.best_translation, 4, "m")),
            ("highest cell", fmt(self.argmax_translation, 4, "m")),
            ("best consensus", f"{self.best_count:.6g} of {self.n_source} source points"),
            ("pairs", f"{self.n_pairs:,} (kernel: {self.kernel})"),
            ("runtime", fmt(self.runtime_s, 2, "s")),
        ]
        return "Consensus cube", [("", rows)] + self.peak._report()[1]


# --------------------------------------------------------------------------- inputs
@dataclass(frozen=True, eq=False)
class _Problem:
    """Reduced coordinates, normals, weights and the candidate pairs of one registration.

    ``src`` and ``tgt`` are the points the consensus is counted on (for
    :func:`max_consensus` an even subset of the source and, for very dense targets, a
    thinned target); ``tgt_full`` is the whole reduced target, on which the
    least-squares refinement fits its local planes.
    """

    src: np.ndarray  # (n, 3) reduced source (the points that vote)
    tgt: np.ndarray  # (m, 3) reduced target of the search
    origin: np.ndarray
    w: np.ndarray  # (n,) weights
    tgt_normals: np.ndarray | None
    src_normals: np.ndarray | None
    criterion: str
    eps: float
    radius: float
    max_angle: float | None
    tgt_full: np.ndarray | None = None
    noise: float = float("nan")  # median local noise of the target (m)
    n_source: int = 0  # source points handed in
    spacing: float = float("nan")  # spacing of the voting source points (m)
    src_ref: np.ndarray | None = None  # (r, 3) reduced source points of the least-squares refinement
    w_ref: np.ndarray | None = None  # (r,) their weights


def _prepare(source, target, criterion, eps, radius, max_angle, weights, normals, normal_k, *,
             max_points=None, pair_window=None, pair_budget=PAIR_BUDGET, refine_points=None) -> _Problem:
    """Check and reduce the inputs; choose the voting points, the search target and the tolerances.

    ``max_points``: keep at most that many source points, spread evenly in space
    (:func:`even_subset`); ``refine_points``: the points of the least-squares refinement, an even
    subset of at most that many (None: the voting points). ``pair_window``: half-width (m) of the translation window
    searched; with it the target is thinned evenly until the candidate pairs fit
    ``pair_budget`` (dense TLS targets). Normals the local PCA cannot determine
    (identical or collinear neighbours) are dropped, never used.
    """
    criterion = choice(criterion, CRITERIA, "criterion")
    eps = None if eps is None else positive(eps, "eps")
    normal_k = _count(normal_k, "normal_k", 3)
    xyz_s = as_points(source, min_points=1, name="source")
    xyz_t = as_points(target, min_points=3, name="target")
    origin = local_origin(xyz_t)
    src, tgt_full = reduce(xyz_s, origin), reduce(xyz_t, origin)
    w = _weights(weights, source, len(src))
    n_src_given, n_tgt_given = (None, None) if normals is None else normals
    # Voting source points: an even subset (not random: dense parts would outvote sparse ones)
    keep_s = np.flatnonzero(w > 0)
    keep_r = None if refine_points is None else (keep_s if keep_s.size <= refine_points else (
        keep_s[even_subset(src[keep_s], refine_points)]))
    if max_points is not None and keep_s.size > max_points:
        keep_s = keep_s[even_subset(src[keep_s], max_points)]
    # Search target: the whole target, or an even thinning of it when the pairs would be too many
    keep_t = np.arange(len(tgt_full))
    if pair_window is not None:
        keep_t = _search_target(src[keep_s], tgt_full, pair_window, pair_budget)
    plane = criterion == "point_to_plane"
    n_tgt, noise = None, float("nan")
    if plane or max_angle is not None or eps is None:
        n_tgt, ok_t, sig = _normals(n_tgt_given, tgt_full, keep_t, normal_k, "target")
        noise = float(np.nanmedian(sig)) if np.isfinite(sig).any() else float("nan")
        keep_t, n_tgt = keep_t[ok_t], n_tgt[ok_t]
        if keep_t.size < 3:
            raise DegenerateGeometryError(
                "fewer than 3 target points have a determined normal (identical or collinear "
                "neighbours): the target has no surface to register on")
        if not (plane or max_angle is not None):
            n_tgt = None
    n_src = None
    if max_angle is not None:
        max_angle = positive(max_angle, "max_angle")
        n_src, ok_s, _ = _normals(n_src_given, src, keep_s, normal_k, "source")
        keep_s, n_src = keep_s[ok_s], n_src[ok_s]
        if keep_s.size == 0:
            raise DegenerateGeometryError("no source point has a determined normal for the angle test")
    tgt = tgt_full[keep_t]
    if eps is None:
        eps = _default_eps(noise)
    if plane:
        radius = _default_radius(tgt) if radius is None else positive(radius, "radius")
        radius = max(radius, eps)
    else:
        radius = eps
    spacing = _spacing(src[keep_s])
    return _Problem(src[keep_s], tgt, origin, w[keep_s], n_tgt, n_src, criterion, float(eps), float(radius),
                    max_angle, tgt_full, noise, len(src), spacing,
                    None if keep_r is None else src[keep_r], None if keep_r is None else w[keep_r])


def _count(value, name, minimum):
    """An integer >= ``minimum`` (floats that are whole numbers are accepted)."""
    try:
        val = float(value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be an integer >= {minimum}, got {value!r}") from None
    if not np.isfinite(val) or val != int(val) or val < minimum:
        raise LabkitError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(val)


def _non_negative(value, name):
    try:
        val = float(value)
    except (TypeError, ValueError):
        raise LabkitError(f"{name} must be a number >= 0, got {value!r}") from None
    if not np.isfinite(val) or val < 0:
        raise LabkitError(f"{name} must be a finite number >= 0, got {value!r}")
    return val


def even_subset(xyz, n: int) -> np.ndarray:
    """Indices of at most ``n`` points spread evenly in space (one per voxel, nearest its centre).

    The voxel edge is found by bisection on the number of occupied voxels, so dense
    parts (near a TLS scanner, overlapping strips) are thinned and sparse parts kept:
    every part of the surface gets a vote in proportion to its area, not to its density.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) <= n:
        return np.arange(len(xyz))
    lo_xyz = xyz.min(axis=0)
    span = float(np.ptp(xyz, axis=0).max()) or 1.0
    lo, hi = span / n ** (1 / 3) / 8, span  # few voxels at hi; too many at lo (a surface fills n^(2/3) of n^3)
    best = None
    for _ in range(30):
        size = np.sqrt(lo * hi)
        idx = _one_per_voxel(xyz, lo_xyz, size)
        if idx.size > n:
            lo = size
        else:
            hi, best = size, idx
            if idx.size > 0.97 * n:
                break
    return best if best is not None else _one_per_voxel(xyz, lo_xyz, hi)


def _one_per_voxel(xyz, lo, size):
    cells = np.floor((xyz - lo) / size).astype(np.int64)
    key = np.ravel_multi_index(cells.T, cells.max(axis=0) + 1)
    centre = lo + (cells + 0.5) * size
    d2 = np.einsum("ij,ij->i", xyz - centre, xyz - centre)
    order = np.lexsort((d2, key))
    first = np.flatnonzero(np.r_[True, np.diff(key[order]) != 0])
    return np.sort(order[first])


def _spacing(xyz) -> float:
    """Median distance of the points to their nearest neighbour (m)."""
    if len(xyz) < 2:
        return float("nan")
    d, _ = cKDTree(xyz).query(xyz[:: max(1, len(xyz) // 5000)], k=2, workers=-1)
    return float(np.median(d[:, 1]))


def _search_target(src, tgt, window, budget):
    """Indices of the target points the consensus is counted on.

    The candidate pairs of one source point are the target points in a cube of
    half-width ``window`` around it; their mean number, estimated on a sample of source
    points, times the number of source points must stay within ``budget``. Otherwise
    the target is thinned evenly (one point per voxel), the voxel growing with the
    square root of the excess (the pairs lie on surfaces). The window is taken 30 %
    wider than the box, for the search radius around it.
    """
    keep = np.arange(len(tgt))
    sample = src[:: max(1, len(src) // 256)]
    size = _spacing(tgt)
    for _ in range(4):
        tree = cKDTree(tgt[keep])
        per_point = tree.query_ball_point(sample, 1.3 * window, p=np.inf, return_length=True, workers=-1).mean()
        excess = per_point * len(src) / budget
        if excess <= 1.0:
            break
        size *= max(np.sqrt(excess), 1.2)
        keep = _one_per_voxel(tgt, tgt.min(axis=0), size)
    return keep


def _default_eps(noise) -> float:
    """Tolerance from the local noise: 3 sigma of a difference of two noisy points (3 sqrt(2) sigma_n)."""
    if not np.isfinite(noise):
        return 0.05
    return float(np.clip(3.0 * np.sqrt(2.0) * noise, EPS_RANGE[0], EPS_RANGE[1]))


def _weights(weights, source, n):
    if weights is None:
        return np.ones(n)
    if isinstance(weights, dict):  # weight per class code
        if "classification" not in getattr(source, "attributes", {}):
            raise LabkitError("weights given per class need a source PointCloud with a 'classification' attribute")
        cls = np.asarray(source["classification"])
        w = np.array([float(weights.get(int(c), 0.0)) for c in np.unique(cls)])
        w = w[np.searchsorted(np.unique(cls), cls)]
    else:
        w = np.array(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or not np.isfinite(w).all() or (w < 0).any():
        raise LabkitError(f"weights must be {n} finite values >= 0 (one per source point)")
    if w.sum() <= 0:
        raise LabkitError("all weights are zero: no source point can vote")
    return w


def _normals(given, xyz, at, k, name):
    """Unit normals at the points ``at``, whether they are determined, and the local noise (m)."""
    if given is not None:
        n = np.asarray(given, dtype=np.float64)
        if n.shape != xyz.shape:
            raise LabkitError(f"{name} normals must have shape {xyz.shape}, got {n.shape}")
        n = n[at]
        length = np.linalg.norm(n, axis=1)
        ok = np.isfinite(n).all(axis=1) & (length > 1e-12)
        n = np.where(ok[:, None], n / np.where(ok, length, 1.0)[:, None], np.nan)
        return n, ok, np.full(len(at), np.nan)
    from ..features import local_pca

    pca = local_pca(xyz, k=min(k, len(xyz)), orient="none", at=at)
    ok = pca.valid & np.isfinite(pca.normals).all(axis=1)
    return pca.normals, ok, np.where(ok, pca.noise, np.nan)


def _default_radius(tgt) -> float:
    """Search radius: median distance to the 4th neighbour, so a disc rarely misses the surface."""
    sample = tgt[:: max(1, len(tgt) // 20000)]
    d, _ = cKDTree(tgt).query(sample, k=min(5, len(tgt)), workers=-1)
    return float(np.median(d[:, -1]))


def _box(extent, center):
    try:
        ext = np.broadcast_to(np.asarray(extent, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise LabkitError(f"extent must be one or three numbers > 0 (m), got {extent!r}") from None
    if not np.isfinite(ext).all() or (ext <= 0).any():
        raise LabkitError(f"extent must be one or three finite numbers > 0 (m), got {extent!r}")
    try:
        c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise LabkitError(f"center must be three numbers (m), got {center!r}") from None
    if not np.isfinite(c).all():
        raise LabkitError(f"center must be three finite numbers (m), got {center!r}")
    return ext, c


def _grid(extent, step, center):
    ext, c = _box(extent, center)
    step = positive(step, "step")
    half = np.floor(ext / step + 1e-9).astype(np.int64)
    n = 2 * half + 1
    if np.prod(n.astype(float)) > MAX_CELLS:
        raise LabkitError(
            f"the grid would have {int(np.prod(n)):,} cells (> {MAX_CELLS:,}); use a larger step or a smaller extent"
        )
    return tuple(c[i] + step * np.arange(-half[i], half[i] + 1) for i in range(3)), step


def _pairs(pb: _Problem, lo, hi, reach):
    """Pairs (p, q) whose difference d = q - p lies in [lo - reach, hi + reach] (eq. 6.6).

    Returns ``ptr`` (CSR over source points), source index and d per pair, and
    the target normals per pair (or None).
    """
    tree = cKDTree(pb.tgt)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    hits = tree.query_ball_point(pb.src + mid, float(half.max() + reach) * (1 + 1e-12), p=np.inf, workers=-1)
    lens = np.fromiter(map(len, hits), dtype=np.int64, count=len(hits))
    j = np.fromiter(chain.from_iterable(hits), dtype=np.int64, count=int(lens.sum()))
    i = np.repeat(np.arange(len(pb.src)), lens)
    D = pb.tgt[j] - pb.src[i]
    keep = ((D >= lo - reach) & (D <= hi + reach)).all(axis=1) & (pb.w[i] > 0)
    if pb.max_angle is not None:  # normal angle test does not depend on t
        cos = np.abs(np.einsum("ij,ij->i", pb.src_normals[i], pb.tgt_normals[j]))
        keep &= cos > np.cos(np.radians(pb.max_angle))
    i, j, D = i[keep], j[keep], D[keep]
    if i.size == 0:
        raise EmptyRegionError(
            "no source point has a target point within the search window: the clouds do not overlap "
            "for these translations (check the frames, extent and center)"
        )
    ptr = np.concatenate(([0], np.cumsum(np.bincount(i, minlength=len(pb.src)))))
    nrm = pb.tgt_normals[j] if pb.criterion == "point_to_plane" else None
    return ptr, i, D, nrm


# --------------------------------------------------------------------------- the cube
def consensus_cube(
    source,
    target,
    extent=1.0,
    step: float = 0.01,
    criterion: str = "point_to_plane",
    eps: float | None = 0.05,
    max_angle: float | None = None,
    weights=None,
    *,
    radius: float | None = None,
    center=None,
    normals=None,
    normal_k: int = 12,
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
    criterion : {'point_to_plane', 'point_to_point'}
        Consistency test of a pair (eq. 6.3 or 6.4).
    eps : float or None
        Distance tolerance (m), > 0; None: from the local noise as in :func:`max_consensus`.
    max_angle : float, optional
        Largest angle (deg) between source and target normals for a consistent pair (eq. 6.4a):
        removes pairs between differently oriented surfaces before counting.
    weights : array_like (n,) or dict, optional
        Weight per source point, or per class code (needs ``source['classification']``).
    radius : float, optional
        Search radius (m) around target points for point-to-plane; default: the
        median distance of target points to their 5th neighbour.
    center : (3,) float, optional
        Centre of the search box (an a-priori shift); default zero.
    normals : (source_normals, target_normals), optional
        Precomputed unit normals (either may be None); otherwise PCA normals.
    normal_k : int
        Neighbours for PCA normals.
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
    """
    t0 = time.perf_counter()
    # Grid, reduced coordinates, normals, weights
    axes, step = _grid(extent, step, center)
    pb = _prepare(source, target, criterion, eps, radius, max_angle, weights, normals, normal_k)
    # Candidate pairs in the window
    a0 = np.array([a[0] for a in axes])
    a1 = np.array([a[-1] for a in axes])
    ptr, _, D, nrm = _pairs(pb, a0, a1, pb.radius)
    # Rasterize the consistent set of every pair, one count per source point and cell
    shape = tuple(a.size for a in axes)
    counts, kernel = _raster_parallel(ptr, (D - a0) / step, nrm, pb, step, shape, use_numba, workers)
    if weights is None:
        counts = np.rint(counts).astype(np.int32)
    # Peak and its shape
    peak = peak_shape(counts, axes, pb.eps, level)
    idx = np.unravel_index(np.argmax(counts), shape)
    t_max = np.array([a[i] for a, i in zip(axes, idx)])
    best = np.where(peak.axis_constrained, peak.summit, np.nan) if peak.kind != "flat" else np.full(3, np.nan)
    return ConsensusCube(
        counts, axes, best, t_max, float(counts[idx]), peak, pb.criterion, pb.eps, pb.radius, pb.max_angle,
        len(pb.src), int(D.shape[0]), step, kernel, time.perf_counter() - t0,
    )


def _raster_parallel(ptr, U, nrm, pb, step, shape, use_numba, workers):
    numba_ok = K.HAVE_NUMBA if use_numba is None else bool(use_numba) and K.HAVE_NUMBA
    R, E = pb.radius / step, pb.eps / step
    if not numba_ok or workers <= 1:
        return K.raster(ptr, U, nrm, R, E, pb.w, shape, use_numba=numba_ok), "numba" if numba_ok else "numpy"
    # split the source points into parts with about the same number of pairs; threads release the GIL
    n = ptr.size - 1
    cuts = np.unique(np.searchsorted(ptr, np.linspace(0, ptr[-1], workers + 1)[1:-1]).clip(0, n))
    bounds = np.concatenate(([0], cuts, [n]))

    def part(a, b):
        sub_ptr = ptr[a : b + 1] - ptr[a]
        sl = slice(ptr[a], ptr[b])
        return K.raster(sub_ptr, U[sl], None if nrm is None else nrm[sl], R, E, pb.w[a:b], shape, use_numba=True)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        parts = list(pool.map(part, bounds[:-1], bounds[1:]))
    return sum(parts[1:], parts[0]), "numba"


def peak_shape(counts, axes, eps: float, level: float = 0.07) -> PeakShape:
    """Shape of the consensus peak: point, ridge, plane or flat (eq. 6.9).

    Parameters
    ----------
    counts : ndarray (nx, ny, nz)
    axes : tuple of three 1D arrays
    eps : float
        Tolerance of the criterion; a peak narrower than the box by far is "determined".
    level : float
        Top region: counts >= peak - level * (peak - median).

    A principal direction is free when the top region spreads along it by at
    least 14 % of the box width (a top region filling the box has 29 %).
    """
    c = np.asarray(counts, dtype=np.float64)
    top, med = c.max(), np.median(c)
    contrast = (top - med) / top if top > 0 else 0.0
    width = np.array([a[-1] - a[0] for a in axes])
    free_spread = max(0.14 * float(width.min()), 1.5 * eps / np.sqrt(3))
    # no peak: the best cells are hardly better than the typical one (counting noise of the peak)
    noise = 3.0 * np.sqrt(max(top, 1.0)) if np.allclose(c, np.rint(c)) else 0.01 * top
    if top <= 0 or top - med <= noise:
        return PeakShape("flat", np.full(3, np.nan), np.eye(3), np.ones(3, bool), np.zeros(3, bool),
                         float(contrast), int(c.size), free_spread, np.full(3, np.nan), int(c.size))
    # top region and summit: cells connected to the peak above two thresholds
    region = _connected_to_peak(c >= top - max(level * (top - med), noise), c)
    summit = _connected_to_peak(c >= top - noise, c)
    X = np.column_stack([a[i] for a, i in zip(axes, np.nonzero(region))])
    centre = np.array([a[i].mean() for a, i in zip(axes, np.nonzero(summit))])
    # principal directions of the top region (eq. 6.9)
    lam, vec = np.linalg.eigh(np.cov(X.T, bias=True) if len(X) > 1 else np.zeros((3, 3)))
    spreads = np.sqrt(np.clip(lam, 0, None))
    free = spreads >= free_spread
    share = (vec[:, free] ** 2).sum(axis=1)
    kind = ("point", "ridge", "plane", "flat")[int(free.sum())]
    return PeakShape(kind, spreads, vec, free, share < 0.5, float(contrast), int(region.sum()), free_spread,
                     centre, int(summit.sum()))


def _connected_to_peak(mask, c):
    """The connected part of ``mask`` that holds the highest cell of ``c``."""
    labels, _ = ndimage.label(mask)
    return labels == labels[np.unravel_index(np.argmax(c), c.shape)]


# --------------------------------------------------------------------------- maximum consensus
def max_consensus(
    source,
    target,
    extent=1.0,
    criterion: str = "point_to_plane",
    eps: float | None = None,
    tol: float = 0.001,
    max_angle: float | None = None,
    weights=None,
    *,
    radius: float | None = None,
    center=None,
    normals=None,
    normal_k: int = 12,
    max_points: int | None = 5000,
    refine_points: int | None = None,
    max_time: float | None = 6.0,
    max_boxes: int = 20000,
    gap_tol: float = 0.0,
    init_step: float | None = None,
    deletion_k: float = 3.0,
    block_size: float | None = None,
    max_std: float | None = None,
    use_numba: bool | None = None,
):
    """Globally best translation by branch and bound, then least squares on the consensus set.

    Branch and bound (eq. 6.7, 6.8) splits the search box into octants; a box
    with centre c and half diagonal h cannot hold a translation with more
    consensus than C(c) evaluated with eps + h (and radius + h). Boxes whose
    bound does not exceed the best consensus found so far are dropped; the
    search stops when the bounds meet, every open box is smaller than ``tol``,
    or the budget (``max_time`` seconds or ``max_boxes`` splits) is spent. It
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
    source, target, extent, criterion, max_angle, weights, radius, center, normals, normal_k
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
        ALS halves at 30,000 points, 30,000 refinement points halve the stated std of X and Y
        (Notes). The refinement's time grows in proportion.
    max_time : float or None
        Time budget (s) of the branch and bound; when it is spent the best translation
        found so far is returned with its certified gap (converged = False).
    max_boxes : int
        Budget of box splits (>= 0); when exhausted the result says so (converged = False).
    gap_tol : float
        Boxes whose upper bound exceeds the best consensus by at most ``gap_tol`` are
        not split (0: search until the bounds meet or the boxes are below ``tol``).
    init_step : float, optional
        Edge (m) of the first-level boxes, bounded all at once by two rasterized cubes;
        default: twice eps, at least 1/32 of the box.
    deletion_k : float
        Deletion threshold (> 0) for standardized residuals in the refinement.
    block_size : float, optional
        Edge (m) of the square (XY) blocks of the jackknife covariance; default: the radius
        of the target's k-neighbourhoods (median distance to the k-th neighbour), the
        distance within which the residuals of two voting points share target points.
    max_std : float, optional
        A direction of the translation is determined when its standard deviation is at
        most ``max_std`` (m); default eps / 2. Weaker directions keep the branch-and-bound
        value, are named undetermined and get the variance of a uniform distribution over
        the box.

    Notes
    -----
    Measured on halves of real clouds shifted by 0.4 m (benchmarks/bench_consensus.py): TLS
    (100,000 and 520,000 points per half) within 1.5 mm and 2 stated std; ALS
    (las_with_several_extra_byte_bloc.laz, nearly flat open ground, X and Y fixed only by
    gentle relief and vegetation) within 12 mm and 1 std at 100,000 points, but 4.5-5.5 cm
    off in X or Y at 2.6-3.8 std at 30,000 and at 350,000 points: there the adjustment
    converges to a fixed point whose horizontal offset the residuals do not show. The
    vegetation votes cause it: the same pair with ``weights={2: 1, 6: 1}`` (ground and
    buildings only, a PointCloud with classes) comes within 19 mm and 1.7 std, and ground
    points alone within 13 mm and 1.5 std. On ALS with vegetation, weight by class.
    Monte Carlo on synthetic pairs: spread / stated std 1.10, 0.83, 1.03 on smooth hills;
    1.08, 1.72, 1.59 on the village, whose ridges and eaves bias the local planes.

    Returns
    -------
    RegistrationResult
        method 'max_consensus'; ``history`` holds the branch-and-bound summary
        (:class:`labkit.registration.bnb.BnBOutcome`) and one record per
        adjustment; the message names the certified gap and why the search stopped.

    Raises
    ------
    LabkitError
        Bad parameters (eps, tol, max_time, init_step, block_size <= 0; max_boxes,
        gap_tol < 0; deletion_k <= 0; max_points < 3), bad weights or normals;
        DegenerateGeometryError when no target normal is determined; EmptyRegionError
        when the clouds do not overlap within the box.
    """
    from .bnb import branch_and_bound, refine

    t0 = time.perf_counter()
    # Parameters of the search and of the adjustment
    tol = positive(tol, "tol")
    ext, c = _box(extent, center)
    opts = _search_options(max_points, max_time, max_boxes, gap_tol, init_step, deletion_k, block_size, max_std)
    refine_points = None if refine_points is None else _count(refine_points, "refine_points", 3)
    # Reduced coordinates: even subset of the source, search target, normals, tolerances
    pb = _prepare(source, target, criterion, eps, radius, max_angle, weights, normals, normal_k,
                  max_points=opts["max_points"], pair_window=float((ext + np.abs(c)).max()),
                  refine_points=refine_points)
    step0 = opts["init_step"] or max(2 * pb.eps, float(2 * ext.max()) / 32)
    ptr, src_of, D, nrm = _pairs(pb, c - ext, c + ext, pb.radius + 2 * step0)
    # Branch and bound over continuous translations, within the budget
    bb = branch_and_bound(ptr, src_of, D, nrm, pb, c, ext, tol, opts["max_boxes"], step0, opts["gap_tol"],
                          use_numba, max_time=opts["max_time"])
    # Least squares with weights and iterative deletion on the consensus set; sandwich covariance
    return refine(bb, src_of, D, nrm, pb, opts["deletion_k"], ext, time.perf_counter() - t0, t0,
                  k=max(4, int(normal_k)), block_size=opts["block_size"], max_std=opts["max_std"])


def _search_options(max_points, max_time, max_boxes, gap_tol, init_step, deletion_k, block_size, max_std) -> dict:
    """Checked budget and adjustment options of :func:`max_consensus`."""
    return {
        "max_points": None if max_points is None else _count(max_points, "max_points", 3),
        "max_time": None if max_time is None else positive(max_time, "max_time"),
        "max_boxes": _count(max_boxes, "max_boxes", 0),
        "gap_tol": _non_negative(gap_tol, "gap_tol"),
        "init_step": None if init_step is None else positive(init_step, "init_step"),
        "deletion_k": positive(deletion_k, "deletion_k"),
        "block_size": None if block_size is None else positive(block_size, "block_size"),
        "max_std": None if max_std is None else positive(max_std, "max_std"),
    }
