"""Branch and bound over translations and the least-squares refinement of maximum consensus.

Used by :func:`labkit.registration.max_consensus` (notebook 06, eq. 6.7-6.10).
"""

from __future__ import annotations

import heapq
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ...core.report import ReportMixin, fmt
from ...core.stats import MAD_TO_SIGMA
from . import kernels as K
from ..consistency import block_consistency
from ..degeneracy import degeneracy_report
from .inputs import even_subset
from .jackknife import largest, sandwich, symmetric_cov
from ..result import RegistrationResult

NAMES = ("tx", "ty", "tz")
OCTANTS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class BnBOutcome(ReportMixin):
    """Summary of the branch and bound.

    Attributes
    ----------
    translation : ndarray (3,)
        Centre of the best box found (m).
    lower : float
        Consensus at ``translation`` (exact): a lower bound of the maximum.
    upper : float
        Certified upper bound of the maximum over the whole search box.
    gap : float
        ``upper - lower``; 0 when the bounds met.
    splits : int
        Boxes split into octants.
    open_boxes : int
        Boxes left unresolved (smaller than tol, or left when the budget ran out).
    converged : bool
        True when the bounds met or every open box is smaller than tol.
    reason : str
        Why the search stopped.
    runtime_s : float
    pair_tests : int
        Pair tests of the splits (8 per candidate pair of a split box): the work the budget counts.
    """

    translation: np.ndarray
    lower: float
    upper: float
    gap: float
    splits: int
    open_boxes: int
    converged: bool
    reason: str
    runtime_s: float
    pair_tests: int = 0

    def _report(self):
        rows = [
            ("best translation", fmt(self.translation, 4, "m")),
            ("consensus (lower bound)", f"{self.lower:.6g}"),
            ("certified upper bound", f"{self.upper:.6g} (gap {self.gap:.6g})"),
            ("boxes split / left open", f"{self.splits} / {self.open_boxes}"),
            ("pair tests (the work budget)", f"{self.pair_tests:,}"),
            ("stopped", self.reason),
            ("runtime", fmt(self.runtime_s, 3, "s")),
        ]
        return "Branch and bound", [("", rows)]


@dataclass(frozen=True, eq=False)
class AdjustmentRecord(ReportMixin):
    """One least-squares adjustment of the refinement (eq. 6.10)."""

    iteration: int
    translation: np.ndarray
    sigma0: float
    n_used: int
    n_deleted: int

    def _report(self):
        rows = [("translation", fmt(self.translation, 4, "m")), ("sigma0", fmt(self.sigma0, 4, "m")),
                ("used / deleted", f"{self.n_used} / {self.n_deleted}")]
        return f"Adjustment {self.iteration}", [("", rows)]


