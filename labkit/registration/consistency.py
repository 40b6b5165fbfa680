"""Do groups of correspondences (classes or spatial blocks) support one transformation? (eqs. 5.16-5.17)"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..core.distributions import chi2_sf
from ..core.report import ReportMixin, fmt


@dataclass(frozen=True, eq=False, repr=False)
class Consistency(ReportMixin):
    """Test whether groups of correspondences (classes or spatial blocks) support one transformation.

    Every group's own least-squares estimate (in the directions that the group determines) is
    compared with the common estimate of all groups; the statistic is a generalized Cochran Q,
    T = sum_g (y_g - V_g^T x)^T C_g^-1 (y_g - V_g^T x) (eq. 5.16), chi-square with
    ``dof = sum_g r_g - rank`` degrees of freedom when one transformation fits every group.

    Attributes
    ----------
    grouping : str
        'class' (class of the target point), 'local noise' (terciles) or 'block' (spatial quadrants).
    groups : tuple of str
        Names of the tested groups (groups that were too small are left out).
    n : ndarray of int
        Correspondences per group.
    statistic : float
        T of eq. (5.16).
    dof : int
        Degrees of freedom.
    p_value : float
        chi-square tail probability of T.
    alpha : float
        Level of the test.
    contribution : ndarray
        Each group's share of T (its own sum in eq. 5.16).
    offset : ndarray (g, 3)
        Each group's shift (dX, dY, dZ) relative to the result in metres (NaN where the
        group does not determine the axis).
    offset_std : ndarray (g, 3)
        Standard deviation of ``offset`` from the group's own covariance.
    between : ndarray (u, u)
        When the test rejects: a sandwich with the G groups as clusters,
        G / (G-1) N^-1 (sum_g s_g s_g^T) N^-1 with s_g = N_g (x_g - x) the pull of group g on the
        result x (eq. 5.17), in the tested parameters (ICP adds it to the result's covariance);
        zeros otherwise. N^-1 s_g is how far group g has moved the result from the other groups'
        estimate; the sum treats each group's disagreement as a random group effect.
    std_ratio : ndarray (3,)
        Standard deviation of dX, dY, dZ with ``between`` divided by the one without (1 when the
        groups agree; set by the registration method).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration import icp
    >>> from labkit.synthetic import wavy_surface
    >>> rng = np.random.default_rng(1)
    >>> target = wavy_surface(1500, rng)  # slopes in X and Y, 2 mm noise
    >>> res = icp(wavy_surface(300, rng) - [0.05, 0.02, 0.03], target)  # another sampling, moved
    >>> c = res.consistency  # do the groups of correspondences agree on one shift?
    >>> c.grouping, len(c.groups), c.agree
    ('local noise', 3, True)
    """

    grouping: str
    groups: tuple
    n: np.ndarray
    statistic: float
    dof: int
    p_value: float
    alpha: float
    contribution: np.ndarray
    offset: np.ndarray
    offset_std: np.ndarray
    between: np.ndarray | None = None
    std_ratio: np.ndarray = field(default_factory=lambda: np.ones(3))

    #: The groups' spread counts as affecting the result when it widens a standard deviation by more.
    AFFECTS = 2.0

    @property
    def agree(self) -> bool:
        """The test's verdict: True unless the groups disagree at level ``alpha``."""
        return not (self.dof > 0 and self.p_value < self.alpha)

    @property
    def consistent(self) -> bool:
        """False when the groups disagree and their spread widens a shift component's standard deviation
        by more than a factor of 2 (the shift depends on which group one believes: changes suspected)."""
        return self.agree or bool(np.nanmax(self.std_ratio) <= self.AFFECTS)

    @property
    def worst(self) -> str:
        """The group with the largest share of the test statistic."""
        return self.groups[int(np.argmax(self.contribution))] if self.groups else ""

    def _report(self):
        if self.agree:
            verdict = "the groups agree"
        elif self.consistent:
            verdict = "the groups differ, but the shift hardly depends on it"
        else:
            verdict = "INCONSISTENT: the shift depends on the group, changes between the epochs suspected"
        rows = [
            ("groups by", self.grouping),
            ("T / dof", f"{self.statistic:.1f} / {self.dof}  (p = {self.p_value:.2g}, alpha = {self.alpha:g})"),
            ("verdict", verdict),
        ]
        for name, n, c, off, s in zip(self.groups, self.n, self.contribution, self.offset, self.offset_std):
            shift = ", ".join("-" if np.isnan(o) else f"{1000 * o:+.1f}+-{1000 * e:.1f}" for o, e in zip(off, s))
            rows.append((f"{name} (n={n})", f"T_g = {c:.1f}; dX, dY, dZ - result = {shift} mm"))
        if not self.agree:
            rows.append(("std widened by", fmt(self.std_ratio, 2) + " (spread between the groups, eq. 5.17)"))
        return "Consistency of the groups", [("", rows)]


def group_consistency(A, l, P, labels, names, cells, *, translation, rel_threshold=1e-2, alpha=1e-3,
                      grouping="class", min_n=30) -> Consistency | None:
    """Generalized Cochran Q test of one transformation for all groups (eq. 5.16).

    Parameters
    ----------
    A : ndarray (m, r, u)
        Design rows of the kept correspondences (u parameters, r components each).
    l : ndarray (m, r)
        Observations (residuals before the last step).
    P : ndarray (m,)
        Final weights.
    labels : ndarray of int (m,)
        Group of each row (index into ``names``; -1: no group).
    names : sequence of str
    cells : ndarray of int (m,)
        Spatial cell of each row; the groups' covariances are cluster-robust over these cells
        (eq. 5.13 without the robust-weight terms).
    translation : sequence of int
        Columns of tx, ty, tz in A (scaled to metres) for the reported offsets.
    rel_threshold : float
        A group determines the eigen-directions of its N_g above ``rel_threshold`` times its largest one.
    alpha : float
        Level of the test.
    min_n : int
        Smaller groups are not tested.

    Returns
    -------
    Consistency or None
        None when fewer than two groups are large enough.

    References
    ----------
    .. [1] Notebook 05, section 6, eqs. 5.16-5.17.
    .. [2] W. G. Cochran (1954): The combination of estimates from different
       experiments. Biometrics 10(1), 101-129 (the Q statistic that eq. 5.16
       generalizes to vector estimates in the directions each group determines).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.consistency import group_consistency
    >>> rng = np.random.default_rng(0)
    >>> m = 400
    >>> A = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()  # a shift (tx, ty, tz) observed at every row
    >>> labels = np.repeat([0, 1], m // 2)
    >>> cells = np.arange(m) % 20
    >>> l = rng.normal(0.0, 0.01, (m, 3))
    >>> same = group_consistency(A, l, np.ones(m), labels, ["ground", "roofs"], cells, translation=[0, 1, 2])
    >>> same.agree
    True
    >>> l[labels == 1, 2] += 0.05  # the roofs moved 5 cm up
    >>> moved = group_consistency(A, l, np.ones(m), labels, ["ground", "roofs"], cells, translation=[0, 1, 2])
    >>> moved.agree, moved.worst in ("ground", "roofs"), np.abs(moved.offset[:, 2]).round(2).tolist()
    (False, True, [0.03, 0.03])
    """
    u = A.shape[2]
    if u == 0:  # every parameter held: nothing to test
        return None
    N_all = np.einsum("mru,m,mrv->uv", A, P, A)
    x0 = np.linalg.lstsq(N_all, np.einsum("mru,m,mr->u", A, P, l), rcond=None)[0]  # the result's own step
    ys, Ws, Vs, used, ns, deltas, offs_std, scores = [], [], [], [], [], [], [], []
    for g, name in enumerate(names):
        rows = labels == g
        if rows.sum() < max(min_n, 2 * u):
            continue
        Ag, lg, Pg = A[rows], l[rows], P[rows]
        N = np.einsum("mru,m,mrv->uv", Ag, Pg, Ag)
        lam, V = np.linalg.eigh(0.5 * (N + N.T))
        keep = lam >= rel_threshold * max(lam[-1], 1e-300)
        lam, V = lam[keep], V[:, keep]
        y = (V.T @ np.einsum("mru,m,mr->u", Ag, Pg, lg)) / lam  # the group's own estimate of V^T x
        v = np.einsum("mru,u->mr", Ag, V @ y) - lg
        s = np.einsum("mru,m,mr,ua->ma", Ag, Pg, v, V)  # scores in the group's directions
        _, cell = np.unique(cells[rows], return_inverse=True)
        G = np.zeros((cell.max() + 1, len(lam)))
        np.add.at(G, cell.ravel(), s)
        m, nc, r = len(s), len(G), len(lam)
        if nc >= 2 * r + 1:  # cluster-robust (eq. 5.13)
            M = np.einsum("ci,cj->ij", G, G) * nc / (nc - 1) * m / max(m - r, 1)
        else:  # too few cells: formal sigma0^2 N
            vPv = float(np.einsum("mr,m,mr->", v, Pg, v))
            M = np.diag(lam) * vPv / max(m * A.shape[1] - r, 1)
        C = M / np.outer(lam, lam)
        try:
            W = np.linalg.inv(0.5 * (C + C.T))
        except np.linalg.LinAlgError:
            continue
        ys.append(y), Ws.append(W), Vs.append(V), used.append(name), ns.append(int(rows.sum()))
        # the group's estimate relative to the result, on the parameters it determines
        determined = 1 - (V**2).sum(axis=1) < 0.05  # little share in the directions the group leaves free
        deltas.append(np.where(determined, V @ (y - V.T @ x0), 0.0))
        offs_std.append(np.where(determined, np.sqrt(np.clip(np.diag(V @ C @ V.T), 0, None)), np.nan))
        scores.append(V @ (lam * (y - V.T @ x0)))  # s_g = N_g (x_g - x): the group's pull on the result
    if len(used) < 2:
        return None
    H = sum(V @ W @ V.T for V, W in zip(Vs, Ws))
    b = sum(V @ W @ y for V, W, y in zip(Vs, Ws, ys))
    x = np.linalg.lstsq(H, b, rcond=None)[0]  # common estimate of all groups
    rank = np.linalg.matrix_rank(H, tol=rel_threshold * np.abs(H).max() * 1e-3)
    parts = np.array([float((y - V.T @ x) @ W @ (y - V.T @ x)) for V, W, y in zip(Vs, Ws, ys)])
    T = float(parts.sum())
    dof = int(sum(len(y) for y in ys) - rank)
    p = float(chi2_sf(T, dof)) if dof > 0 else 1.0
    delta, offset_std = np.array(deltas), np.array(offs_std)
    offset = np.where(np.isnan(offset_std), np.nan, delta)[:, translation]
    between = np.zeros((u, u))
    if dof > 0 and p < alpha:  # the groups as clusters of a sandwich (eq. 5.17)
        S = np.array(scores)
        k = len(S)
        Ni_S = np.linalg.lstsq(N_all, S.T, rcond=None)[0]  # N^-1 s_g: each group's influence on the result
        between = Ni_S @ Ni_S.T * k / (k - 1)
    return Consistency(grouping, tuple(used), np.array(ns), T, dof, p, float(alpha), parts, offset,
                       offset_std[:, translation], between)


def block_consistency(A, l, P, xyz, cells, degeneracy, *, alpha=1e-3, rel_threshold=1e-2) -> Consistency | None:
    """Do the four spatial quadrants of a translation's observations agree? (eq. 5.16 on blocks)

    For an estimate of (tx, ty, tz) from point-to-plane rows ``A x = l`` (A: the unit normals, m x 3) whose
    groups have no classes: the quadrants about the median X and Y of the points ``xyz``, each with its
    cluster-robust covariance over ``cells``; the directions the ``degeneracy`` report leaves undetermined
    stay out. None when fewer than two quadrants are large enough or nothing is determined.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.degeneracy import degeneracy_report
    >>> rng = np.random.default_rng(0)
    >>> xyz = rng.uniform(0, 10, (800, 3))
    >>> A = rng.normal(size=(800, 3)); A /= np.linalg.norm(A, axis=1, keepdims=True)
    >>> l = A @ [0.1, 0.2, 0.0] + rng.normal(0, 0.01, 800)
    >>> deg = degeneracy_report(A.T @ A, ("tx", "ty", "tz"))
    >>> block_consistency(A, l, np.ones(800), xyz, np.floor(xyz[:, :2]).astype(int), deg).agree
    True
    """
    free = np.asarray(degeneracy.parameter_determined, dtype=bool)
    if not free.any() or len(A) < 8:
        return None
    xy = np.asarray(xyz)[:, :2]
    above = (xy > np.median(xy, axis=0)).astype(int)
    labels = above[:, 0] + 2 * above[:, 1]
    _, cell = np.unique(np.asarray(cells).reshape(len(A), -1), axis=0, return_inverse=True)
    test = group_consistency(np.asarray(A)[:, None, free], np.asarray(l)[:, None], np.asarray(P), labels,
                             ["block SW", "block SE", "block NW", "block NE"], cell.ravel(),
                             translation=list(range(int(free.sum()))), rel_threshold=rel_threshold, alpha=alpha,
                             grouping="block")
    if test is None or free.all():
        return test
    full = np.full((len(test.groups), 3), np.nan)  # offsets on all three axes (NaN where held)
    off, std = full.copy(), full.copy()
    off[:, free], std[:, free] = test.offset, test.offset_std
    return replace(test, offset=off, offset_std=std)

