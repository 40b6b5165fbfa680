"""The fixed part of the matching and one matching step (private): what ICP calls in every iteration.

:func:`labkit.registration.matching.match.prepare` builds a :class:`_Matcher` once (kd-tree of the target,
sampled source, exclusions); calling it with the current transformation gives the
:class:`~labkit.registration.matching.match.Correspondences` (nearest neighbours, gates, weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.checks import positive
from ...neighbours.eigh3 import HAVE_NUMBA
from ...neighbours.kdtree import KDTree
from ...core.errors import LabkitError
from .correspondences import _CODE, MIN_SIGMA, Correspondences
from .local_surface import Geometry
from . import matcher_passes as passes
from ...neighbours.kdtree_build import in_runs

if HAVE_NUMBA:
    import numba


def _classes_of(cloud, n):
    if hasattr(cloud, "attributes") and "classification" in cloud.attributes:
        return np.asarray(cloud.attributes["classification"])
    return None


def _require_classes(cloud, name):
    """The class rule needs a classification on both clouds; without one it would silently do nothing."""
    if _classes_of(cloud, 0) is None:
        got = "a PointCloud without a 'classification' attribute" if hasattr(cloud, "attributes") else "a plain array"
        raise LabkitError(
            f"classes= needs the class of every point, but the {name} cloud is {got}; pass a PointCloud "
            f"with a 'classification' attribute (e.g. from labkit.io.read_cloud) or leave classes=None"
        )


def _class_sigma(cls, class_sigma):
    """A priori standard deviation per point from its class (NaN where the class is not listed)."""
    out = np.full(len(cls), np.nan)
    for c, s in class_sigma.items():
        out[cls == c] = positive(s, f"class_sigma[{c}]")
    return out


class _TreePoints:
    """The target's points by input row, read from the kd-tree's own leaf-order copy (private).

    ``view[j]`` equals ``points[j]`` (a merged duplicate reads its identical kept copy), so the
    matcher holds one copy of a 10-million-point target instead of two.
    """

    def __init__(self, tree, n):
        self.tree, self.n = tree, n

    def __len__(self):
        return self.n

    @property
    def shape(self):
        return (self.n, 3)

    def __getitem__(self, j):
        return self.tree.data[self.tree.representative[j]]


@dataclass(frozen=True, eq=False)
class _Matcher:
    """Everything that stays fixed over the ICP iterations (private)."""

    source: np.ndarray  # sampled source points, local frame, untransformed
    source_index: np.ndarray
    source_normals: np.ndarray | None
    source_sigma: np.ndarray  # per sampled source point, from class and noise
    source_rule: np.ndarray  # pre-assignment exclusions (class, noise)
    target: _TreePoints  # target points by input row (local frame), from the tree
    tree: KDTree
    geometry: Geometry
    target_class: np.ndarray | None
    options: dict
    origin: np.ndarray
    n_source: int
    source_class: np.ndarray | None = None  # class of each sampled source point (None: no classification)
    query_order: np.ndarray | None = None  # sampled source points in spatial (leaf) order: coherent queries
    query_groups: np.ndarray | None = None  # per row of query_order: its leaf in the source's tree (ascending)
    search_memory: tuple | None = None  # (warm, (at, second)) per row of query_order: a search made ahead (first_search)

    def __post_init__(self):
        # the queries (the sampled source points the source rules leave) in leaf order, and their groups:
        # the same in every call, as are the source rules
        ok = self.source_rule[self.query_order] == 0 if self.query_order is not None else None
        if ok is not None and ok.all():  # no source rule (no classes, no noise limit): every row a query, no copies
            ok = slice(None)
        live = None if ok is None else self.query_order[ok]
        starts = None
        if self.query_groups is not None:
            g = self.query_groups[ok]
            starts = np.append(np.flatnonzero(np.r_[True, g[1:] != g[:-1]]), len(g))
        object.__setattr__(self, "_queries", (live, starts))
        # the queries' source points in query order: rotated in place of a gather of the moved points
        object.__setattr__(self, "_source_q", None if live is None else
                           np.ascontiguousarray(np.take(self.source, live, axis=0), dtype=np.float64))
        # and their normals: read in query order by the gates (an empty array without normals or queries)
        normals_q = np.empty((0, 3))
        if live is not None and self.source_normals is not None:
            normals_q = np.ascontiguousarray(np.take(self.source_normals, live, axis=0), dtype=np.float64)
        object.__setattr__(self, "_normals_q", normals_q)
        # per query (in that order): the warm start and the memory of the search (KDTree.nearest_in_groups):
        # the leaf position of its nearest target point in the last call (-1: none), where it was last
        # searched and the squared distance of its second nearest target point then. They change no answer.
        n = 0 if live is None else len(live)
        if self.search_memory is not None and live is not None:  # the rows of the search made ahead that are queries
            warm, (at, second) = self.search_memory
            object.__setattr__(self, "_warm", np.ascontiguousarray(warm[ok], dtype=np.intp))
            object.__setattr__(self, "_memory", (np.ascontiguousarray(at[ok]), np.ascontiguousarray(second[ok])))
        else:
            object.__setattr__(self, "_warm", np.full(n, -1, dtype=np.intp))
            object.__setattr__(self, "_memory", (np.zeros((n, 3)), np.zeros(n)))
        object.__setattr__(self, "_work", {})  # the work arrays of the calls (_scratch)

    def _scratch(self, name, n, shape=(), dtype=np.float64, most=0):
        """The first ``n`` rows of a work array of the calls, kept between them (ICP calls the matcher one
        iteration after the other, as the warm starts above already require): the same memory in every
        iteration instead of 20-30 MB of new pages, zeroed by the system on first touch. ``most``: the rows
        any call can need (made at once, also when a later call needs more than this one). What a call
        returns is never one of these."""
        buf = self._work.get(name)
        if buf is None or len(buf) < n or buf.shape[1:] != shape or buf.dtype != dtype:
            buf = self._work[name] = np.empty((max(n, most),) + shape, dtype)
        return buf[:n]

    def __call__(self, R=None, t=None) -> Correspondences:
        """Correspondences of the source moved by p' = R p + t (local frame)."""
        R = np.eye(3) if R is None else R
        t = np.zeros(3) if t is None else t
        if HAVE_NUMBA and self.query_groups is not None and self.geometry.given is None:
            return self._compiled_call(np.ascontiguousarray(R, dtype=np.float64),
                                       np.ascontiguousarray(np.broadcast_to(t, (3,)), dtype=np.float64))
        return self._numpy_call(R, t)

    def _compiled_call(self, R, t):
        """:meth:`_numpy_call` in a few compiled passes over the queries (in their leaf order, where the target
        points they meet lie close together) and over the rows, each spread over the cores in ranges
        (:mod:`.matcher_passes`; every range writes its own rows): the same correspondences, number for number."""
        opt = self.options
        live, starts = self._queries
        m, n_live = len(self.source), len(live)
        threads = passes.cores() if n_live > passes.SERIAL_ROWS else 1  # thread start-up dominates small queries
        rule = self.source_rule.copy()
        tidx = np.full(m, -1)
        # written at the rows with a partner, NaN at the others by the last pass (weights_planes_range)
        d, nt, noise_t, angle = np.empty((m, 3)), np.empty((m, 3)), np.empty(m), np.empty(m)
        cuts = passes.range_cuts(n_live, threads)
        q = self._scratch("q", n_live, (3,))  # the queries moved, in query order
        in_runs(lambda a, b: passes.rotate_range(self._source_q, R, t, q, a, b), cuts, threads)
        # (3) nearest neighbour in the target kd-tree, within max_distance
        dist, j = self.tree.nearest_in_groups(q, starts, opt["max_distance"], workers=-1 if threads > 1 else 1,
                                              warm=self._warm, memory=self._memory)
        # the queries with a partner, in query order: counted per range, then each range written from the
        # sum of the counts of the ranges before it
        counts = {}
        in_runs(lambda a, b: counts.__setitem__(a, passes.count_found(dist, a, b)), cuts, threads)
        offsets = dict(zip(cuts[:-1], np.cumsum([0] + [counts[a] for a in cuts[:-1]]).tolist()))
        n_found = sum(counts.values())
        # per query with a partner (query order): its position, the leaf position of its target point and that
        # point's place in the geometry cache (-1: not there yet), its row and its target point
        found, pos, slots, rows, jf = (self._scratch(name, n_found, dtype=np.intp, most=n_live)
                                       for name in ("found", "pos", "slots", "rows", "jf"))
        uncached = []  # per range: how many of its target points the geometry cache does not hold yet
        geometry, rep = self.geometry, self.tree.representative

        def write_found(a, b):
            uncached.append(passes.found_range(dist, j, live, rep, geometry.slot, rule, tidx, _CODE["distance"],
                                               found, pos, slots, rows, jf, a, b, offsets[a]))

        in_runs(write_found, cuts, threads)
        j = jf
        if sum(uncached):
            geometry._compute(pos)  # the target points met for the first time
        quadric = opt["surface"] == "quadric"
        gates = opt["classes"] is not None or opt["max_noise"] is not None
        normals = self.source_normals
        has_angle = normals is not None
        max_angle = opt["max_angle_deg"]
        gate_angle, max_angle = max_angle is not None and has_angle, np.inf if max_angle is None else float(max_angle)
        cosang = self._scratch("cosang", n_found, most=n_live)
        # |q_j - p_i|^2: the duplicate rule keeps the nearest source point by it (-1: rejected)
        d2 = self._scratch("d2", n_found, most=n_live)
        # a target point whose neighbourhood is a point or a line has no normal; (4) gates on the target
        # point (class, noise) and the source normal, in the order of _numpy_call: with the gather where
        # the normals are final and nothing comes between
        fused = not quadric and not gates
        normals_q = self._normals_q  # the source normals in query order (an empty (0, 3) array without)
        store, code = geometry._store, _CODE["degenerate"]

        def angles(a, b):  # the normal angles of the pairs a:b and their gate
            if has_angle:
                c = cosang[a:b]
                np.clip(c, 0, 1, out=c)
                np.degrees(np.arccos(c, out=c), out=c)  # the angles, in place
            passes.angles_range(rows, cosang, has_angle, max_angle, gate_angle, rule, angle, _CODE["normal_angle"],
                                d2, a, b)

        def pairs(a, b):  # the pairs a:b: their differences, normals, noise, gates and angles
            passes.gather_range(self.tree.data, q, found, rows, pos, slots, geometry.slot, store["normals"],
                                store["noise"], d, nt, noise_t, d2, rule, normals_q, R, cosang, fused,
                                fused and has_angle, code, a, b)
            if quadric:  # see _numpy_call: the foot point on the quadric replaces q_j
                geometry.foot_at_rows(None, rows[a:b], d, nt, pos[a:b])
            if not fused:
                passes.normal_gates_range(rows, found, nt, rule, normals_q, R, cosang, True,
                                          has_angle and not gates, code, a, b)
            if not gates:
                angles(a, b)

        if n_found:
            in_runs(pairs, passes.range_cuts(n_found, threads), threads)
        if opt["classes"] is not None:
            bad = ~np.isin(self.target_class[j], opt["classes"])
            rule[rows[bad & (rule[rows] == 0)]] = _CODE["class"]
        if opt["max_noise"] is not None:
            bad = noise_t[rows] > opt["max_noise"]
            rule[rows[bad & (rule[rows] == 0)]] = _CODE["noise"]
        if gates:
            if has_angle:
                passes.normal_gates_range(rows, found, nt, rule, normals_q, R, cosang, False, True, code, 0, n_found)
            angles(0, n_found)
        if opt["unique"] and n_found:
            # one source point per target point, the nearest by the point-to-point distance (see _numpy_call):
            # split by target points (each pass reads every pair and writes the rows of its own target points)
            best = self._scratch("best", self.tree.n, dtype=np.int64)
            best_d2 = self._scratch("best_d2", self.tree.n)
            in_runs(lambda lo, hi: passes.duplicates_range(rows, pos, d2, rule, best, best_d2, lo, hi,
                                                                    _CODE["duplicate"]),
                             passes.range_cuts(self.tree.n, threads, per_thread=1), threads)
        # (5) weights p = 1 / (sigma_s^2 + sigma_t^2)  (eq. 5.6) and the plane distances
        noise_sigma = opt["noise_weighting"] and not (opt["class_sigma"] and self.target_class is not None)
        if noise_sigma or not n_found:
            sigma_t = noise_t  # sigma_t = max(noise_t, MIN_SIGMA), in the kernel
        else:
            sigma_t = np.full(m, np.nan)
            sigma_t[rows] = self._target_sigma(j, noise_t[rows])
        weight, plane = np.empty(m), np.empty(m)
        xyz = np.empty((m, 3))

        def weights_planes(a, b):
            passes.weights_planes_range(self.source, R, t, self.origin, rule, self.source_sigma, sigma_t, noise_sigma,
                                        MIN_SIGMA**2, tidx, nt, d, noise_t, angle, weight, plane, xyz, a, b)

        in_runs(weights_planes, passes.range_cuts(m, threads), threads)
        return Correspondences(
            self.source_index, tidx, xyz, d, plane, angle, nt, weight, rule, self.n_source, dict(opt),
        )  # fmt: skip

    def _numpy_call(self, R, t):
        """The correspondences step by step in numpy (without numba, or with given target normals)."""
        opt = self.options
        p = _rotated(self.source, R, t)  # not `@`: a BLAS call per iteration (see _rotated)
        rule = self.source_rule.copy()
        live, starts = self._queries  # in leaf order: neighbouring queries in cache
        m = len(p)
        tidx = np.full(m, -1)
        d = np.full((m, 3), np.nan)
        nt = np.full((m, 3), np.nan)
        noise_t = np.full(m, np.nan)
        # (3) nearest neighbour in the target kd-tree, within max_distance
        workers = -1 if len(live) > 20000 else 1  # thread start-up dominates small queries
        if self.query_groups is None:
            dist, j = self.tree.query(p[live], k=1, distance_upper_bound=opt["max_distance"], workers=workers)
        else:  # the same answer; a source leaf's points walk the target tree together
            dist, j = self.tree.nearest_in_groups(p[live], starts, opt["max_distance"], workers=workers,
                                                  warm=self._warm, memory=self._memory)
        # back to ascending rows (one scatter), so that the steps below read and write in order
        nearest = np.full(m, -1)
        nearest[live] = np.where(np.isfinite(dist), j, -1)
        rule[live[~np.isfinite(dist)]] = _CODE["distance"]
        live = np.flatnonzero(nearest >= 0)
        j = nearest[live]
        tidx[live] = j
        _differences(self.tree.data, self.tree.representative, j, p, live, d)  # d[live] = q_j - p_i
        self.geometry.at_rows(j, live, nt, noise_t, need_noise=opt["need_noise"])  # nt[live], noise_t[live]
        nearest_d = d  # q_j - p_i: the duplicate rule keeps the nearest source point by this
        if opt["surface"] == "quadric" and len(live):
            nearest_d = d.copy()
            # the foot point on the target's local quadric replaces q_j: no curvature bias (sagitta).
            # The quadric is shifted to pass through the measured q_j (its slopes and curvatures
            # kept): q_j's noise then enters one residual only, as with the plane; the fitted value
            # would spread every target point's noise over the ~k residuals around it, correlated
            # beyond the block cells (stated std 1.4-1.6 times too small on sparse hills)
            self.geometry.foot_at_rows(j, live, d, nt)  # d[live], nt[live]: offset and the quadric's normal there
        # a target point whose neighbourhood is a point or a line has no normal
        rule[live[np.isnan(nt[live, 0]) & (rule[live] == 0)]] = _CODE["degenerate"]
        # (4) gates on the target point: class, noise, normal angle
        if opt["classes"] is not None:  # prepare() made sure the target has classes
            bad = ~np.isin(self.target_class[j], opt["classes"])
            rule[live[bad & (rule[live] == 0)]] = _CODE["class"]
        if opt["max_noise"] is not None:
            bad = noise_t[live] > opt["max_noise"]
            rule[live[bad & (rule[live] == 0)]] = _CODE["noise"]
        angle = np.full(m, np.nan)
        if self.source_normals is not None:
            rule[live[np.isnan(self.source_normals[live, 0]) & (rule[live] == 0)]] = _CODE["degenerate"]
            cosang = _cos_normals(self.source_normals, np.ascontiguousarray(R, dtype=np.float64), nt, live)
            angle[live] = np.degrees(np.arccos(np.clip(cosang, 0, 1)))
            if opt["max_angle_deg"] is not None:
                bad = angle[live] > opt["max_angle_deg"]
                rule[live[bad & (rule[live] == 0)]] = _CODE["normal_angle"]
        if opt["unique"]:
            # by the point-to-point distance, never by the residual: keeping the source point with
            # the smallest quadric offset would select on the residual itself (residuals too small,
            # stated covariance 1.3-1.65 times too small in Monte Carlo runs)
            _reject_duplicates(rule, tidx, nearest_d, len(self.target))
        # (5) weights p = 1 / (sigma_s^2 + sigma_t^2)  (eq. 5.6)
        weight = np.zeros(m)
        weight[live] = 1.0 / (self.source_sigma[live] ** 2 + self._target_sigma(j, noise_t[live]) ** 2)
        weight[rule != 0] = 0.0
        plane = np.einsum("ij,ij->i", nt, d)
        return Correspondences(
            self.source_index, tidx, p + self.origin, d, plane, angle, nt, weight, rule,
            self.n_source, dict(opt),
        )  # fmt: skip

    def _target_sigma(self, j, noise):
        opt = self.options
        var = np.zeros(len(j))
        if opt["class_sigma"] and self.target_class is not None:
            s = _class_sigma(self.target_class[j], opt["class_sigma"])
            var += np.where(np.isnan(s), opt["default_sigma"], s) ** 2
        if opt["noise_weighting"]:
            # the plane and the quadric both pass through the measured q_j: its variance counts once
            var += noise**2
        if not opt["class_sigma"] and not opt["noise_weighting"]:
            return np.full(len(j), np.sqrt(0.5))  # unit weights: p = 1
        return np.sqrt(np.maximum(var, MIN_SIGMA**2))