def branch_and_bound(ptr, src_of, D, nrm, pb, center, ext, tol, max_boxes, init_step=0.05, gap_tol=0.0,
                     use_numba=None, *, max_time=None, max_work=None) -> BnBOutcome:
    """Best-first branch and bound over the box ``center +- ext`` (eq. 6.7, 6.8).

    Upper bound of a box with centre c and half diagonal h: the consensus at c
    with radius + h and eps + h; lower bound: the exact consensus at c. The
    first level (boxes of about ``init_step``) is bounded all at once by two
    rasterized cubes; a box is then split into octants, each tested only on
    the pairs that passed its parent's enlarged test. The search stops early when
    ``max_boxes`` splits or ``max_work`` pair tests are spent (counted work: the same input
    always gives the same result), or, only if given, ``max_time`` seconds (wall time: the
    result then depends on the load of the machine); the bound of every box still open then
    enters the certified upper bound.

    Examples
    --------
    The steps of :func:`labkit.registration.max_consensus`, one by one:

    >>> import numpy as np
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> from labkit.registration.consensus.inputs import candidate_pairs, prepare_problem
    >>> pb = prepare_problem(source, target, "point_to_plane", 0.01, None, None, None, None, 12, max_points=100)
    >>> center, ext = np.zeros(3), np.full(3, 0.08)
    >>> ptr, src_of, D, nrm = candidate_pairs(pb, center - ext, center + ext, pb.radius + 0.08)
    >>> bb = branch_and_bound(ptr, src_of, D, nrm, pb, center, ext, 0.02, 1000, 0.04, use_numba=False)
    >>> bb.lower <= bb.upper, bool(np.allclose(bb.translation, [0.05, 0.02, 0.03], atol=0.02))
    (True, True)
    """
    t0 = time.perf_counter()
    R, E, w = pb.radius, pb.eps, pb.w
    # First level: bounds of all boxes from two cubes at the box centres (the box is rounded up to whole boxes)
    s = float((2 * ext / np.ceil(2 * ext / init_step - 1e-9)).min())
    n0 = np.ceil(2 * ext / s - 1e-9).astype(int)
    a0 = center - n0 * s / 2 + s / 2
    h0 = s * np.sqrt(3) / 2
    U = (D - a0) / s
    shape = tuple(int(n) for n in n0)
    with ThreadPoolExecutor(max_workers=2) as pool:  # the compiled kernel releases the GIL
        jobs = [pool.submit(K.raster, ptr, U, nrm, r / s, e / s, w, shape, use_numba=use_numba)
                for r, e in ((R + h0, E + h0), (R, E))]
        ub0, lb0 = (j.result() for j in jobs)
    k = np.unravel_index(np.argmax(lb0), shape)
    best, best_t = float(lb0[k]), a0 + s * np.array(k)
    half0 = np.full(3, s / 2)
    heap = [(-ub0[i], -1, n, a0 + s * np.array(i), half0, None, 0.0)
            for n, i in enumerate(zip(*np.nonzero(ub0 > best + gap_tol)))]
    heapq.heapify(heap)
    every = np.arange(len(D), dtype=np.int64)

    def evaluate(act, centres, h):
        return K.children(act, src_of, D, nrm, centres, R, E, h, w, use_numba=use_numba)

    counter, splits, small_ub, n_small, work = len(heap), 0, -np.inf, 0, 0
    dropped = float(ub0[ub0 <= best + gap_tol].max(initial=best))  # bounds of boxes not split (gap_tol)
    reason = "bounds met" if gap_tol == 0 else f"bounds within gap_tol = {gap_tol:g}"
    while heap:
        neg_ub, depth, _, c, half, act, base = heap[0]
        if -neg_ub <= best + gap_tol:
            dropped = max(dropped, -neg_ub)
            break
        if splits >= max_boxes:
            reason = f"box budget exhausted ({splits} splits)"
            break
        if max_work is not None and work >= max_work:
            reason = f"work budget of {max_work:.3g} pair tests spent ({splits} splits)"
            break
        if max_time is not None and time.perf_counter() - t0 > max_time:
            reason = f"time budget of {max_time:g} s spent ({splits} splits)"
            break
        heapq.heappop(heap)
        if 2 * half.max() < tol:  # too small to split: stays open, counts for the gap
            small_ub, n_small = max(small_ub, -neg_ub), n_small + 1
            continue
        if act is None:  # pairs that can be consistent somewhere in this first-level box (ball and slab)
            acts, _, _, sure = evaluate(every, c[None, :], float(np.linalg.norm(half)))
            act, base, work = acts[0], float(sure[0]), work + every.size
        # Split into octants and bound each
        hh = half / 2
        centres = c + OCTANTS * hh
        acts, ub, lb, sure = evaluate(act, centres, float(np.linalg.norm(hh)))
        ub, lb, sure = ub + sure + base, lb + sure + base, sure + base
        splits, work = splits + 1, work + 8 * act.size
        j = int(np.argmax(lb))
        if lb[j] > best:
            best, best_t = float(lb[j]), centres[j].copy()
        dropped = max(dropped, float(ub[ub <= best + gap_tol].max(initial=-np.inf)))
        for i in np.flatnonzero(ub > best + gap_tol):
            heapq.heappush(heap, (-ub[i], depth - 1, counter, centres[i], hh, acts[i], sure[i]))
            counter += 1
    left = [-item[0] for item in heap if -item[0] > best + gap_tol]
    upper = max([best, small_ub, min(dropped, best + gap_tol), *left])
    converged = not left
    if converged and n_small and small_ub > best:
        reason = f"boxes smaller than tol = {tol} m"
    return BnBOutcome(best_t, float(best), float(upper), float(upper - best), splits, len(left) + n_small,
                      converged, reason, time.perf_counter() - t0, int(work))


