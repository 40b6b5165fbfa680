"""The fixed part of the matching and one matching step (private): what ICP calls in every iteration.

:func:`labkit.registration.matching.match.prepare` builds a :class:`_Matcher` once (kd-tree of the target,
sampled source, exclusions); calling it with the current transformation gives the
:class:`~labkit.registration.matching.match.Correspondences` (nearest neighbours, gates, weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.checks import positive
from ...core.jit import compiled
from ...neighbours.eigh3 import HAVE_NUMBA
from ...neighbours.kdtree import KDTree
from ...core.errors import LabkitError
from .correspondences import _CODE, MIN_SIGMA, Correspondences
from .local_surface import Geometry

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
        live = None if ok is None else self.query_order[ok]
        starts = None
        if self.query_groups is not None:
            g = self.query_groups[ok]
            starts = np.append(np.flatnonzero(np.r_[True, g[1:] != g[:-1]]), len(g))
        object.__setattr__(self, "_queries", (live, starts))
        # the queries' source points in query order: rotated in place of a gather of the moved points
        object.__setattr__(self, "_source_q", None if live is None else np.take(self.source, live, axis=0))
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
        points they meet lie close together) and one over the rows: the same correspondences, number for number."""
        opt = self.options
        live, starts = self._queries
        m = len(self.source)
        rule = self.source_rule.copy()
        tidx = np.full(m, -1)
        # written at the rows with a partner, NaN at the others by the last pass (_weights_planes)
        d, nt, noise_t, angle = np.empty((m, 3)), np.empty((m, 3)), np.empty(m), np.empty(m)
        q = _rotated(self._source_q, R, t)  # the queries moved, in query order
        # (3) nearest neighbour in the target kd-tree, within max_distance
        workers = -1 if len(live) > 20000 else 1  # thread start-up dominates small queries
        dist, j = self.tree.nearest_in_groups(q, starts, opt["max_distance"], workers=workers,
                                              warm=self._warm, memory=self._memory)
        found = np.empty(len(live), dtype=np.intp)  # positions (in query order) of the queries with a partner
        pos = np.empty(len(live), dtype=np.intp)  # leaf position of each one's target point
        n_found, uncached = _found(dist, j, live, self.tree.representative, self.geometry.slot, rule, tidx,
                                   _CODE["distance"], found, pos)
        found, pos = found[:n_found], pos[:n_found]
        rows, j = live[found], j[found]  # the rows with a partner and their target points (query order)
        geometry = self.geometry
        if uncached:
            geometry._compute(pos)  # the target points met for the first time
        quadric = opt["surface"] == "quadric"
        gates = opt["classes"] is not None or opt["max_noise"] is not None
        normals = self.source_normals
        cosang = np.empty(n_found)
        # a target point whose neighbourhood is a point or a line has no normal; (4) gates on the target
        # point (class, noise) and the source normal, in the order of _numpy_call: with the gather where
        # the normals are final and nothing comes between
        fused = not quadric and not gates
        some_normals = normals if normals is not None else nt
        if n_found:
            _gather_pairs(self.tree.data, q, found, rows, pos, geometry.slot, geometry._store["normals"],
                          geometry._store["noise"], d, nt, noise_t,  # d = q_j - p_i, nt, noise_t
                          rule, some_normals, R, cosang, fused, fused and normals is not None, _CODE["degenerate"])
        nearest_d = d
        if quadric and n_found:
            nearest_d = d.copy()  # see _numpy_call: the foot point on the quadric replaces q_j
            geometry.foot_at_rows(j, rows, d, nt, pos)
        if not fused:
            _normal_gates(rows, nt, rule, some_normals, R, cosang, True, normals is not None and not gates,
                          _CODE["degenerate"])
        if opt["classes"] is not None:
            bad = ~np.isin(self.target_class[j], opt["classes"])
            rule[rows[bad & (rule[rows] == 0)]] = _CODE["class"]
        if opt["max_noise"] is not None:
            bad = noise_t[rows] > opt["max_noise"]
            rule[rows[bad & (rule[rows] == 0)]] = _CODE["noise"]
        if normals is not None and gates:
            _normal_gates(rows, nt, rule, normals, R, cosang, False, True, _CODE["degenerate"])
        if normals is not None:
            np.clip(cosang, 0, 1, out=cosang)
            np.degrees(np.arccos(cosang, out=cosang), out=cosang)  # the angles, in place
        max_angle = opt["max_angle_deg"]
        # the normal angle's gate and (unique) one source point per target point, the nearest by the
        # point-to-point distance (see _numpy_call)
        _angle_and_duplicates(rows, pos, cosang, normals is not None, np.inf if max_angle is None else float(max_angle),
                              max_angle is not None and normals is not None, bool(opt["unique"]), nearest_d, rule,
                              angle, self.tree.n, _CODE["normal_angle"], _CODE["duplicate"])
        # (5) weights p = 1 / (sigma_s^2 + sigma_t^2)  (eq. 5.6) and the plane distances
        noise_sigma = opt["noise_weighting"] and not (opt["class_sigma"] and self.target_class is not None)
        if noise_sigma or not n_found:
            sigma_t = noise_t  # sigma_t = max(noise_t, MIN_SIGMA), in the kernel
        else:
            sigma_t = np.full(m, np.nan)
            sigma_t[rows] = self._target_sigma(j, noise_t[rows])
        weight, plane = np.empty(m), np.empty(m)
        xyz = np.empty((m, 3))
        _weights_planes(self.source, R, t, self.origin, rule, self.source_sigma, sigma_t, noise_sigma, MIN_SIGMA**2,
                        tidx, nt, d, noise_t, angle, weight, plane, xyz)
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


