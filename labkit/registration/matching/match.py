"""Correspondences between two clouds: the registration study's ``Matching`` (the registration study, steps 2 and 4).

One call of :func:`match` runs the steps of notebook 05, section 2:

1. sampling of the source (density differences; random, voxel or normal-space);
2. exclusion of source points by class and by local noise;
3. nearest-neighbour assignment on a kd-tree of the target (the ALS base);
4. gating: distance, angle between the normals, class and noise of the target point;
5. weights from the a priori precision per class and from the local noise
   (eq. 5.6: p_i = 1 / (sigma_s,i^2 + sigma_t,j^2)).

Every sampled source point gets one row; ``rule`` says which rule (if any)
rejected it, so a plot can colour the points by rule and the report can count them.

Speed: the target's compiled kd-tree (``labkit.neighbours.kdtree``, exact
duplicates merged) and its local geometry are built once per call and cached per
distinct target point (the target does not move); the source is queried in its own
leaf order; the one-source-per-target rule is one O(m) pass, not a sort of all pairs; the
covariance of each target normal's random tilt (ICP's eq. 5.12b) is kept with the normal
instead of being searched and decomposed again.
Points whose neighbourhood is a point or a line have no normal and are rejected
by the rule 'degenerate'.

Large clouds: ``sample='auto'`` (ICP's default) thins a source of more than
:data:`AUTO_LIMIT` points to about :data:`AUTO_PAIRS` (voxel, then normal-space balance); the
geometry of both clouds is computed and stored only at the points used (compact cache); the
matcher reads the target from its kd-tree, which ``labkit.neighbours.treecache`` keeps for the distances.

The parts live in private modules beside this one: the table of correspondences
(``_correspondences``), the local surface at the points (``_local_surface``), the sampling
(``_sampling``) and the matcher that ICP calls in every iteration (``_matcher``).
"""

from __future__ import annotations

import numpy as np

from ...core.checks import as_points, as_rng, choice, positive
from ...core.frame import local_origin, reduce
from ...core.jit import compiled, have_numba
from ...core.threads import side_by_side
from ...neighbours.kdtree import KDTree
from ...neighbours.kdtree_build import in_runs
from ...neighbours.treecache import kept_neighbours, local_tree, take_tree
from ...core.errors import LabkitError
from .correspondences import _CODE, MIN_SIGMA, RULES, Correspondences, _replace  # noqa: F401 - re-exported
from .local_surface import Geometry, _leaf_geometry, _local_geometry, _on_quadric, _plane_tilt  # noqa: F401
from .matcher import (
    _class_sigma, _classes_of, _Matcher, _reject_duplicates, _require_classes, _TreePoints, first_search,
)  # noqa: F401
from ...neighbours.sampling import (
    MAX_VARIATION, auto_sample, normal_space_sample, voxel_keys, voxel_sample,
)  # noqa: F401
from ..options import SURFACES, MatchOptions, takes_match_options

__all__ = [
    "AUTO_LIMIT", "AUTO_PAIRS", "AUTO_QUADRIC_RADIUS", "MAX_VARIATION", "MIN_SIGMA", "RULES", "SURFACES",
    "Correspondences", "match", "prepare",
]  # fmt: skip

# SURFACES (from .options): the local surface models of :func:`match`: the PCA plane (default) or a
# quadric (curved, sparse surfaces); 'auto' chooses by the size of the target's k-neighbourhoods.
#: surface='auto' fits quadrics where the median radius of the target's k-neighbourhoods exceeds this (m).
AUTO_QUADRIC_RADIUS = 1.0

#: sample='auto': a source of at most this many points is used whole; a larger one is thinned to
#: about :data:`AUTO_PAIRS` points (one per voxel, then normal-space balance, see :func:`auto_sample`).
AUTO_LIMIT = 300_000
AUTO_PAIRS = 100_000
#: Queries per target point from which ICP computes the target's normals at every point up front.
WHOLE_TARGET = 0.5