def _consensus_set(t, src_of, D, nrm, R, E):
    """Per source point the best consistent pair at translation t (eq. 6.3, 6.4)."""
    e = t - D
    d2 = np.einsum("ij,ij->i", e, e)
    if nrm is None:
        ok, score = d2 < R * R, d2
    else:
        r = np.abs(np.einsum("ij,ij->i", nrm, e))
        ok, score = (d2 < R * R) & (r < E), r
    idx = np.flatnonzero(ok)
    idx = idx[np.lexsort((score[idx], src_of[idx]))]
    first = np.concatenate(([True], src_of[idx][1:] != src_of[idx][:-1])) if idx.size else idx.astype(bool)
    return idx[first]


def _consistent(src, t, tgt, tree, k, R, E):
    """Indices of the points ``src + t`` with a target point within ``R`` and |residual| < ``E`` to their
    local target plane (eq. 6.4 with the plane of the k-neighbourhood)."""
    x = src + t
    d, _ = tree.query(x, k=1, workers=-1)
    near = np.flatnonzero(d < R)
    if near.size == 0:
        return near
    n, c, _, _ = _local_planes(tgt, tree, x[near], k)
    return near[np.abs(np.einsum("ij,ij->i", n, x[near] - c)) < E]


def _local_planes(tgt, tree, x, k):
    """Plane of the k target points nearest to each x: unit normal, centroid, noise^2 (eq. 6.11).

    The noise is s^2 = k l3 / (k - 3), the spread of the neighbourhood along its normal;
    it is large on vegetation, edges and ridges, where a plane does not describe the surface.
    """
    _, J = tree.query(x, k=k, workers=-1)
    P = tgt[J]
    c = P.mean(axis=1)
    Y = P - c[:, None, :]
    lam, V = np.linalg.eigh(np.einsum("nki,nkj->nij", Y, Y) / k)
    s2 = lam[:, 0] * k / (k - 3)
    # covariance of the normal's tilt from the noise alone: s^2 / (k l_j) along the in-plane axes e_j
    tilt = np.einsum("nj,nij,nkj->nik", s2[:, None] / (k * np.maximum(lam[:, 1:], 1e-300)), V[:, :, 1:], V[:, :, 1:])
    return V[:, :, 0], c, s2, tilt


def _design(members, x, tgt, tree, k, w, src):
    """A, l, p of the point-to-plane model n.t = n.(c - p) for every member at x = p + t (eq. 6.10, 6.12).

    Weight p = w / var with var = s^2 (1 + 1/k) + s^2: the noise of the plane's centroid plus
    that of the source point, which lies on a surface as rough as the target's neighbourhood.
    """
    n, c, s2, tilt = _local_planes(tgt, tree, x, k)
    var = np.maximum(s2, 1e-6) * (2.0 + 1.0 / k)  # at least (1 mm)^2 per epoch
    var = var / np.median(var)  # sigma0 in metres: that of an observation of median noise
    return n, np.einsum("ij,ij->i", n, c - src[members]), w[members] / var, tilt


