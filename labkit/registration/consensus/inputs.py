"""The inputs of the consensus search: reduced clouds, voting points, normals, tolerances and pairs.

:func:`prepare_problem` checks and reduces the clouds once and chooses the voting source points (an
even subset), the search target and the tolerances; :func:`candidate_pairs` lists the pairs (p, q)
whose difference can be consistent for some translation in the window (eq. 6.6). Both the cube
(:func:`labkit.registration.consensus_cube`) and the branch and bound
(:func:`labkit.registration.max_consensus`) count on these pairs, never on nearest-neighbour
searches per translation.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain

import numpy as np
from scipy.spatial import cKDTree

from ...core.checks import as_points, choice, count, positive
from ...core.frame import local_origin, reduce
from ...core.errors import DegenerateGeometryError, EmptyRegionError, LabkitError
from ...features import local_pca
from ...neighbours.sampling import even_subset, median_spacing, voxel_thin
METRICS = ("point_to_plane", "point_to_point")
MAX_CELLS = 100_000_000
PAIR_BUDGET = 1_000_000  # candidate pairs of max_consensus before the search target is thinned
EPS_RANGE = (0.005, 0.10)  # limits (m) of the tolerance derived from the local noise


@dataclass(frozen=True, eq=False)
class Problem:
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
    metric: str
    eps: float
    radius: float
    max_angle_deg: float | None
    tgt_full: np.ndarray | None = None
    noise: float = float("nan")  # median local noise of the target (m)
    n_source: int = 0  # source points handed in
    spacing: float = float("nan")  # spacing of the voting source points (m)
    src_ref: np.ndarray | None = None  # (r, 3) reduced source points of the least-squares refinement
    w_ref: np.ndarray | None = None  # (r,) their weights
    src_full: np.ndarray | None = None  # (n, 3) every reduced source point (the planes of the reverse fit)
    weighted: bool = False  # weights were given (the reverse fit has no weights for the target)


def prepare_problem(source, target, metric, eps, radius, max_angle_deg, weights, normals, k, *,
                    max_points=None, pair_window=None, pair_budget=PAIR_BUDGET, refine_points=None) -> Problem:
    """Check and reduce the inputs; choose the voting points, the search target and the tolerances.

    ``max_points``: keep at most that many source points, spread evenly in space
    (:func:`labkit.neighbours.sampling.even_subset`); ``refine_points``: the points of the least-squares
    refinement, an even subset of at most that many (None: the voting points). ``pair_window``: half-width (m) of the translation window
    searched; with it the target is thinned evenly until the candidate pairs fit
    ``pair_budget`` (dense TLS targets). Normals the local PCA cannot determine
    (identical or collinear neighbours) are dropped, never used.
    """
    metric = choice(metric, METRICS, "metric")
    eps = None if eps is None else positive(eps, "eps")
    k = count(k, "k", minimum=3)
    xyz_s = as_points(source, min_points=1, name="source")
    xyz_t = as_points(target, min_points=3, name="target")
    origin = local_origin(xyz_t)
    src, tgt_full = reduce(xyz_s, origin), reduce(xyz_t, origin)
    w = source_weights(weights, source, len(src))
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
        keep_t = search_target(src[keep_s], tgt_full, pair_window, pair_budget)
    plane = metric == "point_to_plane"
    n_tgt, noise = None, float("nan")
    if plane or max_angle_deg is not None or eps is None:
        n_tgt, ok_t, sig = normals_at(n_tgt_given, tgt_full, keep_t, k, "target")
        noise = float(np.nanmedian(sig)) if np.isfinite(sig).any() else float("nan")
        keep_t, n_tgt = keep_t[ok_t], n_tgt[ok_t]
        if keep_t.size < 3:
            raise DegenerateGeometryError(
                "fewer than 3 target points have a determined normal (identical or collinear "
                "neighbours): the target has no surface to register on")
        if not (plane or max_angle_deg is not None):
            n_tgt = None
    n_src = None
    if max_angle_deg is not None:
        max_angle_deg = positive(max_angle_deg, "max_angle_deg")
        n_src, ok_s, _ = normals_at(n_src_given, src, keep_s, k, "source")
        keep_s, n_src = keep_s[ok_s], n_src[ok_s]
        if keep_s.size == 0:
            raise DegenerateGeometryError("no source point has a determined normal for the angle test")
    tgt = tgt_full[keep_t]
    if eps is None:
        eps = default_eps(noise)
    if plane:
        radius = default_radius(tgt) if radius is None else positive(radius, "radius")
        radius = max(radius, eps)
    else:
        radius = eps
    spacing = median_spacing(src[keep_s])
    return Problem(
        src=src[keep_s], tgt=tgt, origin=origin, w=w[keep_s], tgt_normals=n_tgt, src_normals=n_src, metric=metric,
        eps=float(eps), radius=float(radius), max_angle_deg=max_angle_deg, tgt_full=tgt_full, noise=noise,
        n_source=len(src), spacing=spacing, src_ref=None if keep_r is None else src[keep_r],
        w_ref=None if keep_r is None else w[keep_r], src_full=src, weighted=weights is not None,
    )


def search_target(src, tgt, window, budget):
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
    size = median_spacing(tgt)
    for _ in range(4):
        tree = cKDTree(tgt[keep])
        per_point = tree.query_ball_point(sample, 1.3 * window, p=np.inf, return_length=True, workers=-1).mean()
        excess = per_point * len(src) / budget
        if excess <= 1.0:
            break
        size *= max(np.sqrt(excess), 1.2)
        keep = voxel_thin(tgt, size)
    return keep


def default_eps(noise) -> float:
    """Tolerance from the local noise: 3 sigma of a difference of two noisy points (3 sqrt(2) sigma_n)."""
    if not np.isfinite(noise):
        return 0.05
    return float(np.clip(3.0 * np.sqrt(2.0) * noise, EPS_RANGE[0], EPS_RANGE[1]))


def source_weights(weights, source, n):
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


def normals_at(given, xyz, at, k, name):
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
    pca = local_pca(xyz, k=min(k, len(xyz)), orient="none", at=at)
    ok = pca.valid & np.isfinite(pca.normals).all(axis=1)
    return pca.normals, ok, np.where(ok, pca.noise, np.nan)


def default_radius(tgt) -> float:
    """Search radius: median distance to the 4th neighbour, so a disc rarely misses the surface."""
    sample = tgt[:: max(1, len(tgt) // 20000)]
    d, _ = cKDTree(tgt).query(sample, k=min(5, len(tgt)), workers=-1)
    return float(np.median(d[:, -1]))


def search_box(extent, center):
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


def grid(extent, step, center):
    ext, c = search_box(extent, center)
    step = positive(step, "step")
    half = np.floor(ext / step + 1e-9).astype(np.int64)
    n = 2 * half + 1
    if np.prod(n.astype(float)) > MAX_CELLS:
        raise LabkitError(
            f"the grid would have {int(np.prod(n)):,} cells (> {MAX_CELLS:,}); use a larger step or a smaller extent"
        )
    return tuple(c[i] + step * np.arange(-half[i], half[i] + 1) for i in range(3)), step


def candidate_pairs(pb: Problem, lo, hi, reach):
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
    if pb.max_angle_deg is not None:  # normal angle test does not depend on t
        cos = np.abs(np.einsum("ij,ij->i", pb.src_normals[i], pb.tgt_normals[j]))
        keep &= cos > np.cos(np.radians(pb.max_angle_deg))
    i, j, D = i[keep], j[keep], D[keep]
    if i.size == 0:
        raise EmptyRegionError(
            "no source point has a target point within the search window: the clouds do not overlap "
            "for these translations (check the frames, extent and center)"
        )
    ptr = np.concatenate(([0], np.cumsum(np.bincount(i, minlength=len(pb.src)))))
    nrm = pb.tgt_normals[j] if pb.metric == "point_to_plane" else None
    return ptr, i, D, nrm