def _sample(points, geometry, spec, rng):
    """Indices of the sampled source points (step 1)."""
    n = len(points)
    if spec is None or (isinstance(spec, str) and spec == "auto" and n <= AUTO_LIMIT):
        return np.arange(n)
    if isinstance(spec, str) and spec == "auto":
        return auto_sample(points, geometry, AUTO_PAIRS, rng)
    if isinstance(spec, str):
        raise LabkitError(f"sample must be None, 'auto', an int or (method, value), got {spec!r}")
    if isinstance(spec, (int, np.integer)):
        spec = ("random", int(spec))
    kind, value = spec
    choice(kind, ("random", "voxel", "normal_space"), "sample method")
    if kind == "voxel":
        return voxel_sample(points, positive(value, "voxel size"), rng)
    m = int(positive(value, "sample size"))
    if m >= n:
        return np.arange(n)
    if kind == "random":
        return np.sort(rng.choice(n, m, replace=False))
    pool = np.sort(rng.choice(n, min(n, 6 * m), replace=False))  # candidates for the normals
    coarse, _, variation = geometry.compute(pool, min(10, geometry.k))  # coarse normals suffice for the bins
    has = np.isfinite(coarse[:, 0])  # no bin for points without a normal (a point or a line)
    if has.sum() >= m:
        pool, coarse, variation = pool[has], coarse[has], variation[has]
    else:
        coarse = np.where(has[:, None], coarse, [0.0, 0.0, 1.0])
    # rare normals are often artefacts of neighbourhoods across an edge: keep planar candidates only
    planar = variation < MAX_VARIATION
    if planar.sum() >= m:
        pool, coarse = pool[planar], coarse[planar]
    return pool[normal_space_sample(coarse, m, rng)]