def _adjust(A, l, p, tilt, t_ref, box_var, max_std):
    """Weighted LS in the determined subspace of N; undetermined directions keep t_ref.

    Determinability from precision (eq. 6.12): an eigen-direction of N with eigenvalue
    lam is determined when its standard deviation sigma0 / sqrt(lam) is at most ``max_std``
    (metres), not when lam exceeds a fixed share of the largest one: on open terrain X and
    Y are 5-50 times weaker than Z and still known to millimetres. A direction must
    also carry at least four times the information that the noise of the normals alone
    puts into it (N_noise = sum p_i T_i, T_i the tilt covariance of normal i): on a flat
    field the tilted normals of noisy planes feign X and Y information (eq. 6.12).
    """
    N = A.T @ (p[:, None] * A)
    N_noise = np.einsum("i,ijk->jk", p, tilt)
    rel = 1e-9  # numerically determined directions first, for sigma0
    for _ in range(2):
        deg = degeneracy_report(N, NAMES, rel_threshold=rel)
        lam, V = deg.eigenvalues, deg.eigenvectors
        Vc, lc = V[:, deg.constrained], lam[deg.constrained]
        n_vec = A.T @ (p * (l - A @ t_ref))
        x = t_ref + Vc @ ((Vc.T @ n_vec) / lc)  # x = t_ref + N^+ A^T P (l - A t_ref)
        v = A @ x - l
        dof = max(len(l) - int(deg.constrained.sum()), 1)
        sigma0 = float(np.sqrt(v @ (p * v) / dof))
        # std of direction i: sigma0 / sqrt(lam_i) <= max_std  <=>  lam_i >= sigma0^2 / max_std^2
        noise_info = np.einsum("ji,jk,ki->i", V, N_noise, V)
        fail = (lam < sigma0**2 / max_std**2) | (lam < 4.0 * noise_info)
        new_rel = max(float(lam[fail].max(initial=0.0)) / max(float(lam.max()), 1e-300) * (1 + 1e-9), 1e-9)
        if new_rel <= rel:
            break
        rel = new_rel
    Qc = (Vc / lc) @ Vc.T
    Vu = V[:, ~deg.constrained]
    cov = sigma0**2 * Qc + box_var * (Vu @ Vu.T)
    return x, v, sigma0, cov, deg


def _fit_with_deletion(A, l, p, tilt, t, t_ref, box_var, k_del, max_std, max_rounds=30):
    """Adjustment with iterative deletion of |v| sqrt(p) > k_del sigma0 (eq. 6.13).

    Start from a robust scale (MAD of the weighted residuals at t), then alternate the
    adjustment and the test on all observations until the kept set no longer changes.
    """
    used = p > 0
    if used.sum() < 3:
        return None
    z = (A @ t - l) * np.sqrt(p)
    keep = used & (np.abs(z) <= k_del * max(MAD_TO_SIGMA * float(np.median(np.abs(z[used]))), 1e-12))
    for _ in range(max_rounds):
        if keep.sum() < 3:
            return None
        x, v, sigma0, cov, deg = _adjust(A[keep], l[keep], p[keep], tilt[keep], t_ref, box_var, max_std)
        new = used & (np.abs(A @ x - l) * np.sqrt(p) <= k_del * sigma0) if sigma0 > 0 else keep
        if (new == keep).all():
            break
        keep = new
    return x, sigma0, cov, deg, keep


def _held_effect(t, deg, box_var, members, src, w, tgt, tree, k, reject_sigma, max_std):
    """Covariance that the held (undetermined) directions pass on to the determined ones.

    The least squares leave a held component where it was put, anywhere within the search box. On
    undulating ground the local planes at a wrong horizontal position lie at another height,
    so the determined components depend on the held ones through the association (not
    through N, whose eigen-directions are uncoupled). The dependence is measured by moving
    t one box standard deviation along each held direction and adjusting again; the
    secant S gives S box_var S^T.
    """
    Vu = deg.eigenvectors[:, ~deg.constrained]
    Vc = deg.eigenvectors[:, deg.constrained]
    extra = np.zeros((3, 3))
    if Vu.shape[1] == 0 or Vc.shape[1] == 0:
        return extra
    step = np.sqrt(box_var)
    for j in range(Vu.shape[1]):
        tj = t + step * Vu[:, j]
        A, l, p, tilt = _design(members, src[members] + tj, tgt, tree, k, w, src)
        fit = _fit_with_deletion(A, l, p, tilt, tj, tj, box_var, reject_sigma, max_std)
        if fit is None:
            continue
        s_j = Vc @ (Vc.T @ (fit[0] - t)) / step  # change of the determined part per metre of the held one
        extra += box_var * np.outer(s_j, s_j)
    return extra


