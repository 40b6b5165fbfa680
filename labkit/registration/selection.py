"""Which points a registration uses: stable classes, or surfaces without volume scatter (notebook 05, section 2b).

The registration study's step 4 ("Nutzen nur von best. Klassen", local noise to reject or weight): airborne
scans hold surfaces that stay put between epochs (ground, roofs, roads) and volume scatter
(crowns, shrubs) whose points are new samples of a cloud of leaves in every flight. A normal
fitted to a crown is random, and point-to-plane residuals on it pull the horizontal shift while
their spread looks like noise: on real ALS halves with vegetation, ICP and maximum consensus
with all points were decimetres off at a stated few centimetres (benchmarks/bench_trust.py).

:func:`select_points` decides by what the data carry:

- **classified** (both clouds have a ``classification`` with points in the stable classes
  :data:`labkit.core.masks.STABLE_CLASSES` - ground, building, road surface): only those classes;
- **unclassified** (plain arrays, or all points in one unclassified code 0/1): surface points
  only. A point is volume scatter when its k-neighbourhood is rough in absolute terms
  (local noise sigma_n about a local quadric above :data:`SMOOTH_NOISE`) *and* relative to its own
  extent (sigma_n / sqrt(l2) above :data:`MAX_SCATTER`, eq. 5.5b; the quadric keeps curved ground a surface): a crown scatters about as much across as
  along (ratio 0.5-0.9 on the real forests), ground and roofs lie flat (ratio 0.02-0.15; dense
  ground can reach 0.25 from its noise alone, but then sigma_n is 1-2 cm).

Where the selection would leave fewer than :data:`MIN_SELECTED` points in either cloud, all
points are used and the result says so.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace  # noqa: F401  (replace: Examples)

import numpy as np

from ..core.arrays import rows
from ..core.checks import as_points, choice
from ..core.distributions import chi2_sf
from ..core.errors import LabkitError
from ..core.masks import ASPRS_NAMES, STABLE_CLASSES
from ..core.frame import local_origin
from ..neighbours.kdtree import neighbour_rows, unique_kept_neighbours
from ..core.threads import side_by_side
from ..neighbours.treecache import NeighbourRows, forget, keep_neighbours, keep_tree, local_tree, offer_tree
from .matching.local_surface import roughness

__all__ = ["MAX_SCATTER", "MIN_SELECTED", "SELECT", "SMOOTH_NOISE", "ClassCheck", "Selection", "check_other_classes",
           "select_points"]

#: Local noise (m) below which a neighbourhood counts as a surface whatever its extent (ALS ground
#: and roofs: 1-5 cm; crowns: 0.1-0.6 m on the real forests).
SMOOTH_NOISE = 0.05
#: sqrt(l3 / l2) of a k-neighbourhood above which it is volume scatter (when also rougher than
#: SMOOTH_NOISE): a flat neighbourhood has l3 << l2, a ball of leaves l3 ~ l2.
MAX_SCATTER = 0.2
#: Fewer selected points than this in either cloud: all points are used.
MIN_SELECTED = 50
#: Points per chunk of the surface test (bounds its memory on clouds of many millions of points).
CHUNK = 500_000
#: Clouds of at most this many points keep the neighbours of the surface test for ICP's normals
#: (ICP then searches only the points next to a point left out; 8 bytes per point and neighbour).
KEEP_NEIGHBOURS = 2_000_000
#: The choices of ``select``.
SELECT = ("auto", "all")
#: Codes that mean "not classified" (a cloud with only these carries no classification).
UNCLASSIFIED = (0, 1)


@dataclass(frozen=True, eq=False)
class Selection:
    """Which points of the two clouds a registration used, and why.

    Attributes
    ----------
    rule : str
        'stable classes', 'surface points' or 'all points'.
    classes : tuple of int
        The classes used ('stable classes'), else empty.
    n_source, n_target : int
        Points given.
    used_source, used_target : int
        Points kept.
    reason : str
        One line for the result's message and summary.
    source_rows, target_rows : ndarray of int or None
        The rows of the given clouds that were kept (None: all).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ground = np.column_stack([rng.uniform(0, 20, (800, 2)), rng.normal(0, 0.02, 800)])
    >>> crown = rng.normal([10, 10, 8], 1.5, (400, 3))  # volume scatter
    >>> _, _, sel = select_points(np.vstack([ground, crown]), ground)
    >>> sel.rule, sel.used_source < 900, str(sel).startswith("surface points")
    ('surface points', True, True)
    """

    rule: str
    classes: tuple
    n_source: int
    n_target: int
    used_source: int
    used_target: int
    reason: str
    source_rows: np.ndarray | None = None
    target_rows: np.ndarray | None = None

    def __str__(self):
        return self.reason


def _classes(cloud):
    attrs = getattr(cloud, "attributes", None)
    if attrs is None or "classification" not in attrs:
        return None
    return np.asarray(attrs["classification"])


def _xyz(cloud):
    return np.asarray(getattr(cloud, "xyz", cloud), dtype=np.float64)


def _subset(cloud, mask):
    return cloud.subset(mask) if hasattr(cloud, "subset") else rows(_xyz(cloud), mask)


def surface_mask(points, k=20):
    """True where a point's k-neighbourhood is a surface, False where it is volume scatter.

    One k-nearest-neighbour search per point gives both terms of the test: the PCA's eigenvalues
    and the noise about the local quadric fitted to the same neighbours (fitted only where the
    bound that the plane's residuals set on it leaves the test open: the same answer, see
    :func:`labkit.registration.matching.local_surface.roughness`). The points are walked in
    chunks of whole leaves of about :data:`CHUNK` points (in the kd-tree's leaf order), so that
    memory grows with the cloud's coordinates and its tree, not with the per-point geometry (about
    0.5 GB of it per million points held at once). :func:`select_points` keeps the neighbours of
    clouds up to :data:`KEEP_NEIGHBOURS` points for ICP's normals.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ground = np.column_stack([rng.uniform(0, 20, (800, 2)), rng.normal(0, 0.02, 800)])
    >>> crown = rng.normal([10, 10, 8], 1.5, (400, 3))  # a ball of leaves
    >>> keep = surface_mask(np.vstack([ground, crown]))
    >>> float(keep[:800].mean()) > 0.95, float(keep[800:].mean()) < 0.1
    (True, True)
    """
    return _surface_test(points, k)[0]


def _surface_test(points, k, neighbours=False):
    """:func:`surface_mask`, and with ``neighbours`` (clouds up to :data:`KEEP_NEIGHBOURS` points) also
    (tree, the k neighbours of each distinct point as leaf positions, where they are unique and all kept,
    and their PCA: ICP's normals reuse both where the neighbourhood holds only selected points), else
    None; last the kd-tree of the cloud (reduced to its local origin)."""
    xyz = _xyz(points)
    k = int(min(max(k, 10), len(xyz)))
    # the tree ICP's matching would build on the same array (kept for it when every point stays)
    tree = local_tree(xyz, local_origin(xyz), merge_duplicates=True)
    cols = np.ascontiguousarray(tree.data.T)
    k = min(k, tree.n)
    kept = neighbours and len(xyz) <= KEEP_NEIGHBOURS and k < tree.n  # (k = n: every neighbourhood is the whole cloud)
    keep = np.empty(tree.n, dtype=bool)  # per distinct point, in leaf order
    leaves = tree.leaf_bounds
    cut = np.unique(leaves[np.searchsorted(leaves, np.arange(0, tree.n, CHUNK))].tolist() + [tree.n])
    nbs, ties, lams, vecs = [], [], [], []
    for a, b in zip(cut[:-1], cut[1:]):  # chunks of whole leaves
        keep[a:b], nb, pca = _surface_rows(tree, cols, a, b, k, kept)
        if kept:
            nbs.append(nb[0])
            ties.append(nb[1])
            lams.append(pca[0])
            vecs.append(pca[1])
    if not kept:
        return keep[tree.representative], None, tree
    one = len(nbs) == 1  # one chunk (most clouds): no copy of (n, k) indices
    nb, tie = (nbs[0], ties[0]) if one else (np.concatenate(nbs), np.concatenate(ties))
    pca = (lams[0], vecs[0]) if one else (np.concatenate(lams), np.concatenate(vecs))
    clean = np.empty(tree.n, dtype=bool)  # the same k nearest among the kept points
    unique_kept_neighbours(nb, keep, tie, clean)
    return keep[tree.representative], (tree, nb, clean, k, pca), tree


def _kept_rows(info, mask):
    """The neighbours of ``_surface_test`` as rows of the selected points ``mask`` (:class:`NeighbourRows`; the
    rows are made when first asked for: ICP's local plane needs only the kept PCA)."""
    tree, nb, clean, k, (lam, vecs) = info
    pos = tree.representative[np.flatnonzero(mask)]

    def rows():
        new = np.cumsum(mask) - 1  # row among the selected points of every input row
        out = np.zeros((len(pos), k), dtype=np.int32 if len(pos) < 2**31 else np.int64)
        neighbour_rows(nb, pos, tree.indices, new, clean, k, out)
        return out

    return NeighbourRows(rows, clean[pos], k, (lam, vecs, pos))  # the PCA of every distinct point, and where


def _is_surface(noise, lam):
    """The test of :func:`surface_mask` on the noise (m,) and the eigenvalues (m, 3), ascending (monotone in the noise)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return (noise <= SMOOTH_NOISE) | (noise / np.sqrt(lam[:, 1]) <= MAX_SCATTER)


def _surface_rows(tree, cols, a, b, k, ties=False):
    """The surface test of :func:`surface_mask` at the tree's distinct points ``a..b-1`` (leaf bounds), and
    their k neighbours (with ``ties``: and the search's tie flags) and their PCA
    (:func:`~labkit.registration.matching.local_surface.roughness`)."""
    noise, lam, nb, pca = roughness(tree, cols, a, b, k, decided=_is_surface, ties=ties, pca=True)  # l3, l2, l1
    # the spread about a local quadric: a curved surface (sparse hills, a sphere) is no volume
    noise = np.where(np.isfinite(noise), noise, np.sqrt(lam[:, 0]))
    with np.errstate(invalid="ignore"):
        valid = (lam[:, 1] > 1e-12 * lam[:, 2]) & np.isfinite(lam[:, 2])  # not a point, not a line (features.determined)
    return valid & _is_surface(noise, lam), nb, pca


def select_points(source, target, select="auto", k=20):
    """The points of ``source`` and ``target`` a registration should use (module docstring).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
    select : {'auto', 'all'}
        'auto': stable classes of classified clouds, surface points of unclassified ones; 'all': every point.
    k : int
        Neighbours of the local PCA for the surface test.

    Returns
    -------
    source, target
        The selected points (PointClouds keep their attributes).
    Selection
        What was used and why.

    References
    ----------
    .. [1] Notebook 05, section 2b; the registration study, step 4 (classes, local noise to reject or weight).
    .. [2] M. Weinmann, B. Jutzi, S. Hinz, C. Mallet (2015): Semantic point cloud interpretation based on
       optimal neighborhoods, relevant features and efficient classifiers. ISPRS Journal of
       Photogrammetry and Remote Sensing 105, 286-304.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit import PointCloud
    >>> rng = np.random.default_rng(0)
    >>> xyz = np.column_stack([rng.uniform(0, 20, (600, 2)), rng.normal(0, 0.02, 600)])
    >>> cls = np.where(np.arange(600) < 400, 2, 5)  # ground and high vegetation
    >>> cloud = PointCloud(xyz, {"classification": cls})
    >>> src, tgt, sel = select_points(cloud, cloud)
    >>> sel.rule, sel.classes, len(src.xyz)
    ('stable classes', (2,), 400)
    """
    choice(select, SELECT, "select")
    ns = len(as_points(source, name="source"))  # bad input is named before any neighbourhood is computed
    nt = len(as_points(target, name="target"))
    if select == "all":
        return source, target, Selection("all points", (), ns, nt, ns, nt, "all points (select='all')")
    cs, ct = _classes(source), _classes(target)
    if cs is not None and ct is not None:
        present = set(np.unique(cs).tolist()) | set(np.unique(ct).tolist())
        if not present <= set(UNCLASSIFIED):  # a real classification
            stable = tuple(c for c in STABLE_CLASSES if c in present)
            ms, mt = np.isin(cs, stable), np.isin(ct, stable)
            if stable and ms.sum() >= MIN_SELECTED and mt.sum() >= MIN_SELECTED:
                names = ", ".join(f"{c} ({ASPRS_NAMES.get(c, '?')})" for c in stable)
                left = sorted(present - set(stable))
                reason = (f"stable classes {names}: {ms.sum():,} of {ns:,} source and {mt.sum():,} of {nt:,} target "
                          f"points" + (f"; classes {', '.join(map(str, left))} left out (they may move or "
                                       "scatter between epochs)" if left else ""))
                return (_subset(source, ms), _subset(target, mt),
                        Selection("stable classes", stable, ns, nt, int(ms.sum()), int(mt.sum()), reason,
                                  np.flatnonzero(ms), np.flatnonzero(mt)))
    if min(ns, nt) <= 3:
        return source, target, Selection("all points", (), ns, nt, ns, nt, "all points (too few for a local surface)")
    # the two clouds side by side, each to the end of its own work (its surface test, selected points,
    # neighbour rows for ICP and its selected points' tree): one cloud's serial steps overlap the other's
    # work; the same numbers as one after the other
    shared = _Shared()
    (ms, tree_s, src, rows_s, cut_s), (mt, tree_t, tgt, rows_t, cut_t) = side_by_side(
        (_select_one, source, k, shared, False), (_select_one, target, k, shared, True))
    if ms.all() and mt.all():
        xyz_t = _xyz(target)
        keep_tree(xyz_t, local_origin(xyz_t), True, tree_t)  # ICP's matching asks for the target's tree next
        _keep_rows((source, rows_s), (target, rows_t))
        return source, target, Selection("all points", (), ns, nt, ns, nt, "all points (every neighbourhood a surface)")
    if ms.sum() < MIN_SELECTED or mt.sum() < MIN_SELECTED:
        return source, target, Selection(
            "all points", (), ns, nt, ns, nt,
            f"all points: fewer than {MIN_SELECTED} surface points ({ms.sum()}, {mt.sum()}) - volume scatter kept")
    forget()  # the kept tree is the whole target's, and ICP builds its own on the surface points
    reason = (f"surface points: {ms.sum():,} of {ns:,} source and {mt.sum():,} of {nt:,} target points; volume "
              f"scatter (vegetation) left out: local noise > {100 * SMOOTH_NOISE:.0f} cm and noise/sqrt(l2) > "
              f"{MAX_SCATTER:g} in {k}-neighbourhoods")
    src = _subset(source, ms) if src is None else src
    tgt = _subset(target, mt) if tgt is None else tgt
    _keep_rows((src, rows_s), (tgt, rows_t))  # ICP's normals reuse the neighbourhoods that only hold selected points
    # ICP's matching takes the selected points' trees cut from the whole clouds' (in ICP's frame: the local
    # origin of the target's selected points) instead of new builds
    origin = local_origin(_xyz(tgt)) if shared.origin is None else shared.origin
    for sub, tree, mask, cut in ((src, tree_s, ms, cut_s), (tgt, tree_t, mt, cut_t)):
        xyz = _xyz(sub)
        offer_tree(xyz, origin, True, cut if cut is not None else tree.restricted(mask, xyz - origin))
    return (src, tgt, Selection("surface points", (), ns, nt, int(ms.sum()), int(mt.sum()), reason,
                                np.flatnonzero(ms), np.flatnonzero(mt)))


class _Shared:
    """What the target's thread of :func:`select_points` hands the source's once known (``ready``): its mask
    and the local origin of its selected points (ICP's frame; None where it keeps every point or failed)."""

    def __init__(self):
        self.ready = threading.Event()
        self.mask = self.origin = None


def _select_one(cloud, k, shared, is_target):
    """One cloud's part of :func:`select_points`: (mask, whole cloud's tree, selected points or None where
    every point stays, their :class:`NeighbourRows` or None, their tree cut from the whole cloud's or None).
    All of it is made before the other cloud's mask is known, except the cut tree, which waits for the
    origin of the target's selected points (ICP's frame; made here only where this cloud and the target
    both leave points out, otherwise :func:`select_points` cuts it where needed)."""
    try:
        mask, info, tree = _surface_test(cloud, k, True)
        sub = None if mask.all() else _subset(cloud, mask)
        if is_target:
            shared.mask = mask
            shared.origin = None if sub is None else local_origin(_xyz(sub))
    finally:
        if is_target:
            shared.ready.set()
    rows = None if info is None else _kept_rows(info, mask)
    cut = None
    if sub is not None and mask.sum() >= MIN_SELECTED:
        shared.ready.wait()
        if shared.origin is not None and shared.mask.sum() >= MIN_SELECTED:
            cut = tree.restricted(mask, _xyz(sub) - shared.origin)
    return mask, tree, sub, rows, cut


def _keep_rows(*clouds):
    """Keep the neighbour rows of each (cloud, rows or None) for ICP's normals."""
    for cloud, rows in clouds:
        if rows is not None:
            keep_neighbours(_xyz(cloud), rows)


@dataclass(frozen=True, eq=False)
class ClassCheck:
    """A class left out of a registration, tested against the shift of the stable classes.

    The class's points are registered on their own (source class onto target class, from the result: ICP's
    ``class_shift`` matches them once and adds one translation step) and its shift at the class's centre is
    compared with the result's: T = d^T (C_c + C)^-1 d over the axes both determine, chi-square with that many
    degrees of freedom (eq. 5.16 for two groups).

    Attributes
    ----------
    code : int
        The class (ASPRS code).
    name : str
    n_source, n_target : int
        Points of the class in the two clouds.
    offset, offset_std : ndarray (3,)
        The class's shift minus the result's (m) and its standard deviation (NaN where not determined).
    statistic : float
    dof : int
    p_value : float
    alpha : float
    note : str
        Why the class was not tested (empty when it was).

    Examples
    --------
    >>> import numpy as np
    >>> c = ClassCheck(5, "high vegetation", 900, 880, np.array([0.2, -0.1, 0.0]), np.array([0.03, 0.03, 0.01]),
    ...                 56.0, 3, 4e-12, 1e-3)
    >>> c.agree, str(c).split(":")[0]
    (False, '5 (high vegetation), 900 / 880 points')
    """

    code: int
    name: str
    n_source: int
    n_target: int
    offset: np.ndarray
    offset_std: np.ndarray
    statistic: float
    dof: int
    p_value: float
    alpha: float
    note: str = ""

    @property
    def agree(self) -> bool:
        """True unless the class's shift differs from the result's at level ``alpha``."""
        return not (self.dof > 0 and self.p_value < self.alpha)

    def __str__(self):
        head = f"{self.code} ({self.name}), {self.n_source} / {self.n_target} points"
        if self.note:
            return f"{head}: not tested ({self.note})"
        shift = ", ".join(f"d{a} -" if not np.isfinite(s) else f"d{a} {1000 * o:+.0f}+-{1000 * s:.0f}"
                          for a, o, s in zip("XYZ", self.offset, self.offset_std))
        verdict = "agrees" if self.agree else "MOVED (differs from the stable classes)"
        return f"{head}: {shift} mm against the result, T = {self.statistic:.1f} / {self.dof} -> {verdict}"


def check_other_classes(source, target, result, selection, register, *, alpha=1e-3, **settings):
    """Test every class the selection left out against the result of the stable classes.

    Parameters
    ----------
    source, target : PointCloud
        The caller's clouds (with ``classification``).
    result : RegistrationResult
        The registration on the stable classes.
    selection : Selection
        Its selection (rule 'stable classes'; otherwise nothing is tested).
    register : callable
        The registration of each class from the result, called with ``select='all'`` and
        ``initial=result.matrix`` plus ``settings``: ``icp`` itself, or (as ``icp`` does)
        :func:`labkit.registration.closest_point.class_shift.class_shift`, one matching at the result
        and one translation step.
    alpha : float
        Level of the test.

    Returns
    -------
    tuple of ClassCheck
        One per class present in both clouds with at least :data:`MIN_SELECTED` points in each.

    References
    ----------
    .. [1] Notebook 05, section 2b and eq. 5.16; the registration study, step 4 (classes).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit import PointCloud
    >>> from labkit.registration import icp
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 30, (3000, 2))
    >>> z = 0.5 * np.sin(xy[:, 0] / 3) + 0.4 * np.cos(xy[:, 1] / 4)  # hills in X and Y
    >>> cls = np.where(xy[:, 0] < 20, 2, 6)  # ground and, on the east side, 'buildings'
    >>> cloud = PointCloud(np.column_stack([xy, z + rng.normal(0, 0.005, 3000)]), {"classification": cls})
    >>> moved = cloud.with_xyz(cloud.xyz + np.where(cls[:, None] == 6, [0.0, 0.0, 0.1], 0.0))  # the roofs rise
    >>> src, tgt, sel = select_points(cloud, moved)
    >>> res = icp(cloud.subset(cls == 2), moved.subset(cls == 2), select="all")
    >>> [c.agree for c in check_other_classes(cloud, moved, res, replace(sel, classes=(2,)), icp)]
    [False]
    """
    if selection.rule != "stable classes":
        return ()
    cs, ct = _classes(source), _classes(target)
    out = []
    for code in sorted(set(np.unique(cs).tolist()) & set(np.unique(ct).tolist()) - set(selection.classes)):
        ms, mt = cs == code, ct == code
        name = ASPRS_NAMES.get(code, "?")
        if ms.sum() < MIN_SELECTED or mt.sum() < MIN_SELECTED:
            continue
        nan = np.full(3, np.nan)
        src = _subset(source, ms)
        try:
            own = register(src, _subset(target, mt), select="all", initial=result.matrix, **settings)
        except LabkitError as exc:
            out.append(ClassCheck(code, name, int(ms.sum()), int(mt.sum()), nan, nan, np.nan, 0, 1.0, alpha,
                                  str(exc).split(";")[0]))
            continue
        centre = _xyz(src).mean(axis=0)[None]
        d = (own.apply(centre) - result.apply(centre))[0]  # the class's shift minus the result's, at its centre
        var = own.translation_std**2 + result.translation_std**2
        both = np.isfinite(var) & (var > 0)
        if not both.any():
            out.append(ClassCheck(code, name, int(ms.sum()), int(mt.sum()), nan, nan, np.nan, 0, 1.0, alpha,
                                  "the class determines no axis"))
            continue
        cov = (own.translation_cov + result.translation_cov)[np.ix_(both, both)]
        T = float(d[both] @ np.linalg.solve(cov, d[both]))
        dof = int(both.sum())
        out.append(ClassCheck(code, name, int(ms.sum()), int(mt.sum()), np.where(both, d, np.nan),
                              np.where(both, np.sqrt(var), np.nan), T, dof, float(chi2_sf(T, dof)), float(alpha)))
    return tuple(out)