@takes_match_options
def prepare(
    source,
    target,
    *,
    options: MatchOptions | None = None,
    target_normals=None,
    source_normals=None,
    max_distance=1.0,
    max_angle_deg=30.0,
    classes=None,
    class_sigma=None,
    default_sigma=0.0,
    noise_weighting=True,
    max_noise=None,
    sample=None,
    unique=True,
    k=20,
    rng=None,
    tree=None,
    origin=None,
    surface="plane",
    points=None,
    start=None,
) -> _Matcher:
    """Build the fixed part of the matching once (kd-tree, sampling, exclusions).

    The arguments are those of :func:`match` (the matching options: see
    :class:`~labkit.registration.MatchOptions`); ``origin`` is the shared local
    origin (default: from the target); ``points`` the coordinates of source and target
    as the caller already checked them (:func:`labkit.core.checks.as_points`; default:
    checked here). ICP calls this once and the returned matcher in every iteration. ``start`` (R, t),
    optional: the transformation of the matcher's first call, whose nearest-neighbour search is then made
    here beside the source's normals (the same correspondences).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_surface
    >>> target = wavy_surface(1500, 1, noise=0.0)  # slopes in X and Y, no noise
    >>> matcher = prepare(target[::5] + [0.0, 0.0, 0.02], target)
    >>> corr = matcher(np.eye(3), np.array([0.0, 0.0, -0.02]))  # pairs after moving the source back
    >>> len(corr), bool(np.abs(corr.dz[corr.accepted]).max() < 0.01)
    (300, True)
    """
    opt = options  # checked and complete (takes_match_options); the loose keywords above are not read
    k = opt.k
    if points is None:
        points = as_points(source, min_points=3, name="source"), as_points(target, min_points=3, name="target")
    src, tgt = points
    if k > len(tgt):
        raise LabkitError(f"k must lie between 3 and the number of target points ({len(tgt)}), got {k}")
    rng = as_rng(rng)
    origin = local_origin(tgt) if origin is None else np.asarray(origin, dtype=np.float64)
    src_l = reduce(src, origin)
    if tree is not None and getattr(tree, "n", None) != len(tgt):
        raise LabkitError(f"the given tree holds {getattr(tree, 'n', '?')} points, the target has {len(tgt)}")
    sample = opt.sample
    need_src_geo = (
        opt.max_angle_deg is not None or opt.noise_weighting or opt.max_noise is not None
        or (isinstance(sample, tuple) and sample[0] == "normal_space")
        or (isinstance(sample, str) and sample == "auto" and len(src_l) > AUTO_LIMIT)
    )  # fmt: skip
    if need_src_geo and len(src_l) < k:
        raise LabkitError(f"the source needs at least k = {k} points for its normals, got {len(src_l)}")
    # the target's compiled kd-tree (exact duplicates merged) and its geometry cache: once per call
    # (kept for the next step on the same target, e.g. the distances of labkit register); the source's
    # tree for its normals built beside it (the same trees as one after the other)
    tree, src_tree = side_by_side(
        (local_tree, tgt, origin, True), (lambda: _source_tree(src, src_l, origin) if need_src_geo else None,)
    )
    surface = _auto_surface(tree, k) if opt.surface == "auto" else opt.surface
    quadric = surface == "quadric"
    tgt_geo = Geometry(
        None, k, _given_normals(opt.target_normals, len(tgt), "target_normals"), tree, quadric, keep_tilt=True,
        known=kept_neighbours(tgt, min(k, tree.n)),  # the neighbours the point selection found, where it kept them
    )
    n_tgt = len(tgt)  # the tree holds the target (one copy of a large cloud, read through _TreePoints)
    src_geo = None
    if need_src_geo:
        src_geo = Geometry(
            src_l, k, _given_normals(opt.source_normals, len(src_l), "source_normals"), src_tree, quadric=quadric,
            known=kept_neighbours(src, k),
        )
    # (1) sampling
    idx = _sample(src_l, src_geo, sample, rng)
    # query order: the sampled source points in the leaf order of a kd-tree over them
    src_tree = src_geo.tree if src_geo is not None else KDTree(src_l[idx])
    if src_geo is not None:
        keys = src_tree.representative[idx]
        order = _stable_order(keys, src_tree.n)
        leaf_pos = keys[order]
    else:
        order = np.empty(len(idx), dtype=np.intp)
        order[:] = src_tree.indices
        leaf_pos = np.arange(len(idx))
    groups = _leaf_of(src_tree.leaf_bounds, leaf_pos)  # the source leaf of each query
    settings = dict(  # the matcher's resolved form: no gate is an infinite distance, 'auto' is decided
        max_distance=np.inf if opt.max_distance is None else opt.max_distance,
        max_angle_deg=opt.max_angle_deg,
        classes=None if opt.classes is None else np.asarray(list(opt.classes)),
        class_sigma=dict(opt.class_sigma or {}),
        default_sigma=opt.default_sigma,
        noise_weighting=opt.noise_weighting,
        max_noise=opt.max_noise,
        need_noise=bool(opt.noise_weighting or opt.max_noise is not None),
        sample=sample,
        unique=opt.unique,
        k=k,
        surface=surface,
    )
    # (2) exclusions on the source side and a priori sigma per source point
    src_cls, tgt_cls = _classes_of(source, len(src)), _classes_of(target, len(tgt))
    if opt.classes is not None:
        _require_classes(source, "source")
        _require_classes(target, "target")
    src_pts = np.take(src_l, idx, axis=0)  # (by index: faster than the fancy index)
    normals_of_source = lambda: (None, None) if src_geo is None else src_geo.at(idx, need_noise=True)  # noqa: E731
    if start is None:
        (src_normals, src_noise), memory = normals_of_source(), None
    else:  # the first call's nearest target points, and their geometry, beside the source's normals
        def ahead():
            found = first_search(tree, src_pts, order, groups, *start, settings["max_distance"])
            if tgt_geo.given is None:  # the target's normals at those points: the first call finds them cached
                # where the queries are about as many as the target's points, later steps meet most of them:
                # all at once here, in leaf order (cheaper than in the few batches of the first steps)
                whole = len(src_pts) >= WHOLE_TARGET * tree.n
                tgt_geo.at_positions(np.arange(tree.n) if whole else found[0][found[0] >= 0])
            return found

        (src_normals, src_noise), memory = side_by_side((normals_of_source,), (ahead,))
    rule, sigma = _source_rules(src_cls, idx, src_noise, settings)
    return _Matcher(
        src_pts, idx, src_normals, sigma, rule, _TreePoints(tree, n_tgt), tree, tgt_geo, tgt_cls, settings, origin, len(src),
        None if src_cls is None else src_cls[idx], order, groups, memory,
    )  # fmt: skip