@dataclass(frozen=True, eq=False)
class _Side:
    """One direction of the refinement: its estimate, covariance and last design."""

    t: np.ndarray
    sigma0: float
    cov: np.ndarray
    deg: object
    keep: np.ndarray
    A: np.ndarray
    l: np.ndarray
    p: np.ndarray
    cells: np.ndarray
    kind: str
    records: list
    ls_ok: bool
    n_used: int
    held: np.ndarray
    blocks: tuple | None


def _one_side(src, w, members, tgt, tree, t_start, t_ref, *, box_var, k, reject_sigma, max_std, block_size,
              max_outer):
    """Association with the local target planes and adjustment until t settles; its covariance (eq. 6.10-6.14).

    Returns None when too few points are consistent for the adjustment.
    """
    t, records, fit = np.array(t_start, dtype=np.float64), [], None
    for it in range(1, (max_outer if members.size >= 3 else 0) + 1):
        A, l, p, tilt = _design(members, src[members] + t, tgt, tree, k, w, src)
        fit = _fit_with_deletion(A, l, p, tilt, t, t_ref, box_var, reject_sigma, max_std)
        if fit is None:
            return None
        x, sigma0, cov, deg, keep = fit
        records.append(AdjustmentRecord(it, x.copy(), sigma0, int(keep.sum()), int(members.size - keep.sum())))
        moved = np.linalg.norm(x - t)
        t = x
        if moved < max(1e-6, 0.05 * sigma0 / np.sqrt(deg.eigenvalues.max())):  # a small part of the best std
            break
        # a cycle: the deletion and the association switch between a few states; their mean is the answer
        back = [j for j in range(2, min(5, len(records)) + 1) if np.allclose(records[-j].translation, x, atol=1e-9)]
        if back:
            t, moved = np.mean([r.translation for r in records[-back[0]:]], axis=0), 0.0
            break
    if fit is None:
        return None
    ls_ok = bool(moved < max(1e-6, 0.05 * sigma0 / np.sqrt(deg.eigenvalues.max())))
    # the jackknife over blocks of each edge (blocks in the target frame); per axis the largest counts
    xy = (src[members[keep]] + t)[:, :2]
    jack = [(b, sandwich(A[keep], l[keep], p[keep], t, deg, np.floor(xy / b).astype(np.int64), box_var))
            for b in np.atleast_1d(block_size)]
    jack = [(b, r) for b, r in jack if r is not None]
    cells = np.floor(xy / np.atleast_1d(block_size)[0]).astype(np.int64)
    if jack:
        b, cov = largest([(b, r[0]) for b, r in jack])
        kind, blocks = f"delete-a-block jackknife over {b:.3g} m blocks", [(b, *r[1:]) for b, r in jack]
    else:
        kind, blocks = "sigma0^2 N^-1 (too few blocks for the jackknife)", None
    held = _held_effect(t, deg, box_var, members, src, w, tgt, tree, k, reject_sigma, max_std)
    return _Side(t, sigma0, cov + held, deg, keep, A, l, p, cells, kind, records, ls_ok, int(keep.sum()), held,
                 blocks)


def _reverse_side(fwd, pb, src, tgt, R, E, bb, opts):
    """The same adjustment with the roles swapped: target points on the local planes of the source (estimates -t).

    A k-neighbourhood plane lies inside a curved surface (its centroid is off the surface by about
    curvature x radius^2 / 4), so every point-to-plane residual has a bias that depends on the local
    shape; on slopes it becomes a horizontal bias of the translation that no resampling shows (it is
    the same for every random half: 8 mm in Y at a stated 2.4 mm on a UAV scan). Swapping the roles
    keeps the bias (the planes are still inside the surface) but flips the sign of t, so the mean of
    the two estimates cancels it to first order. Only without given weights (the target has none)
    and with the whole source at hand; None otherwise.
    """
    if pb.weighted or pb.src_full is None or len(pb.src_full) < opts["k"] + 1:
        return None
    if pb.src_full.shape == tgt.shape and np.array_equal(pb.src_full, tgt):  # an identical copy: nothing new
        return None
    sub = even_subset(tgt, max(len(src), 3))  # as many target points as the source side had
    tree_s = cKDTree(pb.src_full)
    members = _consistent(tgt[sub], -fwd.t, pb.src_full, tree_s, opts["k"], R, E)
    return _one_side(tgt[sub], np.ones(len(sub)), members, pb.src_full, tree_s, -fwd.t, -bb.translation, **opts)