def first_search(tree, source, query_order, query_groups, R, t, max_distance):
    """The nearest target point of every query (the rows ``query_order`` of ``source`` moved by R, t), as the
    search memory of a :class:`_Matcher` (its ``search_memory``): made ahead, e.g. beside the source's
    normals, the matcher's first call at (R, t) then finds every answer already known (the same answers)."""
    q = _rotated(np.take(source, query_order, axis=0), R, t)  # (row by row: the same as rotating all, then taking)
    g = query_groups
    starts = np.append(np.flatnonzero(np.r_[True, g[1:] != g[:-1]]), len(g))
    warm, memory = np.full(len(q), -1, dtype=np.intp), (np.zeros((len(q), 3)), np.zeros(len(q)))
    tree.nearest_in_groups(q, starts, max_distance, workers=-1 if len(q) > 20000 else 1, warm=warm, memory=memory)
    return warm, memory


def _rotated_numpy(points, R, t=None):
    """points @ R.T (+ t) for a tall (m, 3) array, by einsum.

    ``@`` hands a tall (m, 3) x (3, 3) product to the threaded BLAS, whose threads spin against
    the kd-tree's threads: on a loaded 2-core machine 80 ms median for 100,000 points, einsum 8 ms.
    """
    out = np.einsum("ij,kj->ik", points, R)
    return out if t is None else out + t