def _leaf_of(bounds, pos):
    """``np.searchsorted(bounds, pos, side="right")`` for ascending ``pos``: one walk along both (the same
    indices); other ``pos`` by the search itself."""
    if not have_numba():  # pragma: no cover - depends on the environment
        return np.searchsorted(bounds, pos, side="right")
    out, ok = compiled(_walk_right)(np.ascontiguousarray(bounds, dtype=np.int64), np.ascontiguousarray(pos, dtype=np.int64))
    return out if ok else np.searchsorted(bounds, pos, side="right")


def _walk_right(bounds, pos):  # pragma: no cover - compiled
    """For each of the ascending ``pos`` the number of ``bounds`` (ascending) at or below it; False when ``pos``
    is not ascending."""
    out = np.empty(pos.shape[0], np.intp)
    j = 0
    nb = bounds.shape[0]
    for i in range(pos.shape[0]):
        x = pos[i]
        if i > 0 and x < pos[i - 1]:
            return out, False
        while j < nb and bounds[j] <= x:
            j += 1
        out[i] = j
    return out, True


def _stable_order(keys, n_keys):
    """``np.argsort(keys, kind="stable")`` of integers in [0, n_keys): by counting (one pass and a scatter, not
    a sort)."""
    if not have_numba():  # pragma: no cover - depends on the environment
        return np.argsort(keys, kind="stable")
    return compiled(_counting_order)(np.ascontiguousarray(keys, dtype=np.int64), int(n_keys))


def _counting_order(keys, n_keys):  # pragma: no cover - compiled
    start = np.zeros(n_keys + 1, np.int64)
    for i in range(keys.shape[0]):
        start[keys[i] + 1] += 1
    for v in range(n_keys):
        start[v + 1] += start[v]
    order = np.empty(keys.shape[0], np.intp)
    for i in range(keys.shape[0]):  # rows in ascending order: equal keys keep it (stable)
        order[start[keys[i]]] = i
        start[keys[i]] += 1
    return order


def _source_tree(src, src_l, origin):
    """The source's kd-tree: the one made ahead for this array (the point selection's), else built on ``src_l``."""
    tree = take_tree(src, origin, True)
    return KDTree(src_l, merge_duplicates=True) if tree is None else tree