def refine(bb, src_of, D, nrm, pb, reject_sigma, ext, runtime_bb, t0, max_outer: int = 50, k: int = 12,
           block_size: float | None = None, max_std: float | None = None):
    """Least squares on the consensus set with weights and iterative deletion (eq. 6.10-6.14).

    The consensus set of the branch-and-bound optimum names the source points that
    agree (the inliers of maximum consensus). Each of them is then related to the
    plane of its ``k`` nearest target points (of the whole target) at the current
    translation, weighted by the local noise of that plane, and the translation is
    adjusted with iterative deletion; association and adjustment alternate until the
    translation settles. The covariance is the cluster-robust sandwich over cubic blocks
    of edge ``block_size`` (:func:`.jackknife.sandwich`), sigma0^2 N^-1 where the blocks are too few.
    A direction is determined when its standard deviation is at most ``max_std`` (default
    eps / 2: known to better than the consensus tolerance itself).
    The pairs of the consensus test itself are not used as observations: of all
    target points within the search radius they are the one whose plane fits best
    at the branch-and-bound translation, and residuals truncated at eps both pull the
    estimate towards that translation and make sigma0 far too small (notebook 06).

    Examples
    --------
    After the branch and bound (see :func:`branch_and_bound`), the adjustment of its consensus set:

    >>> import numpy as np
    >>> from labkit.synthetic import wavy_pair
    >>> source, target = wavy_pair(300)  # wavy surface sampled twice, the source moved by -[0.05, 0.02, 0.03]
    >>> from labkit.registration.consensus.inputs import candidate_pairs, prepare_problem
    >>> pb = prepare_problem(source, target, "point_to_plane", 0.01, None, None, None, None, 12, max_points=100)
    >>> center, ext = np.zeros(3), np.full(3, 0.08)
    >>> ptr, src_of, D, nrm = candidate_pairs(pb, center - ext, center + ext, pb.radius + 0.08)
    >>> bb = branch_and_bound(ptr, src_of, D, nrm, pb, center, ext, 0.02, 1000, 0.04, use_numba=False)
    >>> res = refine(bb, src_of, D, nrm, pb, 3.0, ext, 0.0, 0.0)
    >>> bool(np.allclose(res.translation, [0.05, 0.02, 0.03], atol=0.01)), res.covariance.shape
    (True, (3, 3))
    """
    R, E = pb.radius, pb.eps
    tgt = pb.tgt if pb.tgt_full is None else pb.tgt_full
    box_var = float((2 * ext.max()) ** 2 / 12)  # undetermined directions: uniform over the search box
    tree = cKDTree(tgt)
    k = int(min(k, len(tgt)))
    max_std = max_std or E / 2
    src, w = (pb.src, pb.w) if pb.src_ref is None else (pb.src_ref, pb.w_ref)
    if pb.src_ref is None:  # the consensus set of the voting points
        members = np.unique(src_of[_consensus_set(bb.translation, src_of, D, nrm, R, E)])
    else:  # the refinement points consistent at the optimum: a target point within R, off its local plane by < eps
        members = _consistent(src, bb.translation, tgt, tree, k, R, E)
    if block_size is None:  # two voting points closer than twice the radius of the k-neighbourhoods share
        d, _ = tree.query(tgt[:: max(1, len(tgt) // 5000)], k=k, workers=-1)  # target points: one block
        block_size = max(2.0 * float(np.median(d[:, -1])), 1e-3) * np.array([1.0, 2.0])  # the larger one counts
    opts = dict(box_var=box_var, k=k, reject_sigma=reject_sigma, max_std=max_std, block_size=block_size,
                max_outer=max_outer)
    fwd = _one_side(src, w, members, tgt, tree, bb.translation, bb.translation, **opts)
    rev = None if fwd is None else _reverse_side(fwd, pb, src, tgt, R, E, bb, opts)
    t, sigma0, cov, deg, n_used, kind, test, records, ls_ok = (
        bb.translation.copy(), float("nan"), np.full((3, 3), np.nan), None, 0, "none", None, [], False)
    if fwd is not None:
        t, sigma0, cov, deg, n_used, kind, records, ls_ok = (fwd.t, fwd.sigma0, fwd.cov, fwd.deg, fwd.n_used,
                                                            fwd.kind, fwd.records, fwd.ls_ok)
        if rev is not None:  # symmetric estimate: the first-order bias of the local planes cancels
            P = fwd.deg.eigenvectors[:, fwd.deg.constrained]
            P = P @ P.T
            bias = P @ (fwd.t + rev.t) / 2  # half the sum of the two (reverse = -t): the plane bias
            t = fwd.t - bias
            cov, kind = symmetric_cov(fwd, rev, box_var)
            cov = cov + 0.25 * np.outer(bias, bias)  # the remainder of the cancellation: std half the bias
            kind += (f"; symmetric: mean of the fits source->target and target->source (they differ by 2 x "
                     f"{np.array2string(1000 * bias, precision=1)} mm, the bias of the local planes), "
                     "blocks deleted from both, plus half that bias as the std of what the mean leaves of it")
            ls_ok = ls_ok and rev.ls_ok
        elif pb.weighted or pb.src_full is None:
            kind += "; one-sided (given weights): the bias of the local planes is not cancelled"
        if fwd.blocks is None:  # sigma0^2 N^-1 alone: 1.14-1.52 times too small on the hills
            none = np.zeros(3, bool)
            deg = replace(deg, constrained=none, axis_determined=none, parameter_determined=none)
            t, cov = bb.translation.copy(), box_var * np.eye(3)
            kind = "none stated: fewer than 8 blocks for the jackknife, so no check of the precision (undetermined)"
        # reported, not added: on smooth synthetic hills the quadrants differ (their k-neighbourhood planes
        # are biased by the local curvature) and adding their spread doubled the stated std against a
        # Monte Carlo spread / stated of 1.10, 0.83, 1.03 without it (tests/test_consensus.py)
        keep = fwd.keep
        test = block_consistency(fwd.A[keep], fwd.l[keep], fwd.p[keep], src[members[keep]], fwd.cells, deg)
    undetermined = deg.undetermined_axes if deg is not None else NAMES
    msg = (f"branch and bound: consensus {bb.lower:.6g}, certified upper bound {bb.upper:.6g} "
           f"(gap {bb.gap:.6g}) after {bb.splits} splits, {bb.reason}; eps {E * 1000:.1f} mm, "
           f"{len(pb.src)} of {pb.n_source or len(pb.src)} source points vote, {len(src)} refine")
    if deg is None:
        msg += "; too few consistent points for the least-squares refinement"
    elif not deg.well_posed:
        msg += (f"; undetermined along {', '.join(undetermined)}: kept the branch-and-bound value there "
                "(max_consensus moves it to the centre of the consensus hill: see 'held directions'), "
                "variance = uniform over the search box")
    if deg is not None:
        msg += f"; covariance: {kind}"
    if test is not None and not test.agree:
        msg += (f"; the spatial quadrants disagree (T = {test.statistic:.0f}, dof = {test.dof}, p = "
                f"{test.p_value:.1g}): model errors or changes suspected, not included in the covariance; "
                "consider labkit register --method consensus+icp")
    if not ls_ok:
        msg += "; refinement did not settle"
    return RegistrationResult(
        translation=t, rotation=np.eye(3), origin=pb.origin.copy(), covariance=cov, parameter_names=NAMES,
        sigma0=sigma0, n_used=n_used, share_used=n_used / len(src), converged=bool(bb.converged and ls_ok),
        iterations=bb.splits, degeneracy=deg, method="max_consensus", history=(bb, *records),
        runtime_s=time.perf_counter() - t0, message=msg, consistency=test,
    )