def _differences_numpy(data, rep, j, p, live, d):
    d[live] = data[rep[j]] - p[live]


def _dot_rows_numpy(a, b):
    return np.einsum("ij,ij->i", a, b)


def _cos_normals_numpy(source_normals, R, nt, live):
    """|R n_s . n_t| of the rows ``live`` (the cosine of the angle between the moved source and the target normal)."""
    return np.abs(_dot_rows_numpy(_rotated_numpy(source_normals[live], R), nt[live]))


def _dot_rows_at_numpy(d, live):
    return _dot_rows_numpy(d[live], d[live])


if HAVE_NUMBA:
    # one compiled pass each instead of numpy's temporaries (ICP calls them in every iteration on every
    # source point); the sums in einsum's order, (x0 y0 + x2 y2) + x1 y1: the same numbers to the bit

    @numba.njit(cache=True, nogil=True)
    def _rotate_kernel(P, R, t, out):  # pragma: no cover - compiled
        for i in range(P.shape[0]):
            x, y, z = P[i, 0], P[i, 1], P[i, 2]
            for k in range(3):
                out[i, k] = ((x * R[k, 0] + z * R[k, 2]) + y * R[k, 1]) + t[k]

    @numba.njit(cache=True, nogil=True)
    def _rotate_only_kernel(P, R, out):  # pragma: no cover - compiled
        for i in range(P.shape[0]):
            x, y, z = P[i, 0], P[i, 1], P[i, 2]
            for k in range(3):
                out[i, k] = (x * R[k, 0] + z * R[k, 2]) + y * R[k, 1]

    @numba.njit(cache=True, nogil=True)
    def _differences(data, rep, j, p, live, d):  # pragma: no cover - compiled
        """d[live] = data[rep[j]] - p[live] in one pass (the target point q_j minus the moved p_i)."""
        for r in range(live.shape[0]):
            q, i = rep[j[r]], live[r]
            d[i, 0], d[i, 1], d[i, 2] = data[q, 0] - p[i, 0], data[q, 1] - p[i, 1], data[q, 2] - p[i, 2]

    @numba.njit(cache=True, nogil=True)
    def _dot_rows(a, b):  # pragma: no cover - compiled
        out = np.empty(a.shape[0])
        for i in range(a.shape[0]):
            out[i] = (a[i, 0] * b[i, 0] + a[i, 2] * b[i, 2]) + a[i, 1] * b[i, 1]
        return out

    @numba.njit(cache=True, nogil=True)
    def _cos_normals(source_normals, R, nt, live):  # pragma: no cover - compiled
        """:func:`_cos_normals_numpy` in one pass: no gathered or rotated copies (the same sums, the same order)."""
        out = np.empty(live.shape[0])
        for r in range(live.shape[0]):
            i = live[r]
            x, y, z = source_normals[i, 0], source_normals[i, 1], source_normals[i, 2]
            a0 = (x * R[0, 0] + z * R[0, 2]) + y * R[0, 1]
            a1 = (x * R[1, 0] + z * R[1, 2]) + y * R[1, 1]
            a2 = (x * R[2, 0] + z * R[2, 2]) + y * R[2, 1]
            out[r] = abs((a0 * nt[i, 0] + a2 * nt[i, 2]) + a1 * nt[i, 1])
        return out

    @numba.njit(cache=True, nogil=True)
    def _dot_rows_at(d, live):  # pragma: no cover - compiled
        out = np.empty(live.shape[0])
        for r in range(live.shape[0]):
            i = live[r]
            out[r] = (d[i, 0] * d[i, 0] + d[i, 2] * d[i, 2]) + d[i, 1] * d[i, 1]
        return out

    def _rotated(points, R, t=None):
        """points @ R.T (+ t) for a tall (m, 3) array, compiled (:func:`_rotated_numpy`, the same numbers)."""
        P = np.ascontiguousarray(points, dtype=np.float64)
        R = np.ascontiguousarray(R, dtype=np.float64)
        out = np.empty((len(P), 3))
        if t is None:
            _rotate_only_kernel(P, R, out)
        else:
            _rotate_kernel(P, R, np.ascontiguousarray(np.broadcast_to(t, (3,)), dtype=np.float64), out)
        return out