def _auto_surface(tree, k):
    """'quadric' where the target's k-neighbourhoods are wide (sparse ALS), else 'plane' (TLS, dense DIM).

    A plane fitted to a neighbourhood of radius r on ground curved with radius R misses the surface
    by up to the sagitta r^2 / (2 R); its point-to-plane residuals carry that offset, and weighted by
    the slopes it biases the weak horizontal shift (real ALS halves at 2.7 pts/m^2: X 13 mm off at a
    stated 3.5 mm with the plane, 1.5 mm at a stated 2.9 mm with the quadric). Within r = 1 m the
    sagitta of natural ground (R > 100 m) stays below 5 mm and averages out over the neighbourhood,
    and the plane - robust at edges, cheaper, with the better known tilt noise that
    determinability relies on (eq. 5.12b) - is kept (dense ALS above about 6 pts/m^2, TLS). r is the median distance of the k-th neighbour over an even subset of at
    most 2000 target points; k < 10 leaves too few points for a quadric.
    """
    if k < 10 or tree.n <= k:
        return "plane"
    step = max(1, tree.n // 2000)
    q = tree.data[::step]
    dist = np.empty(len(q))

    def run(a, b):  # two halves side by side: too few queries for the tree's own threads, the same answers
        dist[a:b] = tree.query(q[a:b], k=k, workers=1)[0][:, -1]

    in_runs(run, [0, len(q) // 2, len(q)], 2)
    return "quadric" if float(np.median(dist)) > AUTO_QUADRIC_RADIUS else "plane"


def _given_normals(normals, n, name):
    if normals is None:
        return None
    arr = as_points(normals, name=name)
    if len(arr) != n:
        raise LabkitError(f"{name} must have one normal per point ({n}), got {len(arr)}")
    length = np.linalg.norm(arr, axis=1, keepdims=True)
    if (length < 1e-12).any():
        raise LabkitError(f"{name} contains zero-length normals")
    return arr / length


def _source_rules(cls, idx, noise, opt):
    """Rule codes (class, noise) and a priori sigma for the sampled source points."""
    rule = np.zeros(len(idx), dtype=np.int8)
    var = np.zeros(len(idx))
    if cls is not None:
        c = cls[idx]
        if opt["classes"] is not None:
            rule[~np.isin(c, opt["classes"])] = _CODE["class"]
        if opt["class_sigma"]:
            s = _class_sigma(c, opt["class_sigma"])
            var += np.where(np.isnan(s), opt["default_sigma"], s) ** 2
    if opt["max_noise"] is not None:
        rule[(noise > opt["max_noise"]) & (rule == 0)] = _CODE["noise"]
    if opt["noise_weighting"]:
        var += noise**2
    if not opt["class_sigma"] and not opt["noise_weighting"]:
        return rule, np.full(len(idx), np.sqrt(0.5))  # with the target's 0.5: p = 1
    return rule, np.sqrt(np.maximum(var, MIN_SIGMA**2))


@takes_match_options
def match(
    source,
    target,
    *,
    options: MatchOptions | None = None,
    target_normals=None,
    source_normals=None,
    max_distance=1.0,
    max_angle_deg=30.0,
    classes=None,
    class_sigma=None,
    default_sigma=0.0,
    noise_weighting=True,
    max_noise=None,
    sample=None,
    unique=True,
    k=20,
    rng=None,
    tree=None,
    surface="plane",
) -> Correspondences:
    """Find, gate and weight correspondences from ``source`` to ``target`` (seed: ``Matching``).

    Parameters
    ----------
    source, target : array_like (n, 3) or PointCloud
        Clouds in the same (e.g. UTM) frame; a PointCloud's ``classification``
        is used by ``classes`` and ``class_sigma``.
    options : MatchOptions, optional
        The matching options in one object (:class:`labkit.registration.MatchOptions`, which documents
        each of them); a keyword below given as well overrides its field.
    max_distance, max_angle_deg, classes, class_sigma, default_sigma, noise_weighting, max_noise, sample, unique, k,
    target_normals, source_normals, surface
        The matching options as keywords, see :class:`~labkit.registration.MatchOptions`. Without
        ``options`` the defaults are those of MatchOptions except ``sample=None`` (every source point)
        and ``surface='plane'`` (the PCA plane). Normals are computed only where needed.
    rng : int or Generator, optional
        For the sampling.
    tree : optional
        Kept for compatibility: labkit builds its own compiled kd-tree of the target
        (exact duplicates merged) once per call; a given tree is only checked for its size.

    Returns
    -------
    Correspondences
        One row per sampled source point with dx, dy, dz, the point-to-plane
        distance, the normal angle, the weight and the rule that rejected it.

    Notes
    -----
    Weights follow eq. (5.6), p_i = 1 / (sigma_s,i^2 + sigma_t,j^2): the variance of
    a point-to-plane residual between two independently measured points. Without
    ``class_sigma`` and ``noise_weighting`` all weights are 1.

    References
    ----------
    .. [1] Notebook 05, section 2, eqs. 5.1-5.2 and 5.5-5.6; the registration study, step 2 (kd-tree matching)
       and step 4 (normal angles, local noise).
    .. [2] J. H. Friedman, J. L. Bentley, R. A. Finkel (1977): k-d tree search, doi:10.1145/355744.355745.
    .. [3] S. Rusinkiewicz, M. Levoy (2001): Efficient variants of the ICP algorithm. Proc. Third
       International Conference on 3-D Digital Imaging and Modeling (3DIM), 145-152.
    .. [4] H. Hoppe et al. (1992): Surface reconstruction from unorganized points (SIGGRAPH '92).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.synthetic import wavy_surface
    >>> target = wavy_surface(1500, 1, noise=0.0)  # slopes in X and Y, no noise
    >>> corr = match(target[::5] + [0.0, 0.0, 0.02], target, max_distance=0.5)
    >>> corr.n_accepted > 250, bool(np.allclose(np.median(corr.dz[corr.accepted]), -0.02, atol=0.005))
    (True, True)
    """
    return prepare(source, target, options=options, rng=rng, tree=tree)()