if HAVE_NUMBA:
    # the steps of _Matcher._compiled_call: each one pass, the same arithmetic as _numpy_call (no fastmath)

    @compiled
    def _found(dist, j, live, rep, slot, rule, tidx, code, found, pos):  # pragma: no cover - compiled
        """The queries (query order) with a partner within the gate: their positions ``found``, the leaf
        positions ``pos`` of their target points (``rep``: the tree's representative) and tidx; the others
        get the rule ``code`` (distance). Returns their number and how many of their target points the
        geometry cache does not hold yet."""
        n, uncached = 0, 0
        for r in range(live.shape[0]):
            if np.isfinite(dist[r]):
                p = rep[j[r]]
                found[n], pos[n] = r, p
                tidx[live[r]] = j[r]
                if slot[p] < 0:
                    uncached += 1
                n += 1
            else:
                rule[live[r]] = code
        return n, uncached

    @compiled
    def _gather_pairs(data, q, found, rows, pos, slot, normals_buf, noise_buf, d, nt, noise, rule, normals, R, cosang,
                      target, source, code):  # pragma: no cover - compiled
        """d[i] = q_j - p_i, nt[i] and noise[i] from the geometry cache, for the rows i = ``rows`` (query order);
        with ``target`` / ``source`` also the gates of :func:`_normal_gates` on them."""
        for n in range(rows.shape[0]):
            i, r, p = rows[n], found[n], pos[n]
            s = slot[p]
            d[i, 0], d[i, 1], d[i, 2] = data[p, 0] - q[r, 0], data[p, 1] - q[r, 1], data[p, 2] - q[r, 2]
            nt[i, 0], nt[i, 1], nt[i, 2] = normals_buf[s, 0], normals_buf[s, 1], normals_buf[s, 2]
            noise[i] = noise_buf[s]
            if target and np.isnan(normals_buf[s, 0]) and rule[i] == 0:
                rule[i] = code
            if source:
                if np.isnan(normals[i, 0]) and rule[i] == 0:
                    rule[i] = code
                x, y, z = normals[i, 0], normals[i, 1], normals[i, 2]
                a0 = (x * R[0, 0] + z * R[0, 2]) + y * R[0, 1]
                a1 = (x * R[1, 0] + z * R[1, 2]) + y * R[1, 1]
                a2 = (x * R[2, 0] + z * R[2, 2]) + y * R[2, 1]
                cosang[n] = abs((a0 * normals_buf[s, 0] + a2 * normals_buf[s, 2]) + a1 * normals_buf[s, 1])

    @compiled
    def _normal_gates(rows, nt, rule, normals, R, cosang, target, source, code):  # pragma: no cover - compiled
        """'degenerate' where the target normal (``target``) or the source normal (``source``) is missing and no
        rule came first; with ``source`` also |R n_s . n_t| per row (:func:`_cos_normals`, the same sums)."""
        for n in range(rows.shape[0]):
            i = rows[n]
            t0, t1, t2 = nt[i, 0], nt[i, 1], nt[i, 2]
            if target and np.isnan(t0) and rule[i] == 0:
                rule[i] = code
            if source:
                x, y, z = normals[i, 0], normals[i, 1], normals[i, 2]
                if np.isnan(x) and rule[i] == 0:
                    rule[i] = code
                a0 = (x * R[0, 0] + z * R[0, 2]) + y * R[0, 1]
                a1 = (x * R[1, 0] + z * R[1, 2]) + y * R[1, 1]
                a2 = (x * R[2, 0] + z * R[2, 2]) + y * R[2, 1]
                cosang[n] = abs((a0 * t0 + a2 * t2) + a1 * t1)

    @compiled
    def _angle_and_duplicates(rows, pos, ang, has_angle, max_angle, gate, unique, d, rule, angle, n_target,
                              code_angle, code_duplicate):  # pragma: no cover - compiled
        """angle[rows] = ang and its gate; then (``unique``) one source point per target point (``pos``: its
        leaf position, one per distinct target point as the input row the search answers): the one with
        the smallest |d|^2 keeps it, equal distances the lower row (:func:`_reject_duplicates`, in any order)."""
        best = np.full(n_target if unique else 0, -1, np.int64)  # the row keeping each target point so far
        best_d2 = np.empty(n_target if unique else 0)
        for n in range(rows.shape[0]):
            i = rows[n]
            if has_angle:
                angle[i] = ang[n]
                if gate and rule[i] == 0 and ang[n] > max_angle:
                    rule[i] = code_angle
            else:
                angle[i] = np.nan
            if unique and rule[i] == 0:
                d2 = (d[i, 0] * d[i, 0] + d[i, 2] * d[i, 2]) + d[i, 1] * d[i, 1]
                t = pos[n]
                b = best[t]
                if b < 0:
                    best[t], best_d2[t] = i, d2
                elif d2 < best_d2[t] or (d2 == best_d2[t] and i < b):
                    rule[b] = code_duplicate
                    best[t], best_d2[t] = i, d2
                else:
                    rule[i] = code_duplicate

    @compiled
    def _weights_planes(P, R, t, origin, rule, sigma_s, sigma_t, from_noise, min_var, tidx, nt, d, noise, angle,
                        weight, plane, xyz):  # pragma: no cover - compiled
        """Per row: NaN in d, nt, noise and angle where it has no partner (``tidx`` -1), the weight
        1 / (sigma_s^2 + sigma_t^2) (0 where a rule rejected it; ``from_noise``: sigma_t = max(noise, MIN_SIGMA)
        from the noise given as ``sigma_t``), the plane distance nt . d and the moved source point in the
        caller's frame (R p + t + origin), as _numpy_call computes them."""
        for i in range(P.shape[0]):
            if tidx[i] < 0:
                for k in range(3):
                    d[i, k] = np.nan
                    nt[i, k] = np.nan
                noise[i] = np.nan
                angle[i] = np.nan
            x, y, z = P[i, 0], P[i, 1], P[i, 2]
            for k in range(3):
                xyz[i, k] = (((x * R[k, 0] + z * R[k, 2]) + y * R[k, 1]) + t[k]) + origin[k]
            plane[i] = (nt[i, 0] * d[i, 0] + nt[i, 2] * d[i, 2]) + nt[i, 1] * d[i, 1]
            if rule[i] != 0:
                weight[i] = 0.0
                continue
            st = sigma_t[i]
            if from_noise:
                v = st * st
                if v < min_var:
                    v = min_var
                st = np.sqrt(v)
            ss = sigma_s[i]
            weight[i] = 1.0 / (ss * ss + st * st)


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
