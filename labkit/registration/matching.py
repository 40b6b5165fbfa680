"""Correspondences between two clouds: the seed's ``Matching`` (seed 003, steps 2 and 4).

One call of :func:`match` runs the steps of notebook 05, section 2:

1. sampling of the source (density differences; random, voxel or normal-space);
2. exclusion of source points by class and by local noise;
3. nearest-neighbour assignment on a kd-tree of the target (the ALS base);
4. gating: distance, angle between the normals, class and noise of the target point;
5. weights from the a priori precision per class and from the local noise
   (eq. 5.6: p_i = 1 / (sigma_s,i^2 + sigma_t,j^2)).

Every sampled source point gets one row; ``rule`` says which rule (if any)
rejected it, so a plot can colour the points by rule and the report can count them.

Speed (issue 11): the target's compiled kd-tree (``labkit._kdtree``, exact
duplicates merged) and its local geometry are built once per call and cached per
distinct target point (the target does not move); the source is queried in its own
leaf order; the one-source-per-target rule is one O(m) pass, not a sort of all pairs.
Points whose neighbourhood is a point or a line have no normal and are rejected
by the rule 'degenerate' (issue 16).

Large clouds (issue 14): ``sample='auto'`` (ICP's default) thins a source of more than
:data:`AUTO_LIMIT` points to about :data:`AUTO_PAIRS` (voxel, then normal-space balance); the
geometry of both clouds is computed and stored only at the points used (compact cache); the
matcher reads the target from its kd-tree, which ``labkit._treecache`` keeps for the distances.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._checks import as_points, as_rng, choice, positive
from .._eigh3 import HAVE_NUMBA, eigh3_analytic
from .._kdtree import KDTree
from .._treecache import local_tree
from ..features import _covariances  # shared kNN covariance kernel (compiled)
from .._frame import local_origin, reduce
from .._report import ReportMixin, fmt
from ..errors import LabkitError

if HAVE_NUMBA:
    import numba

#: Row labels; code 0 is an accepted correspondence. 'degenerate': the source or target point has
#: no normal (its neighbourhood is a point or a line, issue 16); it is applied with the normal angle.
RULES = ("accepted", "class", "noise", "distance", "normal_angle", "duplicate", "outlier", "degenerate")
_CODE = {name: code for code, name in enumerate(RULES)}
#: Floor for a point's standard deviation in the weights (m), keeps weights finite.
MIN_SIGMA = 0.005
#: Local surface models of :func:`match`: the PCA plane (default) or a quadric (curved, sparse surfaces);
#: 'auto' chooses by the size of the target's k-neighbourhoods (:func:`_auto_surface`).
SURFACES = ("plane", "quadric", "auto")
#: surface='auto' fits quadrics where the median radius of the target's k-neighbourhoods exceeds this (m).
AUTO_QUADRIC_RADIUS = 1.0
#: Normal-space sampling draws only from planar neighbourhoods: l3 / (l1 + l2 + l3) below this.
MAX_VARIATION = 0.02
#: sample='auto': a source of at most this many points is used whole; a larger one is thinned to
#: about :data:`AUTO_PAIRS` points (one per voxel, then normal-space balance, see :func:`_auto_sample`).
AUTO_LIMIT = 300_000
AUTO_PAIRS = 100_000


@dataclass(frozen=True, eq=False)
class Correspondences(ReportMixin):
    """Source-to-target correspondences with their rejection rule and weight.

    One row per sampled source point. Rows that a rule rejected keep their
    values (NaN where nothing was computed, target index -1 when no neighbour
    was searched) so they can be plotted.

    Attributes
    ----------
    source_index : ndarray of int (m,)
        Row of the source cloud.
    target_index : ndarray of int (m,)
        Row of the nearest target point (-1 when excluded before the search).
    source_xyz : ndarray (m, 3)
        Source points after the current transformation, caller's frame.
    d : ndarray (m, 3)
        Difference vectors q_j - p_i (dx, dy, dz) in metres.
    plane_distance : ndarray (m,)
        Signed point-to-plane distance n_j . (q_j - p_i) (eq. 5.2), metres.
    normal_angle : ndarray (m,)
        Angle between the source and target normals in degrees (orientation-free;
        NaN without source normals).
    target_normal : ndarray (m, 3)
        Unit normal of the target point (NaN where not computed).
    weight : ndarray (m,)
        Weight p_i of the correspondence (0 for rejected rows).
    rule : ndarray of int8 (m,)
        Code into :data:`RULES`: 0 accepted, otherwise the first rule that rejected it.
    n_source : int
        Points in the source cloud before sampling.
    """

    source_index: np.ndarray
    target_index: np.ndarray
    source_xyz: np.ndarray
    d: np.ndarray
    plane_distance: np.ndarray
    normal_angle: np.ndarray
    target_normal: np.ndarray
    weight: np.ndarray
    rule: np.ndarray
    n_source: int
    settings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.rule)

    @property
    def accepted(self) -> np.ndarray:
        """Boolean mask of the rows that no rule rejected."""
        return self.rule == 0

    @property
    def n_accepted(self) -> int:
        return int(self.accepted.sum())

    @property
    def distance(self) -> np.ndarray:
        """Point-to-point distance |q_j - p_i| (eq. 5.1), metres."""
        return np.linalg.norm(self.d, axis=1)

    @property
    def dx(self) -> np.ndarray:
        return self.d[:, 0]

    @property
    def dy(self) -> np.ndarray:
        return self.d[:, 1]

    @property
    def dz(self) -> np.ndarray:
        return self.d[:, 2]

    @property
    def rejected(self) -> tuple:
        """(rule, count) pairs for every rejection rule, including zero counts."""
        counts = np.bincount(self.rule, minlength=len(RULES))
        thinned = (("sampling", self.n_source - len(self.rule)),)
        return thinned + tuple((name, int(c)) for name, c in zip(RULES[1:], counts[1:]))

    def with_outliers(self, mask) -> "Correspondences":
        """A copy in which the accepted rows selected by ``mask`` are marked 'outlier' (weight 0)."""
        mask = np.asarray(mask, dtype=bool) & self.accepted
        rule = self.rule.copy()
        rule[mask] = _CODE["outlier"]
        weight = np.where(mask, 0.0, self.weight)
        return _replace(self, rule=rule, weight=weight)

    def with_weights(self, weight) -> "Correspondences":
        """A copy with other weights (e.g. robust IRLS weights); rejected rows stay at 0."""
        weight = np.where(self.accepted, np.asarray(weight, dtype=np.float64), 0.0)
        return _replace(self, weight=weight)

    def table(self) -> np.ndarray:
        """All rows as a numpy structured array (no pandas needed)."""
        dtype = [
            ("source_index", "i8"), ("target_index", "i8"),
            ("dx", "f8"), ("dy", "f8"), ("dz", "f8"), ("distance", "f8"),
            ("plane_distance", "f8"), ("normal_angle", "f8"), ("weight", "f8"), ("rule", "U12"),
        ]  # fmt: skip
        out = np.empty(len(self), dtype=dtype)
        out["source_index"], out["target_index"] = self.source_index, self.target_index
        out["dx"], out["dy"], out["dz"] = self.d.T
        out["distance"], out["plane_distance"] = self.distance, self.plane_distance
        out["normal_angle"], out["weight"] = self.normal_angle, self.weight
        out["rule"] = np.asarray(RULES)[self.rule]
        return out

    def _report(self):
        ok = self.accepted
        counts = [(f"rejected by {name}", str(c)) for name, c in self.rejected]
        rows = [("source points", str(self.n_source)), ("candidates (after sampling)", str(len(self)))]
        rows += counts + [("accepted", f"{ok.sum()} ({100 * ok.mean() if len(self) else 0:.1f} %)")]
        if ok.any():
            pd = self.plane_distance[ok]
            rows += [
                ("median |point-to-plane|", fmt(np.median(np.abs(pd)), 4, "m")),
                ("median point-to-point", fmt(np.median(self.distance[ok]), 4, "m")),
                ("weights min / median / max", fmt(np.percentile(self.weight[ok], [0, 50, 100]), 3)),
            ]
        return "Correspondences", [("", rows)]


def _replace(corr: Correspondences, **changes) -> Correspondences:
    values = {name: getattr(corr, name) for name in corr.__dataclass_fields__}
    values.update(changes)
    return Correspondences(**values)


# --------------------------------------------------------------------- geometry


def _local_geometry(tree, cols, index, k):
    """Normals, local noise and change of curvature of the input points ``index`` from k neighbours.

    The same PCA as :func:`labkit.features.local_pca` (notebook 04, eqs. 1-5) on the
    tree's distinct points (exact duplicates merged), evaluated only at the query points.
    Noise is sigma_n = sqrt(k lambda_min / (k - 3)). Queries run in the tree's leaf
    order, which keeps the visited leaves in cache. Where the neighbourhood is a point
    or a line the normal and the noise are NaN (issue 16).
    """
    pos = tree.representative[index]  # leaf position of each point's kept copy
    order = np.argsort(pos, kind="stable")
    out = _leaf_geometry(tree, cols, pos[order], k)[:3]
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return tuple(a[back] for a in out)


def _leaf_geometry(tree, cols, pos, k, quadric=False):
    """:func:`_local_geometry` at the tree's own (distinct) points, given by sorted leaf positions.

    With ``quadric`` also the local quadric's coefficients and frame (the frame's normal
    oriented up), and its noise replaces the plane's: on a curved surface the plane's
    l3 holds the curvature too, and would down-weight and reject curved ground.
    The last element is always a function that returns the covariance (m, 3, 3) of the plane
    normal's random tilt (:func:`_plane_tilt`) from the same decomposition: ICP's determinability
    test (eq. 5.12b) needs it at the matched target points and would otherwise search their
    neighbours again.
    """
    k = min(k, tree.n)
    threads = -1 if len(pos) > 2000 else 1  # threads cost more than they save on small queries
    nb = tree.query_leaf_positions(pos, k, workers=threads)
    _, cov = _covariances(tree.data, None, nb, cols)  # the local PCA's kernel (notebook 04, eqs. 1-2)
    cov *= k / (k - 3) if k > 3 else np.nan  # redundancy k - 3 of the plane (eq. 5): lambda_min is sigma_n^2
    lam, vecs = eigh3_analytic(cov)  # as np.linalg.eigh (closed form), ascending: normal = eigenvector of lambda_min
    lam = np.clip(lam, 0, None)
    with np.errstate(invalid="ignore"):
        ok = lam[:, 1] > 1e-12 * lam[:, 2]  # not a point, not a line (features._determined)
    n = vecs[:, :, 0]
    n = np.where(n[:, 2:3] < 0, -n, n)
    n[~ok] = np.nan
    noise = np.where(ok, np.sqrt(lam[:, 0]), np.nan)
    variation = lam[:, 0] / np.maximum(lam.sum(axis=1), 1e-300)  # change of curvature l3 / sum(l)
    tangents = vecs[:, :, 1:].copy() if quadric else vecs[:, :, 1:]  # (the quadric's frame changes below)
    tilt = lambda: _plane_tilt(lam, tangents, k)  # noqa: E731 - evaluated only where kept (the target)
    if quadric:
        vecs[~ok] = np.nan
        flip = vecs[:, 2, 0] < 0  # orient the frame's normal up; h and its coefficients flip with it
        vecs[flip, :, 0] *= -1
        coef, sig, slope = np.empty((len(pos), 6)), np.empty(len(pos)), np.empty((len(pos), 3))
        _quadric(tree.data, nb, pos, vecs, coef, sig, slope)
        fit = np.isfinite(sig)  # else (k < 7, degenerate fit) the plane stays
        _, n_q = _on_quadric(coef[fit], vecs[fit], np.zeros((int(fit.sum()), 3)))
        n[fit] = n_q  # the surface normal at the point itself
        return n, np.where(fit, sig, noise), np.where(ok, variation, np.nan), coef, vecs, slope, tilt
    return n, noise, np.where(ok, variation, np.nan), tilt


def _plane_tilt(lam, tangents, k):
    """Covariance of the random tilt of PCA plane normals: sum_j e_j e_j^T sigma_n^2 / (k lambda_j).

    Along each tangent eigen-direction e_j (spread lambda_j) the slope of a plane fitted to k points
    with noise sigma_n has the variance of a regression slope, sigma_n^2 / (k lambda_j); sigma_n^2 =
    k lambda_0 / (k - 3) (notebook 04, eq. 5). ``lam`` (m, 3) ascending, already scaled by k / (k - 3)
    as in :func:`_leaf_geometry` (lam[:, 0] = sigma_n^2), ``tangents`` (m, 3, 2) the eigenvectors e_1, e_2.
    """
    raw = np.maximum((k - 3) * lam[:, 1:], k * 1e-300)  # k lambda_j of the unscaled covariance
    w = np.clip(lam[:, :1] / raw, 0.0, 1.0)  # tilt variance along e_1, e_2
    e1, e2 = tangents[:, :, 0], tangents[:, :, 1]
    return w[:, 0, None, None] * e1[:, :, None] * e1[:, None, :] + w[:, 1, None, None] * e2[:, :, None] * e2[:, None, :]


def _quadric_kernel(X, nb, qpos, V, coef, sig, slope):  # pragma: no cover - compiled
    """Local quadric h = a u^2 + b uv + c v^2 + d u + e v + f per neighbourhood, in the PCA frame at q.

    (u, v) are the coordinates along the two largest eigenvectors, h along the normal
    (V's columns: eigenvalues ascending), all relative to the query point q itself and
    scaled by the neighbourhood's extent for conditioning. Least squares by the 6x6
    normal equations (Gaussian elimination with partial pivoting);
    sig = sqrt(RSS / (m - 6)), the noise about the curved surface; ``slope`` holds the
    covariance (var d, cov de, var e) of the surface's slopes at q, sig^2 times the (d, e)
    block of the inverse normal matrix: the random tilt of the quadric's normal.
    """
    m, k = nb.shape
    N = np.empty((6, 6))
    g = np.empty(6)
    r = np.empty(6)
    c = np.empty((6, 3))
    for i in range(m):
        q = qpos[i]
        nx, ny, nz = V[i, 0, 0], V[i, 1, 0], V[i, 2, 0]
        ax, ay, az = V[i, 0, 2], V[i, 1, 2], V[i, 2, 2]
        bx, by, bz = V[i, 0, 1], V[i, 1, 1], V[i, 2, 1]
        slope[i, :] = np.nan
        if not (np.isfinite(nx) and np.isfinite(ax) and np.isfinite(bx)) or k < 7:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        s2 = 0.0
        for j in range(k):
            p = nb[i, j]
            wx, wy, wz = X[p, 0] - X[q, 0], X[p, 1] - X[q, 1], X[p, 2] - X[q, 2]
            s2 += wx * wx + wy * wy + wz * wz
        s = np.sqrt(s2 / k)
        if s == 0.0:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        N[:, :] = 0.0
        g[:] = 0.0
        hh = 0.0
        for j in range(k):
            p = nb[i, j]
            wx, wy, wz = X[p, 0] - X[q, 0], X[p, 1] - X[q, 1], X[p, 2] - X[q, 2]
            u = (wx * ax + wy * ay + wz * az) / s
            v = (wx * bx + wy * by + wz * bz) / s
            h = wx * nx + wy * ny + wz * nz
            r[0], r[1], r[2], r[3], r[4], r[5] = u * u, u * v, v * v, u, v, 1.0
            for a in range(6):
                g[a] += r[a] * h
                for b in range(a, 6):
                    N[a, b] += r[a] * r[b]
            hh += h * h
        for a in range(6):
            for b in range(a):
                N[a, b] = N[b, a]
        A = N.copy()
        c[:, :] = 0.0  # right-hand sides: g, and the unit vectors of d and e (their inverse columns)
        c[:, 0] = g
        c[3, 1] = 1.0
        c[4, 2] = 1.0
        ok = True
        for col in range(6):  # elimination with partial pivoting
            piv = col
            for row in range(col + 1, 6):
                if abs(A[row, col]) > abs(A[piv, col]):
                    piv = row
            if abs(A[piv, col]) <= 1e-12 * abs(N[col, col]) + 1e-300:
                ok = False
                break
            if piv != col:
                for b in range(6):
                    A[col, b], A[piv, b] = A[piv, b], A[col, b]
                for b in range(3):
                    c[col, b], c[piv, b] = c[piv, b], c[col, b]
            for row in range(col + 1, 6):
                f = A[row, col] / A[col, col]
                for b in range(col, 6):
                    A[row, b] -= f * A[col, b]
                for b in range(3):
                    c[row, b] -= f * c[col, b]
        if not ok:
            coef[i, :] = np.nan
            sig[i] = np.nan
            continue
        for b in range(3):
            for col in range(5, -1, -1):
                t = c[col, b]
                for a in range(col + 1, 6):
                    t -= A[col, a] * c[a, b]
                c[col, b] = t / A[col, col]
        rss = hh
        for a in range(6):
            rss -= c[a, 0] * g[a]
        sig[i] = np.sqrt(max(rss, 0.0) / (k - 6))
        # back to metres: u_scaled = u / s
        coef[i, 0], coef[i, 1], coef[i, 2] = c[0, 0] / (s * s), c[1, 0] / (s * s), c[2, 0] / (s * s)
        coef[i, 3], coef[i, 4], coef[i, 5] = c[3, 0] / s, c[4, 0] / s, c[5, 0]
        s2n = sig[i] * sig[i] / (s * s)
        slope[i, 0], slope[i, 1], slope[i, 2] = s2n * c[3, 1], s2n * 0.5 * (c[4, 1] + c[3, 2]), s2n * c[4, 2]


if HAVE_NUMBA:
    _quadric = numba.njit(cache=True, nogil=True)(_quadric_kernel)
else:  # pragma: no cover - depends on the environment
    _quadric = _quadric_kernel


def _on_quadric(coef, frame, w):
    """Offset from points to the local quadric along its frame normal, and the surface normal there.

    In the frame at q (columns of ``frame``: normal n, minor tangent t2, major tangent t1):
    (u, v, h) = w . (t1, t2, n) for w = p - q; the surface height is
    h_s(u, v) = a u^2 + b uv + c v^2 + d u + e v + f; the foot point is
    q' = p + (h_s - h) n, and the surface normal there n - dh_s/du t1 - dh_s/dv t2 (normalised).
    """
    n, t2, t1 = frame[:, :, 0], frame[:, :, 1], frame[:, :, 2]
    u = np.einsum("ij,ij->i", w, t1)
    v = np.einsum("ij,ij->i", w, t2)
    h = np.einsum("ij,ij->i", w, n)
    a, b, c, d, e, f = coef.T
    hs = a * u * u + b * u * v + c * v * v + d * u + e * v + f
    gu, gv = 2 * a * u + b * v + d, b * u + 2 * c * v + e
    normal = n - gu[:, None] * t1 - gv[:, None] * t2
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(normal[:, 2:3] < 0, -normal, normal)
    return (hs - h)[:, None] * n, normal


class _Geometry:
    """Normals and noise of one cloud, computed on demand and cached (private).

    ICP with a thinned source needs the target normals only at the few target
    points that are ever matched; computing them lazily saves most of the work.
    The cache holds one entry per distinct point (leaf position of the kd-tree, exact
    duplicates merged) for the whole ICP call: the target does not move, so no point
    is computed twice. Storage is compact: a slot per computed point (``slot``, -1 for
    none) into buffers that grow with the points actually used, so that a 10-million-point
    target whose ICP touches 300,000 points holds 300,000 normals, not 10 million.
    ``n_computed`` counts the points whose geometry was computed (tests use it).
    """

    def __init__(self, points, k, normals=None, tree=None, quadric=False, keep_tilt=False):
        self.tree = KDTree(points, merge_duplicates=True) if tree is None else tree
        self.k, self.quadric, self.keep_tilt = k, quadric, keep_tilt
        self.cols = np.ascontiguousarray(self.tree.data.T)  # coordinate columns for contiguous gathers
        self.given = normals  # per input point, or None
        self.slot = np.full(self.tree.n, -1, dtype=np.int32 if self.tree.n < 2**31 else np.int64)
        self.n_computed = 0
        self._store = {}  # name -> buffer (capacity, ...), rows 0..n_computed-1 used

    def _grow(self, values):
        """Append the rows of each named array to its buffer (doubling the capacity when full)."""
        n_new = len(next(iter(values.values())))
        for name, v in values.items():
            buf = self._store.get(name)
            need = self.n_computed + n_new
            if buf is None or len(buf) < need:
                cap = max(need, 2 * (0 if buf is None else len(buf)), 1024)
                bigger = np.empty((cap,) + v.shape[1:], dtype=v.dtype)
                if buf is not None:
                    bigger[: self.n_computed] = buf[: self.n_computed]
                self._store[name] = buf = bigger
            buf[self.n_computed : need] = v
        self.n_computed += n_new

    _SHAPES = dict(normals=(3,), noise=(), coef=(6,), frame=(3, 3), slope=(3,), tilt=(3, 3))

    def _get(self, name, pos):
        if name not in self._store:  # nothing computed yet (e.g. no pairs at all)
            return np.full((len(pos),) + self._SHAPES[name], np.nan)
        return self._store[name][self.slot[pos]]

    def at(self, index, need_noise=False):
        pos = self.tree.representative[index]
        if need_noise or self.given is None:
            todo = self.slot[pos] < 0
            if todo.any():
                mark = np.zeros(self.tree.n, dtype=bool)
                mark[pos[todo]] = True
                new = np.flatnonzero(mark)  # sorted leaf positions: coherent queries, no sort
                out = _leaf_geometry(self.tree, self.cols, new, self.k, self.quadric)
                values = dict(normals=out[0], noise=out[1])
                if self.keep_tilt:
                    values["tilt"] = out[-1]()
                if self.quadric:
                    values.update(coef=out[3], frame=out[4], slope=out[5])
                self.slot[new] = np.arange(self.n_computed, self.n_computed + len(new))
                self._grow(values)
        normals = self._get("normals", pos) if self.given is None else self.given[index]
        noise = self._get("noise", pos) if need_noise or self.given is None else np.full(len(pos), np.nan)
        return normals, noise

    def foot(self, index, w):
        """Offsets (m, 3) from the points ``q + w`` to the local quadric of ``q`` = point ``index``, and
        the surface normals there (requires :meth:`at` first); rows without a quadric get NaN offsets."""
        pos = self.tree.representative[index]
        coef = self._get("coef", pos)  # a copy (fancy indexing)
        coef[:, 5] = 0.0  # the surface through the measured q itself (see _Matcher.__call__)
        return _on_quadric(coef, self._get("frame", pos), w)

    def plane_tilt(self, index):
        """Covariance (m, 3, 3) of the random tilt of the PCA plane normals at the points ``index``
        (:func:`_plane_tilt`), stored with the normals (``keep_tilt``); computed here for points not
        yet matched."""
        if not self.keep_tilt:
            raise LabkitError("this geometry keeps no tilt covariances (keep_tilt=False)")
        self.at(index, need_noise=True)
        return self._get("tilt", self.tree.representative[index])

    def tilt(self, index):
        """Covariance (m, 3, 3) of the random tilt of the quadric normals at the points ``index``.

        The normal n - d t1 - e t2 at q tilts by -(dd t1 + de t2) with the covariance of the
        fitted slopes (d, e) (requires :meth:`at` first; NaN where no quadric was fitted).
        """
        pos = self.tree.representative[index]
        T = self._get("frame", pos)[:, :, [2, 1]]  # tangents t1 (u), t2 (v)
        vd, cde, ve = self._get("slope", pos).T
        C = np.stack([np.stack([vd, cde], -1), np.stack([cde, ve], -1)], -2)
        return np.einsum("mia,mab,mjb->mij", T, C, T)

    def compute(self, index, k):
        """Normals, noise and change of curvature at ``index`` with k neighbours (no caching)."""
        return _local_geometry(self.tree, self.cols, index, k)


# --------------------------------------------------------------------- sampling


def _sample(points, geometry, spec, rng):
    """Indices of the sampled source points (step 1)."""
    n = len(points)
    if spec is None or (isinstance(spec, str) and spec == "auto" and n <= AUTO_LIMIT):
        return np.arange(n)
    if isinstance(spec, str) and spec == "auto":
        return _auto_sample(points, geometry, AUTO_PAIRS, rng)
    if isinstance(spec, str):
        raise LabkitError(f"sample must be None, 'auto', an int or (method, value), got {spec!r}")
    if isinstance(spec, (int, np.integer)):
        spec = ("random", int(spec))
    kind, value = spec
    choice(kind, ("random", "voxel", "normal_space"), "sample method")
    if kind == "voxel":
        return _voxel_sample(points, positive(value, "voxel size"), rng)
    m = int(positive(value, "sample size"))
    if m >= n:
        return np.arange(n)
    if kind == "random":
        return np.sort(rng.choice(n, m, replace=False))
    pool = np.sort(rng.choice(n, min(n, 6 * m), replace=False))  # candidates for the normals
    coarse, _, variation = geometry.compute(pool, min(10, geometry.k))  # coarse normals suffice for the bins
    has = np.isfinite(coarse[:, 0])  # no bin for points without a normal (a point or a line, issue 16)
    if has.sum() >= m:
        pool, coarse, variation = pool[has], coarse[has], variation[has]
    else:
        coarse = np.where(has[:, None], coarse, [0.0, 0.0, 1.0])
    # rare normals are often artefacts of neighbourhoods across an edge: keep planar candidates only
    planar = variation < MAX_VARIATION
    if planar.sum() >= m:
        pool, coarse = pool[planar], coarse[planar]
    return pool[_normal_space_sample(coarse, m, rng)]


def _voxel_sample(points, size, rng):
    """One random point per cubic voxel of edge ``size``."""
    order = rng.permutation(len(points))
    _, first = np.unique(_voxel_keys(points, size)[order], return_index=True)
    return np.sort(order[first])


def _voxel_keys(points, size):
    """One int64 key per cubic voxel of edge ``size`` (21 bits per axis; wider grids raise).

    Column by column: no (n, 3) temporaries on a 10-million-point cloud.
    """
    key = np.zeros(len(points), dtype=np.int64)
    for a in range(3):
        cell = np.floor(points[:, a] / size).astype(np.int64)  # the grid through 0 of the local frame
        if cell.size:
            cell -= cell.min()
            if cell.max() >= 2**21:
                raise LabkitError(
                    f"voxel size {size:g} m is too small for the cloud's extent (over 2 million voxels per axis)"
                )
        key |= cell << (21 * (2 - a))
    return key


def _auto_sample(points, geometry, m, rng):
    """About ``m`` source points spread evenly in space and over the normal directions (sample='auto').

    1. The voxel edge h that leaves about 2 m occupied voxels: the count at a trial edge on a random
       subset, scaled with the surface law count ~ h^-2 (two rounds); one random point per voxel of
       the whole cloud (dense strip overlaps and the scanner's near range count no more than sparse
       parts). 2. Normal-space balance (Rusinkiewicz & Levoy 2001) from these 2 m candidates to m:
       every normal direction keeps its points up to an equal quota, so that walls and slopes, which
       determine the horizontal shift, are not thinned as much as the ground.
    The shift's covariance stays honest: the cluster-robust block covariance (eq. 5.13) takes its
    variance from the residuals of the pairs actually used, whatever their number.
    """
    n = len(points)
    sub = points[rng.choice(n, min(n, 1_000_000), replace=False)] if n > 1_000_000 else points
    lo, hi = points.min(axis=0), points.max(axis=0)
    ext = np.sort(hi - lo)[::-1]
    h = max(float(np.sqrt(ext[0] * max(ext[1], 1e-9) / (2 * m))), 1e-6)  # a horizontal surface's guess
    for _ in range(2):  # the subset has >= 2 points per voxel at this size: nearly all voxels occupied
        h *= float(np.sqrt(max(_n_distinct(_voxel_keys(sub, h)), 1) / (2 * m)))
    pool = _voxel_sample(points, h, rng)
    if len(pool) <= m:
        return pool
    coarse, _, variation = geometry.compute(pool, min(10, geometry.k))  # coarse normals suffice for the bins
    # rough points (vegetation) have random normals and would fill the rare bins: planar candidates only
    planar = np.isfinite(coarse[:, 0]) & (variation < MAX_VARIATION)
    if planar.sum() >= m:
        pool, coarse = pool[planar], coarse[planar]
    coarse = np.where(np.isfinite(coarse[:, :1]), coarse, [0.0, 0.0, 1.0])
    return pool[_normal_space_sample(coarse, m, rng)]


def _n_distinct(keys):
    """Number of distinct values, by a sort (``len(np.unique(keys))`` hashes in numpy 2.x: 0.46 s
    against 9 ms on 523,000 distinct int64 keys)."""
    if len(keys) == 0:
        return 0
    s = np.sort(keys)
    return int(np.count_nonzero(s[1:] != s[:-1])) + 1


def _normal_space_sample(normals, m, rng, bins=8):
    """Rusinkiewicz & Levoy (2001): as even a share as possible for each normal-direction bin."""
    nrm = np.where(normals[:, 2:3] < 0, -normals, normals)  # orientation-free
    theta = np.arccos(np.clip(nrm[:, 2], 0, 1))  # polar angle 0..90 deg
    phi = np.arctan2(nrm[:, 1], nrm[:, 0]) % np.pi  # axial azimuth 0..180 deg
    key = np.minimum((theta / (np.pi / 2) * bins).astype(int), bins - 1) * 2 * bins
    key += np.minimum((phi / np.pi * 2 * bins).astype(int), 2 * bins - 1)
    key = np.where(theta < np.pi / (4 * bins), -1, key)  # all near-horizontal surfaces share one bin
    order = rng.permutation(len(key))
    order = order[np.argsort(key[order], kind="stable")]
    ks = key[order]
    starts = np.r_[0, np.flatnonzero(np.diff(ks)) + 1]
    sizes = np.diff(np.r_[starts, len(ks)])
    rank = np.arange(len(ks)) - np.repeat(starts, sizes)
    quota = _quota(sizes, m)
    return np.sort(order[rank < quota])


def _quota(sizes, m):
    """Largest per-bin quota q with sum(min(size, q)) <= m."""
    lo, hi = 0, int(sizes.max())
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if np.minimum(sizes, mid).sum() <= m else (lo, mid - 1)
    return max(lo, 1)


# --------------------------------------------------------------------- the matcher


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
    geometry: _Geometry
    target_class: np.ndarray | None
    options: dict
    origin: np.ndarray
    n_source: int
    source_class: np.ndarray | None = None  # class of each sampled source point (None: no classification)
    query_order: np.ndarray | None = None  # sampled source points in spatial (leaf) order: coherent queries

    def __call__(self, R=None, t=None) -> Correspondences:
        """Correspondences of the source moved by p' = R p + t (local frame)."""
        opt = self.options
        R = np.eye(3) if R is None else R
        t = np.zeros(3) if t is None else t
        p = _rotated(self.source, R) + t  # not `@`: a BLAS call per iteration (see _rotated)
        rule = self.source_rule.copy()
        live = self.query_order[rule[self.query_order] == 0]  # in leaf order: neighbouring queries in cache
        m = len(p)
        tidx = np.full(m, -1)
        d = np.full((m, 3), np.nan)
        nt = np.full((m, 3), np.nan)
        noise_t = np.full(m, np.nan)
        # (3) nearest neighbour in the target kd-tree, within max_distance
        workers = -1 if len(live) > 20000 else 1  # thread start-up dominates small queries
        dist, j = self.tree.query(p[live], k=1, distance_upper_bound=opt["max_distance"], workers=workers)
        # back to ascending rows (one scatter), so that the steps below read and write in order
        nearest = np.full(m, -1)
        nearest[live] = np.where(np.isfinite(dist), j, -1)
        rule[live[~np.isfinite(dist)]] = _CODE["distance"]
        live = np.flatnonzero(nearest >= 0)
        j = nearest[live]
        tidx[live] = j
        d[live] = self.target[j] - p[live]
        nt[live], noise_t[live] = self.geometry.at(j, need_noise=opt["need_noise"])
        nearest_d = d  # q_j - p_i: the duplicate rule keeps the nearest source point by this
        if opt["surface"] == "quadric" and len(live):
            nearest_d = d.copy()
            # the foot point on the target's local quadric replaces q_j: no curvature bias (sagitta).
            # The quadric is shifted to pass through the measured q_j (its slopes and curvatures
            # kept): q_j's noise then enters one residual only, as with the plane; the fitted value
            # would spread every target point's noise over the ~k residuals around it, correlated
            # beyond the block cells (stated std 1.4-1.6 times too small on sparse hills)
            off, n_s = self.geometry.foot(j, -d[live])
            fit = np.isfinite(off[:, 0])
            d[live[fit]], nt[live[fit]] = off[fit], n_s[fit]  # the quadric's normal at the foot point
        # a target point whose neighbourhood is a point or a line has no normal (issue 16)
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
            ns = _rotated(self.source_normals[live], R)
            cosang = np.abs(np.einsum("ij,ij->i", ns, nt[live]))
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


def _rotated(points, R):
    """points @ R.T for a tall (m, 3) array, by einsum.

    ``@`` hands a tall (m, 3) x (3, 3) product to the threaded BLAS, whose threads spin against
    the kd-tree's threads: on a loaded 2-core machine 80 ms median for 100,000 points, einsum 8 ms.
    """
    return np.einsum("ij,kj->ik", points, R)


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
    dist2 = np.einsum("ij,ij->i", d[live], d[live])
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


def prepare(
    source,
    target,
    *,
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
) -> _Matcher:
    """Build the fixed part of the matching once (kd-tree, sampling, exclusions).

    The arguments are those of :func:`match`; ``origin`` is the shared local
    origin (default: from the target). ICP calls this once and the returned
    matcher in every iteration.
    """
    src = as_points(source, min_points=3, name="source")
    tgt = as_points(target, min_points=3, name="target")
    if not 3 <= int(k) <= len(tgt):
        raise LabkitError(f"k must lie between 3 and the number of target points ({len(tgt)}), got {k}")
    rng = as_rng(rng)
    origin = local_origin(tgt) if origin is None else np.asarray(origin, dtype=np.float64)
    src_l = reduce(src, origin)
    if tree is not None and getattr(tree, "n", None) != len(tgt):
        raise LabkitError(f"the given tree holds {getattr(tree, 'n', '?')} points, the target has {len(tgt)}")
    # the target's compiled kd-tree (exact duplicates merged) and its geometry cache: once per call
    # (kept for the next step on the same target, e.g. the distances of labkit register)
    tree = local_tree(tgt, origin, merge_duplicates=True)
    choice(surface, SURFACES, "surface")
    if surface == "auto":
        surface = _auto_surface(tree, int(k))
    quadric = surface == "quadric"
    if quadric and int(k) < 10:
        raise LabkitError(f"surface='quadric' fits 6 parameters: k must be at least 10, got {k}")
    tgt_geo = _Geometry(
        None, int(k), _given_normals(target_normals, len(tgt), "target_normals"), tree, quadric, keep_tilt=True
    )
    n_tgt = len(tgt)  # the tree holds the target (one copy of a large cloud, read through _TreePoints)
    need_src_geo = (
        max_angle_deg is not None or noise_weighting or max_noise is not None
        or (isinstance(sample, (tuple, list)) and sample[0] == "normal_space")
        or (isinstance(sample, str) and sample == "auto" and len(src_l) > AUTO_LIMIT)
    )  # fmt: skip
    src_geo = None
    if need_src_geo:
        if len(src_l) < k:
            raise LabkitError(f"the source needs at least k = {k} points for its normals, got {len(src_l)}")
        src_geo = _Geometry(
            src_l, int(k), _given_normals(source_normals, len(src_l), "source_normals"), quadric=quadric
        )
    # (1) sampling
    idx = _sample(src_l, src_geo, sample, rng)
    # query order: the sampled source points in the leaf order of a kd-tree over them
    src_tree = src_geo.tree if src_geo is not None else KDTree(src_l[idx])
    if src_geo is not None:
        order = np.argsort(src_tree.representative[idx], kind="stable")
    else:
        order = np.empty(len(idx), dtype=np.intp)
        order[:] = src_tree.indices
    options = dict(
        max_distance=np.inf if max_distance is None else positive(max_distance, "max_distance"),
        max_angle_deg=None if max_angle_deg is None else positive(max_angle_deg, "max_angle_deg"),
        classes=None if classes is None else np.asarray(list(classes)),
        class_sigma=dict(class_sigma or {}),
        default_sigma=_non_negative(default_sigma, "default_sigma"),
        noise_weighting=bool(noise_weighting),
        max_noise=None if max_noise is None else positive(max_noise, "max_noise"),
        need_noise=bool(noise_weighting or max_noise is not None),
        sample=sample,
        unique=bool(unique),
        k=int(k),
        surface=surface,
    )
    # (2) exclusions on the source side and a priori sigma per source point
    src_cls, tgt_cls = _classes_of(source, len(src)), _classes_of(target, len(tgt))
    if classes is not None:
        _require_classes(source, "source")
        _require_classes(target, "target")
    src_normals, src_noise = (None, None) if src_geo is None else src_geo.at(idx, need_noise=True)
    rule, sigma = _source_rules(src_cls, idx, src_noise, options)
    return _Matcher(
        src_l[idx], idx, src_normals, sigma, rule, _TreePoints(tree, n_tgt), tree, tgt_geo, tgt_cls, options, origin, len(src),
        None if src_cls is None else src_cls[idx], order,
    )  # fmt: skip


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
    dist = tree.query(tree.data[::step], k=k, workers=1)[0][:, -1]
    return "quadric" if float(np.median(dist)) > AUTO_QUADRIC_RADIUS else "plane"


def _non_negative(value, name):
    return 0.0 if value == 0 else positive(value, name)


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


def match(
    source,
    target,
    *,
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
    target_normals, source_normals : array_like (n, 3), optional
        Given normals; otherwise PCA normals of k neighbours, computed only where needed.
    max_distance : float or None
        Gate on the nearest-neighbour distance in metres (eq. 5.1); None: no gate.
    max_angle_deg : float or None
        Gate on the angle between the normals (orientation-free); None: no gate.
    classes : sequence of int, optional
        Allowed ASPRS classes (e.g. (2, 6, 11)); others are rejected by rule 'class'.
        Both clouds need a ``classification`` attribute (else :class:`LabkitError`).
    class_sigma : dict int -> float, optional
        A priori standard deviation per class in metres (roof precise, vegetation not);
        classes not listed get ``default_sigma`` (default 0: only their local noise counts).
    noise_weighting : bool
        Add each point's local noise (std along its normal) to its variance.
    max_noise : float, optional
        Reject points whose local noise exceeds this (m), e.g. vegetation.
    sample : None, 'auto', int or (method, value)
        ``("random", n)``, ``("voxel", size_m)`` or ``("normal_space", n)``; an int means random.
        ``'auto'``: the whole source up to :data:`AUTO_LIMIT` points, a larger one thinned to about
        :data:`AUTO_PAIRS` points spread evenly in space and over the normal directions (one per
        voxel of an edge chosen from the density, then normal-space balance; :func:`_auto_sample`).
    unique : bool
        At most one source point per target point (the closest; the others are
        rejected as 'duplicate'), so that no target point's noise enters two
        residuals and the residuals stay uncorrelated.
    k : int
        Neighbours for normals and local noise.
    rng : int or Generator, optional
        For the sampling.
    surface : {'plane', 'quadric', 'auto'}
        Local surface model of both clouds from their k neighbours. 'plane' (default): the
        PCA plane (notebook 04), right for dense data. 'quadric': a quadric
        h = a u^2 + b uv + c v^2 + d u + e v + f fitted in the PCA frame at each target
        point; for sparse curved ground (ALS at 0.5-1 pts/m^2 on hills) the plane's l3
        holds the curvature, so its noise (and weight, and ``max_noise``) is wrong by
        that much, and the point-to-plane residual carries the sagitta between p_i and
        q_j. With 'quadric' the noise is the spread about the quadric (redundancy
        k - 6), ``d`` runs from p_i to its foot point on the target's quadric, shifted to pass
        through the measured q_j (its slopes and curvatures kept, so that q_j's noise enters one
        residual only, as with the plane), and ``target_normal`` is the quadric's normal at
        the foot point. Needs k >= 10. 'auto': the quadric where the target's k-neighbourhoods are wider
        than 1 m (median radius; sparse ALS), else the plane; ``settings['surface']`` of the
        result names the choice.
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
    """
    matcher = prepare(
        source, target, target_normals=target_normals, source_normals=source_normals,
        max_distance=max_distance, max_angle_deg=max_angle_deg, classes=classes,
        class_sigma=class_sigma, default_sigma=default_sigma, noise_weighting=noise_weighting,
        max_noise=max_noise, sample=sample, unique=unique, k=k, rng=rng, tree=tree, surface=surface,
    )  # fmt: skip
    return matcher()