else:  # pragma: no cover - depends on the environment
    _rotated, _differences, _dot_rows = _rotated_numpy, _differences_numpy, _dot_rows_numpy
    _cos_normals, _dot_rows_at = _cos_normals_numpy, _dot_rows_at_numpy


def _reject_duplicates(rule, tidx, d, n_target):
    """One source point per target point: keep the closest, mark the others 'duplicate' (in place).

    A target point used twice would put its own noise into two residuals; the
    residuals would be correlated and sigma0^2 N^-1 too optimistic. One pass over the
    accepted rows with a per-target-point record of the closest row so far (O(m), no
    sort); equal distances keep the lower row, as a stable sort would.
    """
    live = np.flatnonzero(rule == 0)
    if live.size < 2:
        return
    dist2 = _dot_rows_at(d, live)  # |d_i|^2 of the live rows
    loser = _closest_per_target(live, tidx[live], dist2, n_target)
    rule[loser] = _CODE["duplicate"]


def _closest_per_target_numpy(live, j, dist2, n_target):  # pragma: no cover - without numba
    order = np.lexsort((dist2, j))
    first = np.r_[True, j[order[1:]] != j[order[:-1]]]
    return live[order[~first]]


if HAVE_NUMBA:

    @numba.njit(cache=True, nogil=True)
    def _closest_per_target(live, j, dist2, n_target):  # pragma: no cover - compiled
        best = np.full(n_target, -1, np.int64)  # position in ``live`` of the closest row so far
        lose = np.zeros(len(live), np.bool_)
        for r in range(len(live)):
            b = best[j[r]]
            if b < 0:
                best[j[r]] = r
            elif dist2[r] < dist2[b]:
                lose[b] = True
                best[j[r]] = r
            else:
                lose[r] = True
        return live[lose]
else:  # pragma: no cover - depends on the environment
    _closest_per_target = _closest_per_target_numpy
