"""Distances between two epochs, before and after a transformation (the registration study, step 5).

Cloud to cloud: the distance from each point of one epoch to its nearest
neighbour in the other. Point to plane: the signed distance to the tangent
plane of that neighbour, which is what a shift of a surface changes.

A point whose nearest target point has no usable normal (a degenerate
neighbourhood gives a NaN normal; a zero-length normal is treated the same)
gets a NaN point-to-plane distance instead of a made-up 0; the statistics of
:class:`DistanceChange` leave those points out and count them.

Before/after statistics of :func:`distances_before_after` are taken only where
the target covers the ground: a source point counts when, after the
transformation, it lies within the target's sampling of the surface - its offset
*along* the target's tangent plane at the nearest target point (horizontal for
cloud to cloud) is at most :data:`COVERAGE_FACTOR` times the target's local
spacing there (the distance to its :data:`COVERAGE_K`-th neighbour). The offset
*along the normal* - the change itself - does not enter, so a moved surface stays
covered; a point beyond the edge of the target's strip, in a hole of it or over
ground it never saw is counted apart (``n_outside``) instead of inflating the RMS.
The local spacing adapts the rule to sparse ALS (metres) and dense TLS (millimetres)
alike; under overhangs (a floor below a ceiling the target saw) it errs towards
covered when the normals are missing (cloud to cloud).

Equation numbers refer to ``notebooks/07-comparing-transformations.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.checks import as_points, choice, count
from ..core.crs import check_same_crs
from ..core.arrays import extent
from ..core.frame import local_origin, reduce
from ..core.report import ReportMixin
from ..neighbours.treecache import local_tree
from ..core.errors import DegenerateGeometryError, EmptyRegionError, LabkitError
from ..core.progress import progress_steps
from ..transforms import apply_transform, check_transform


def as_matrix(transform) -> np.ndarray:
    """A 4x4 matrix from a RegistrationResult, a Reference, or an array (checked)."""
    T = getattr(transform, "matrix", transform)
    return check_transform(T)


def check_overlap(source, target, *, name: str = "source and target") -> None:
    """Raise :class:`EmptyRegionError` unless some source points lie inside the target's xy extent."""
    src, tgt = as_points(source, name="source"), as_points(target, name="target")
    lo, hi = extent(tgt[:, :2])

    def inside(p):
        return ((p[:, :2] >= lo) & (p[:, :2] <= hi)).all(axis=1).any()

    # an even subset inside is enough (a large cloud is not passed in full); else every point is looked at
    if inside(src[:: max(1, len(src) // 10_000)]) or inside(src):
        return
    s_lo, s_hi = extent(src[:, :2])
    raise EmptyRegionError(
        f"{name} do not overlap: source spans x {s_lo[0]:.1f}..{s_hi[0]:.1f}, y {s_lo[1]:.1f}..{s_hi[1]:.1f}; "
        f"target spans x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}"
    )


def cloud_to_cloud(source, target, transform=None) -> np.ndarray:
    """Distance from each source point (after ``transform``) to its nearest target point, shape (n,).

    References
    ----------
    .. [1] Notebook 10, section 1 (why C2C is not a change measure).
    .. [2] D. Girardeau-Montaut, M. Roux, R. Marc, G. Thibault (2005): Change detection on points
       cloud data acquired with a ground laser scanner. International Archives of the
       Photogrammetry, Remote Sensing and Spatial Information Sciences 36(3/W19), 30-35.
    .. [3] J. H. Friedman, J. L. Bentley, R. A. Finkel (1977): k-d tree search, doi:10.1145/355744.355745.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.change.distances import cloud_to_cloud
    >>> target = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> cloud_to_cloud(target + [0, 0, 0.05], target).round(3).tolist()
    [0.05, 0.05, 0.05]
    """
    src, tgt = _prepared(source, target, transform)
    origin = local_origin(tgt)
    dist, _ = cKDTree(reduce(tgt, origin)).query(reduce(src, origin), k=1, workers=-1)
    return dist


def point_to_plane_distance(source, target, target_normals=None, *, k: int = 10, transform=None) -> np.ndarray:
    """Signed distance from each source point to the tangent plane of its nearest target point.

    d_i = n_j . (p_i - q_j) (eq. 4), with q_j the nearest target point and n_j its
    unit normal (``target_normals`` or PCA normals of ``k`` neighbours). Positive
    means the source point lies above (on the normal side of) the target surface.

    Given normals of any non-zero length are scaled to unit length. Where n_j is
    unknown - NaN (a degenerate neighbourhood) or of zero length - d_i is NaN,
    never 0; ``np.isnan(d).sum()`` counts those points. If no target point has a
    usable normal, :class:`~labkit.core.errors.DegenerateGeometryError` is raised.

    References
    ----------
    .. [1] Notebook 07, eq. 4; notebook 04, eqs. 1-4 (the PCA normals).
    .. [2] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.
    .. [3] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    A plane z = 0 and points 2 cm above it, between the target points:

    >>> import numpy as np
    >>> from labkit.change.distances import point_to_plane_distance
    >>> g = np.arange(10.0)
    >>> target = np.c_[np.repeat(g, 10), np.tile(g, 10), np.zeros(100)]
    >>> source = np.array([[2.5, 2.5, 0.02], [6.5, 3.5, 0.02]])
    >>> point_to_plane_distance(source, target, k=8).round(3).tolist()
    [0.02, 0.02]
    """
    src, tgt = _prepared(source, target, transform)
    if target_normals is None:
        from ..features import normals

        nrm = normals(tgt, k=count(k, "k", minimum=3))
    else:
        nrm = _unit_normals(target_normals, tgt.shape)
    origin = local_origin(tgt)
    q, p = reduce(tgt, origin), reduce(src, origin)
    _, j = cKDTree(q).query(p, k=1, workers=-1)
    return np.einsum("ij,ij->i", nrm[j], p - q[j])  # (eq. 4)


def _unit_normals(target_normals, shape) -> np.ndarray:
    """Given normals as unit vectors; NaN rows for NaN or zero-length ones (unknown normals)."""
    try:
        nrm = np.array(target_normals, dtype=np.float64)
    except (TypeError, ValueError):
        raise LabkitError(f"target_normals must be numbers with shape {shape}") from None
    if nrm.shape != shape:
        raise LabkitError(f"target_normals must have shape {shape}, got {nrm.shape}")
    if np.isinf(nrm).any():
        raise LabkitError("target_normals contain infinite values")
    length = np.linalg.norm(nrm, axis=1)
    usable = np.isfinite(length) & (length > 0)
    if not usable.any():
        raise DegenerateGeometryError(f"none of the {len(nrm)} target normals is usable (all NaN or zero length)")
    nrm[~usable] = np.nan
    nrm[usable] /= length[usable, None]
    return nrm


#: Neighbour whose distance is a target point's local spacing (the coverage rule; exact copies count once).
COVERAGE_K = 6
#: A source point is covered when its offset along the target surface is at most this many local spacings.
COVERAGE_FACTOR = 1.5


@dataclass(frozen=True, eq=False, repr=False)
class DistanceChange(ReportMixin):
    """Distances of the source to the target before and after a transformation.

    ``covered`` (bool per source point, or None: all) marks the points where the target
    covers the ground (module notes); :meth:`stats` uses only those by default, the others
    are counted in ``n_outside`` and reported apart. The mask is taken at the transformed
    positions and used for both before and after, so both describe the same points.
    Points without a distance (NaN: their nearest target point has no usable
    normal) are left out of :meth:`stats` and counted in ``n_undetermined``.
    """

    before: np.ndarray
    after: np.ndarray
    kind: str
    covered: np.ndarray | None = None

    @property
    def n_undetermined(self) -> int:
        """Points without a distance (NaN) after the transformation."""
        return int(np.isnan(self.after).sum())

    @property
    def n_outside(self) -> int:
        """Source points outside the target's coverage (left out of the statistics)."""
        return 0 if self.covered is None else int((~self.covered).sum())

    def stats(self, which: str = "after", part: str = "covered") -> dict:
        """Median |d|, RMS, mean, 95 % quantile of |d| (m) over the points that have a distance; their count ``n``.

        ``part``: ``'covered'`` (default: where the target covers the ground), ``'outside'``
        (the rest) or ``'all'``.
        """
        choice(which, ("before", "after"), "which")
        choice(part, ("covered", "outside", "all"), "part")
        d = self.before if which == "before" else self.after
        if self.covered is not None and part != "all":
            d = d[self.covered if part == "covered" else ~self.covered]
        d = d[np.isfinite(d)]
        if d.size == 0:
            nan = float("nan")
            return {"median_abs": nan, "rms": nan, "mean": nan, "q95_abs": nan, "n": 0}
        a = np.abs(d)
        return {"median_abs": float(np.median(a)), "rms": float(np.sqrt(np.mean(d**2))),
                "mean": float(np.mean(d)), "q95_abs": float(np.quantile(a, 0.95)), "n": int(d.size)}

    def _report(self):
        rows = []
        if self.covered is not None:
            rows.append(("covered by the target", f"{len(self.after) - self.n_outside} points (statistics below)"))
        for which in ("before", "after"):
            s = self.stats(which)
            rows.append((which, f"median |d| {s['median_abs']:.4f} m, RMS {s['rms']:.4f} m, "
                                f"mean {s['mean']:+.4f} m, 95% |d| {s['q95_abs']:.4f} m"))
        if self.n_outside:
            s = self.stats("after", "outside")
            rows.append(("outside its coverage", f"{self.n_outside} points ({100 * self.n_outside / len(self.after):.1f} %"
                                                 f", left out; after: median |d| {s['median_abs']:.4f} m, "
                                                 f"RMS {s['rms']:.4f} m)"))
        if self.n_undetermined:
            rows.append(("without a distance", f"{self.n_undetermined} points (no usable target normal; left out)"))
        return f"Distances ({self.kind}, {len(self.after)} points)", [("", rows)]


def distances_before_after(source, target, transform, *, kind: str = "point_to_plane", k: int = 10,
                           target_normals=None, progress=False, coverage: bool = True) -> DistanceChange:
    """Distances of ``source`` to ``target`` without and with ``transform`` (4x4, result or reference).

    With ``coverage`` (default) the statistics use only the source points whose transformed
    position the target covers (module notes: offset along the target's tangent plane at most
    :data:`COVERAGE_FACTOR` local spacings); the others are counted apart
    (:attr:`DistanceChange.n_outside`), so the part of one epoch outside the other's
    coverage does not inflate the RMS after registration.

    ``progress`` (bool, "bar", "lines" or callable, see :mod:`labkit.core.progress`) reports the two
    passes ("before", "after") over the source points, chunk by chunk; default silent.

    Built for large clouds: one compiled kd-tree of the target (in a local frame)
    serves both passes; the source is queried in chunks of :data:`CHUNK` points on all cores,
    in small cells of about :data:`GROUP` points that walk the tree together, each chunk before
    and after the transformation in turn (the nearest point before is the first candidate after);
    the target normals (PCA of ``k`` neighbours, exact duplicates merged, oriented up - the
    normals of :func:`labkit.features.normals`) are computed only at the target points that are
    somebody's nearest neighbour, not for the whole target, and the same neighbour search gives
    the local spacing of the coverage rule. Same values as :func:`point_to_plane_distance` and
    :func:`cloud_to_cloud`.

    References
    ----------
    .. [1] Notebook 07, section 3, eq. 4.
    .. [2] Y. Chen, G. Medioni (1992): Object modelling by registration of multiple range images.
       Image and Vision Computing 10(3), 145-155.

    Examples
    --------
    A plane and the same plane 3 cm higher; the registration takes the 3 cm away:

    >>> import numpy as np
    >>> from labkit.change.distances import distances_before_after
    >>> from labkit.transforms import make_transform
    >>> g = np.arange(20.0)
    >>> target = np.c_[np.repeat(g, 20), np.tile(g, 20), np.zeros(400)]
    >>> down = make_transform(np.eye(3), [0, 0, -0.03])
    >>> change = distances_before_after(target[::3] + [0.5, 0.5, 0.03], target, down)
    >>> round(float(np.median(np.abs(change.before))), 3), float(np.max(np.abs(change.after))) < 1e-9
    (0.03, True)
    """
    T = as_matrix(transform)
    choice(kind, ("point_to_plane", "cloud_to_cloud"), "kind")
    src = as_points(source, name="source")
    tgt = as_points(target, min_points=3 if kind == "point_to_plane" else 1, name="target")
    check_overlap(src, tgt)
    try:  # an even subset overlapping is enough; else the exact check on every moved point
        check_overlap(apply_transform(T, src[:: max(1, len(src) // 100_000)]), tgt)
    except EmptyRegionError:
        check_overlap(apply_transform(T, src), tgt)
    nrm = None
    if kind == "point_to_plane":
        k = count(k, "k", minimum=3)
        if target_normals is not None:
            nrm = _unit_normals(target_normals, tgt.shape)
        elif k > len(tgt):
            raise LabkitError(f"k must lie between 3 and the number of target points ({len(tgt)}), got {k}")
    origin = local_origin(tgt)
    # the tree ICP built on this target is reused (labkit register: no second build, no second copy)
    tree = local_tree(tgt, origin, merge_duplicates=nrm is None and kind == "point_to_plane")
    n = len(src)
    # neighbouring queries in small groups that walk the tree together (its nodes stay in cache)
    order, starts = _spatial_order(src)
    with progress_steps(progress, 2 * n, f"distances ({kind})", "pts") as step:
        passes = _nearest(tree, src, order, starts, T, origin, tgt, kind, step)
    kk = min(COVERAGE_K, len(tgt) - 1)
    if kind == "cloud_to_cloud":
        covered = _covered(tree, tgt, src, T, passes[1][1], None, kk) if coverage else None
        return DistanceChange(passes[0][0], passes[1][0], kind, covered)
    spacing = None
    if nrm is None:  # normals only at the target points that are used (a nearest neighbour)
        used = np.zeros(len(tgt), dtype=bool)
        for _, j, _ in passes:
            used[j] = True
        at = np.flatnonzero(used)
        del used
        at = at[np.argsort(tree.representative[at], kind="stable")]  # leaf order: coherent neighbour searches
        nrm = np.full((len(tgt), 3), np.nan, dtype=np.float32)
        # the coverage spacing (distance to the kk-th neighbour) from the normals' own neighbour search
        fuse = coverage and 1 <= kk < min(k, tree.n)
        spacing = np.zeros(len(tgt)) if fuse else None
        with progress_steps(progress, len(at), "normals", "pts") as step:  # of the used target points
            nrm[at] = _normals_at(tree, at, k, step, spacing, kk)
    before = _dot(nrm, *passes[0][1:])
    if not coverage:
        return DistanceChange(before, _dot(nrm, *passes[1][1:]), kind, None)
    after = np.empty(n)  # filled with the coverage test, from the same normals and offsets
    covered = _covered(tree, tgt, src, T, passes[1][1], nrm, kk, passes[1][2], spacing, after)
    return DistanceChange(before, after, kind, covered)


def _covered(tree, tgt, src, T, j, nrm, kk, v=None, spacing=None, dist=None):
    """Coverage of the moved source points: |offset along the tangent plane at q_j| <= factor x spacing(q_j).

    The offset p - q_j is split into its part along the target normal n_j (the change,
    not looked at) and the rest; without a normal (cloud to cloud, or an unusable one)
    the horizontal part is used. The spacing of q_j is the distance to its
    ``kk`` = :data:`COVERAGE_K`-th neighbour, at least half the median spacing (exact copies)
    of the used target points; ``spacing`` (per target row, optional) gives it where it is
    known already, else it is searched here. ``dist`` (optional, with ``nrm`` and ``v``) receives
    the point-to-plane distances n_j . v of these points (:func:`_dot`), taken on the way.
    """
    used = np.zeros(len(tgt), dtype=bool)
    used[j] = True
    used = np.flatnonzero(used)
    if spacing is None:
        spacing = np.zeros(len(tgt))
        spacing[used] = _kth_distance(tree, used, kk)
    floor = 0.5 * float(np.median(spacing[used]))
    del used
    out = np.empty(len(j), dtype=bool)
    for a in range(0, len(j), CHUNK):
        sl = slice(a, a + CHUNK)
        off = (apply_transform(T, src[sl]) - tgt[j[sl]]) if v is None else v[sl].astype(np.float64)
        n = None if nrm is None else nrm[j[sl]].astype(np.float64)
        if n is None:
            along = np.hypot(off[:, 0], off[:, 1])
        else:
            d = np.einsum("ij,ij->i", n, off)  # (eq. 4); NaN where the normal is unknown
            if dist is not None:
                dist[sl] = d
            ok = np.isfinite(n).all(axis=1)
            n = np.where(ok[:, None], n, 0.0)
            tang = off - np.where(ok, d, 0.0)[:, None] * n  # (I - n n^T)(p - q_j)
            along = np.where(ok, np.linalg.norm(tang, axis=1), np.hypot(off[:, 0], off[:, 1]))
        out[sl] = along <= COVERAGE_FACTOR * np.maximum(spacing[j[sl]], floor)
    return out


def _leaf_positions(tree):
    """Leaf position of (the kept copy of) every row of the tree's cloud."""
    rep = tree.representative
    if rep is None:
        rep = np.empty(len(tree.indices), dtype=np.intp)
        rep[tree.indices] = np.arange(len(tree.indices))
    return rep


def _kth_distance(tree, rows, kk):
    """Distance from each target point ``rows`` to its ``kk``-th neighbour (0 where there is none).

    The points are the tree's own: they are searched in the tree's leaf order (neighbouring
    queries in turn, the visited leaves stay in cache; 3-4x faster than in row order), and the
    distance is taken from the neighbour's coordinates as the search computes it.
    """
    out = np.zeros(len(rows))
    if kk < 1 or len(rows) == 0:
        return out
    pos = _leaf_positions(tree)[rows]
    order = np.argsort(pos, kind="stable")
    for a in range(0, len(rows), CHUNK):
        at = order[a : a + CHUNK]
        out[at] = _neighbour_distance(tree, pos[at], tree.query_leaf_positions(pos[at], kk + 1, workers=-1)[:, -1])
    return out


def _neighbour_distance(tree, pos, nb):
    """Distance between the tree points ``pos`` and ``nb`` (leaf positions; 0 where ``nb`` is -1, none)."""
    X = tree.data
    found = nb >= 0  # fewer than kk + 1 (distinct) points: no spacing
    dx, dy, dz = (X[np.where(found, nb, 0)] - X[pos]).T
    return np.where(found, np.sqrt(dx * dx + dy * dy + dz * dz), 0.0)


def _dot(nrm, j, v):
    """d_i = n_j . (p_i - q_j) (eq. 4) in float64, chunk by chunk."""
    out = np.empty(len(j))
    for a in range(0, len(j), CHUNK):
        out[a : a + CHUNK] = np.einsum("ij,ij->i", nrm[j[a : a + CHUNK]].astype(np.float64), v[a : a + CHUNK])
    return out


#: Source points per chunk of :func:`distances_before_after` (bounded temporaries on 10-million-point clouds).
CHUNK = 1_000_000


#: Source points per group of :func:`_spatial_order` (about a kd-tree leaf: the group walks the tree together).
GROUP = 24


def _spatial_order(points, per_cell=GROUP):
    """Order of the points by cubic cells holding about ``per_cell`` points each (on a surface),
    and the start of every cell's run in that order (then ``len(points)``)."""
    lo, hi = extent(points)
    ext = np.sort(hi - lo)[::-1]
    h = max(float(np.sqrt(ext[0] * max(ext[1], 1e-9) * per_cell / max(len(points), 1))), 1e-6)
    cell = np.floor((points - lo) / h).astype(np.int64)
    m = cell.max(axis=0, initial=0) + 1
    key = (cell[:, 0] * m[1] + cell[:, 1]) * m[2] + cell[:, 2]
    del cell
    order = np.argsort(key)  # (the order within a cell does not matter: 3x faster than a stable sort)
    key = key[order]
    return order, np.append(np.flatnonzero(np.r_[True, key[1:] != key[:-1]]), len(key))


def _nearest(tree, src, order, starts, transform, origin, tgt, kind, report):
    """Nearest target point of every source point, before and after ``transform``: per pass the
    distance (cloud to cloud only), target row and p - q_j (float32; point to plane only).

    The source is visited in ``order``, chunk by chunk of whole groups ``starts``
    (:func:`_spatial_order`), each group's points searched together
    (:meth:`~labkit.neighbours.kdtree.KDTree.nearest_in_groups`: the per-point search's answer,
    ties included); a chunk is searched before and after the transformation in turn, the nearest
    point before being the first candidate after (a small move: a shorter search, the same answer).
    The results are scattered back to the source's rows.
    """
    n = len(src)
    c2c = kind == "cloud_to_cloud"
    passes = [(np.empty(n) if c2c else None, np.empty(n, dtype=np.int32 if len(tgt) < 2**31 else np.int64),
               None if c2c else np.empty((n, 3), dtype=np.float32)) for _ in range(2)]
    cuts = np.unique(np.append(starts[np.searchsorted(starts, np.arange(0, n, CHUNK))], n))
    for a, b in zip(cuts[:-1], cuts[1:]):
        rows = order[a:b]
        groups = starts[np.searchsorted(starts, a) : np.searchsorted(starts, b) + 1] - a
        p = src[rows]
        warm = np.full(len(rows), -1, dtype=np.intp)  # leaf position of the nearest point, for the next pass
        for (dist, j, v), name in zip(passes, ("before", "after")):
            if name == "after":
                p = apply_transform(transform, p)
            d, jj = tree.nearest_in_groups(p - origin, groups, workers=-1, warm=warm)
            if c2c:
                dist[rows] = d
            else:
                v[rows] = p - tgt[jj]  # float32: mm on offsets of metres (the plane distance is taken in float64)
            j[rows] = jj
            report(len(p), info=name)
    return passes


def _normals_at(tree, at, k, report, spacing=None, kk=None):
    """PCA normals (oriented up) of k neighbours at the target points ``at`` (features.normals, chunked).

    With ``spacing`` (per target row), the distance of every point ``at`` to its ``kk``-th
    neighbour (kk < k) is written there, taken from the same neighbour search."""
    from ..features import pca_at

    rep = _leaf_positions(tree)

    def seen(rows, nb):
        spacing[at[rows]] = _neighbour_distance(tree, rep[at[rows]], nb[:, kk])

    return pca_at(tree, at, k, chunk_size=CHUNK, step=report, seen=None if spacing is None else seen)[0]


def _prepared(source, target, transform):
    check_same_crs(source, target, "distances")
    src = as_points(source, name="source")
    tgt = as_points(target, name="target")
    if transform is not None:
        src = apply_transform(as_matrix(transform), src)
    check_overlap(src, tgt)
    return src, tgt
