"""Do groups of correspondences (classes or spatial blocks) support one transformation? (eqs. 5.16-5.17)"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..core.distributions import chi2_sf, f_sf
from ..core.jit import compiled, have_numba
from ..core.report import ReportMixin, fmt


@dataclass(frozen=True, eq=False, repr=False)
class Consistency(ReportMixin):
    """Test whether groups of correspondences (classes or spatial blocks) support one transformation.

    Every group's own least-squares estimate (in the directions that the group determines) is
    compared with the common estimate of all groups; the statistic is a generalized Cochran Q,
    T = sum_g (y_g - V_g^T x)^T C_g^-1 (y_g - V_g^T x) (eq. 5.16) with ``dof = sum_g r_g - rank``.
    The C_g are estimated from a group's cells (delete-one-cell jackknife), so T is referred to
    the Welch-James F approximation rather than to chi-square: with the few cells of a group the
    chi-square test rejected several times too often when one transformation fits every group.

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
        Tail probability of T: T / ``scale`` ~ F(dof, ``denominator_dof``), the Welch-James reference
        for groups whose covariances are estimated from a few cells (chi-square when they are known).
    alpha : float
        Level of this grouping's test: the level of the whole test divided by ``family``.
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
    scale, denominator_dof : float
        Of the reference distribution (see ``p_value``).
    family : int
        Number of groupings tested together (Bonferroni: each at ``alpha``; see :func:`family_level`).

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
    scale: float = np.nan
    denominator_dof: float = np.inf
    family: int = 1

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

    @property
    def _reference(self):
        if not np.isfinite(self.denominator_dof):
            return ""
        return f" from T / {self.scale:.2f} ~ F({self.dof}, {self.denominator_dof:.0f})"

    @property
    def _level(self):
        return f" = {self.alpha * self.family:g} / {self.family} groupings" if self.family > 1 else ""

    def _report(self):
        if self.agree:
            verdict = "the groups agree"
        elif self.consistent:
            verdict = "the groups differ, but the shift hardly depends on it"
        else:
            verdict = "INCONSISTENT: the shift depends on the group, changes between the epochs suspected"
        rows = [
            ("groups by", self.grouping),
            ("T / dof", f"{self.statistic:.1f} / {self.dof}  (p = {self.p_value:.2g}{self._reference}, alpha = "
                        f"{self.alpha:.2g}{self._level})"),
            ("verdict", verdict),
        ]
        for name, n, c, off, s in zip(self.groups, self.n, self.contribution, self.offset, self.offset_std):
            shift = ", ".join("-" if np.isnan(o) else f"{1000 * o:+.1f}+-{1000 * e:.1f}" for o, e in zip(off, s))
            rows.append((f"{name} (n={n})", f"T_g = {c:.1f}; dX, dY, dZ - result = {shift} mm"))
        if not self.agree:
            rows.append(("std widened by", fmt(self.std_ratio, 2) + " (spread between the groups, eq. 5.17)"))
        return "Consistency of the groups", [("", rows)]


def group_consistency(A, l, P, labels, names, cells, *, translation, rel_threshold=1e-2, alpha=1e-3,
                      grouping="class", min_n=30, normal=None) -> Consistency | None:
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
    normal : tuple of ndarray, optional
        ``normal_equations(A, P, l)`` when the caller has it (several groupings of the same rows).

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
    .. [3] S. Johansen (1980): The Welch-James approximation to the distribution of the
       residual sum of squares in a weighted linear regression. Biometrika 67(1), 85-92
       (the F reference for estimated covariances, :func:`welch_james`).

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
    N_all, n_all = normal_equations(A, P, l) if normal is None else normal
    x0 = np.linalg.lstsq(N_all, n_all, rcond=None)[0]  # the result's own step
    fits = []  # each group's own fit in the directions it determines
    for g, name in enumerate(names):
        rows = labels == g
        if rows.sum() < max(min_n, 2 * u):
            continue
        at = np.flatnonzero(rows)  # (a gather by index: several times faster than by the mask)
        Ag, lg, Pg = np.take(A, at, axis=0), np.take(l, at, axis=0), np.take(P, at)
        N, n = normal_equations(Ag, Pg, lg)
        lam, V = np.linalg.eigh(0.5 * (N + N.T))
        keep = lam >= rel_threshold * max(lam[-1], 1e-300)
        lam, V = lam[keep], V[:, keep]
        y = (V.T @ n) / lam  # the group's own estimate of V^T x
        v = np.einsum("mru,u->mr", Ag, V @ y) - lg
        cell = cell_labels(cells[rows])
        B = Ag @ V
        fits.append((name, rows, B, Pg, v, cell, lam, V, y, *cell_sums(B, Pg, v, cell)))
    deff, nu_all = design_effect(fits)
    ys, Ws, Vs, used, ns, deltas, offs_std, scores, nus = [], [], [], [], [], [], [], [], []
    for name, rows, B, Pg, v, cell, lam, V, y, Nc, gc in fits:
        C, nu = cell_jackknife(Nc, gc, cell, lam)
        if C is None:  # too few cells: formal sigma0^2 N^-1, widened by the correlation within the groups
            m, r = len(v), len(lam)
            C = np.diag(1 / lam) * float(np.einsum("mr,m,mr->", v, Pg, v)) / max(v.size - r, 1)
            C, nu = C * deff, min(nu_all, max(v.size - r, 1))  # as uncertain as the design effect
        try:
            W = np.linalg.inv(0.5 * (C + C.T))
        except np.linalg.LinAlgError:
            continue
        nus.append(nu)
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
    scale, nu_f = welch_james(H, Vs, Ws, nus, dof)
    if dof <= 0:
        p = 1.0
    elif np.isfinite(nu_f) and nu_f < 1e6:
        p = float(f_sf(T / scale, dof, nu_f))
    else:  # covariances known as good as exactly: the chi-square test
        p = float(chi2_sf(T * dof / scale, dof))
    delta, offset_std = np.array(deltas), np.array(offs_std)
    offset = np.where(np.isnan(offset_std), np.nan, delta)[:, translation]
    between = np.zeros((u, u))
    if dof > 0 and p < alpha:  # the groups as clusters of a sandwich (eq. 5.17)
        S = np.array(scores)
        k = len(S)
        Ni_S = np.linalg.lstsq(N_all, S.T, rcond=None)[0]  # N^-1 s_g: each group's influence on the result
        between = Ni_S @ Ni_S.T * k / (k - 1)
    return Consistency(grouping, tuple(used), np.array(ns), T, dof, p, float(alpha), parts, offset,
                       offset_std[:, translation], between, scale=scale, denominator_dof=nu_f)


def normal_equations(A, P, l):
    """N = A^T P A and n = A^T P l (eq. 5.7) of the rows A (m, r, u), weights P (m,), observations l (m, r).

    One compiled pass (the sums in the order of ``np.einsum``'s loop over the rows, (a_u p) a_v:
    the same numbers), else numpy's einsum.
    """
    if not have_numba():  # pragma: no cover - depends on the environment
        return np.einsum("mru,m,mrv->uv", A, P, A), np.einsum("mru,m,mr->u", A, P, l)
    if A.shape[1] == 1 and A.shape[2] == 3:  # a shift from one residual per row: the sums in registers
        return compiled(_normal_equations_shift)(A, P, l)
    return compiled(_normal_equations_kernel)(A, P, l)


def _normal_equations_shift(A, P, l):  # pragma: no cover - compiled
    """:func:`_normal_equations_kernel` for r = 1, u = 3: the same products added in the same order, each sum
    kept in a variable of its own (the array's entries are stored and loaded again in every row)."""
    n00 = n01 = n02 = n10 = n11 = n12 = n20 = n21 = n22 = 0.0
    g0 = g1 = g2 = 0.0
    for i in range(A.shape[0]):
        a0, a1, a2 = A[i, 0, 0], A[i, 0, 1], A[i, 0, 2]
        p, y = P[i], l[i, 0]
        ap = a0 * p
        n00 += ap * a0
        n01 += ap * a1
        n02 += ap * a2
        g0 += ap * y
        ap = a1 * p
        n10 += ap * a0
        n11 += ap * a1
        n12 += ap * a2
        g1 += ap * y
        ap = a2 * p
        n20 += ap * a0
        n21 += ap * a1
        n22 += ap * a2
        g2 += ap * y
    N = np.array([[n00, n01, n02], [n10, n11, n12], [n20, n21, n22]])
    return N, np.array([g0, g1, g2])


def _normal_equations_kernel(A, P, l):  # pragma: no cover - compiled
    m, r, u = A.shape
    N = np.zeros((u, u))
    n = np.zeros(u)
    for i in range(m):
        for k in range(r):
            for a in range(u):
                ap = A[i, k, a] * P[i]
                for b in range(u):
                    N[a, b] += ap * A[i, k, b]
                n[a] += ap * l[i, k]
    return N, n


def cell_labels(cells):
    """Dense labels 0..G-1 of the cells (m, d) or (m,) of integers, numbered in lexicographic order of the cells.

    The same labels as ``np.unique(cells, axis=0, return_inverse=True)[1]`` (raveled), without its sort of
    rows: the rows become one integer key each (the same order), labelled by one pass over the range of
    the keys when it is at most a few times m, else by the sort of the keys (1-D).

    Examples
    --------
    >>> import numpy as np
    >>> cells = np.array([[2, -1], [0, 5], [2, -1], [0, -3]])
    >>> cell_labels(cells).tolist(), np.unique(cells, axis=0, return_inverse=True)[1].ravel().tolist()
    ([2, 1, 2, 0], [2, 1, 2, 0])
    """
    c = np.asarray(cells).reshape(len(cells), -1).astype(np.int64, copy=False)
    if len(c) == 0:
        return np.zeros(0, dtype=np.intp)
    # per column (a reduction over axis 0 of a 2-D array is many times slower)
    lo = np.array([c[:, col].min() for col in range(c.shape[1])], dtype=np.int64)
    span = np.array([c[:, col].max() for col in range(c.shape[1])], dtype=np.int64) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:  # keys would overflow: the sort of rows
        return np.unique(c, axis=0, return_inverse=True)[1].ravel()
    key = np.zeros(len(c), dtype=np.int64)
    for col in range(c.shape[1]):  # row-major: lexicographic order of the rows is the order of the keys
        key = key * span[col] + (c[:, col] - lo[col])
    top = int(np.prod(span))
    if top > 4 * len(c) + 1024:  # sparse keys: sort them
        return np.unique(key, return_inverse=True)[1].ravel()
    used = np.zeros(top, dtype=bool)
    used[key] = True
    rank = np.cumsum(used) - 1
    return rank[key]


def sum_by_cell(cell, values, n_cells):
    """Per cell the sum of the rows of ``values`` (m, ...) whose ``cell`` (m,) it is: (n_cells, ...).

    The same numbers as ``np.add.at(np.zeros(...), cell, values)`` (each cell's rows added in row order,
    from zero), by one ``np.bincount`` per trailing element instead of the slow unbuffered ``add.at``.

    Examples
    --------
    >>> import numpy as np
    >>> sum_by_cell(np.array([1, 0, 1]), np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]), 3).tolist()
    [[3.0, 4.0], [6.0, 8.0], [0.0, 0.0]]
    """
    values = np.asarray(values, dtype=np.float64)
    flat = values.reshape(len(values), -1)
    out = np.empty((n_cells, flat.shape[1]))
    for c in range(flat.shape[1]):
        out[:, c] = np.bincount(cell, weights=flat[:, c], minlength=n_cells)
    return out.reshape((n_cells,) + values.shape[1:])


def cell_sums(B, P, v, cell):
    """Each cell's normal matrix N_c (nc, k, k) and score sum g_c (nc, k) of a group's own fit.

    B (m, r, k) are the group's design rows in its eigen-directions, P (m,) their weights, v (m, r) the
    residuals about the group's own estimate, ``cell`` (m,) the cell index of each row.
    """
    nc = int(cell.max()) + 1
    if B.shape[1] == 1 and have_numba():  # one pass, no (m, k, k) products (the same sums: see _cell_sums_kernel)
        return compiled(_cell_sums_kernel)(cell, nc, B, P, v)
    Nc = sum_by_cell(cell, np.einsum("mri,m,mrj->mij", B, P, B), nc)
    return Nc, sum_by_cell(cell, np.einsum("mri,m,mr->mi", B, P, v), nc)


def _cell_sums_kernel(cell, nc, B, P, v):  # pragma: no cover - compiled
    """:func:`cell_sums` for one residual per row (r = 1): each row's products (b_i p) b_j and (b_i p) v, as
    einsum forms them, added to its cell's sums in row order from zero, as np.bincount adds them."""
    m, _, k = B.shape
    Nc = np.zeros((nc, k, k))
    g = np.zeros((nc, k))
    for i in range(m):
        c = cell[i]
        for a in range(k):
            bp = B[i, 0, a] * P[i]
            for b in range(k):
                Nc[c, a, b] += bp * B[i, 0, b]
            g[c, a] += bp * v[i, 0]
    return Nc, g


def cell_jackknife(Nc, g, cell, lam):
    """Delete-one-cell jackknife covariance of a group's estimate, and its degrees of freedom.

    ``Nc``, ``g``: the cells' normal matrices and score sums (:func:`cell_sums`) of the group's fit in
    its eigen-directions (normal matrix ``diag(lam)``); ``cell``: each row's cell. Leaving cell c out moves the estimate by
    (Lambda - N_c)^-1 g_c (g_c: the cell's score sum), exactly for least squares; the spread of these
    moves is the cluster-robust covariance (eq. 5.13) without its downward bias when the cells are
    few (each cell's own leverage is taken out). Degrees of freedom: the effective number of cells
    (from the cells' sizes: (sum n_c)^2 / sum n_c^2) minus one. None, None when there are fewer
    than 2 k + 1 effective cells or one cell carries a direction nearly alone.
    """
    k, nc = len(lam), len(g)
    size = np.bincount(cell).astype(float)
    cells_eff = float(size.sum() ** 2 / (size**2).sum())  # n_c for cells of equal size, fewer otherwise
    if cells_eff < 2 * k + 1:
        return None, None
    scaled = Nc / np.sqrt(np.outer(lam, lam))
    if np.linalg.eigvalsh(scaled)[:, -1].max() > 0.9:  # leaving that cell out loses a direction
        return None, None
    d = np.linalg.solve(np.diag(lam)[None] - Nc, g[:, :, None])[:, :, 0]
    return np.einsum("ci,cj->ij", d, d) * (nc - 1) / nc, cells_eff - 1


def design_effect(fits):
    """How much the groups' cell-robust covariances exceed their formal ones (at least 1), and its dof.

    Pooled over the groups, each about its own estimate (so that a disagreement between the groups
    does not count as correlation): sum_g tr(Lambda_g^-1 sum_c g_c g_c^T) over its expectation for
    uncorrelated residuals, sum_g sigma0_g^2 (r_g - sum_c tr((Lambda_g^-1 N_c)^2)) (g_c, N_c: a cell's
    score sum and normal matrix; eq. 5.13). It widens the formal covariance of a group with too few cells
    of its own by the correlation of neighbouring residuals; dof: the cells minus one per group.
    """
    num = den = nu = 0.0
    for _, _, _, P, v, _, lam, _, _, Nc, g in fits:
        nc, k = len(g), len(lam)
        if nc < 2:
            continue
        s02 = float(np.einsum("mr,m,mr->", v, P, v)) / max(v.size - k, 1)
        num += float(np.sum(g**2 / lam))
        den += s02 * (k - float(np.einsum("cij,cji->", Nc / lam, Nc / lam)))
        nu += nc - 1
    if den <= 0 or nu < 1:
        return 1.0, np.inf
    return max(1.0, num / den), nu


def welch_james(H, Vs, Ws, nus, dof):
    """Scale c and denominator dof nu of T / c ~ F(dof, nu): T with estimated group covariances.

    Johansen's (1980) approximation for a weighted least-squares fit whose weights are inverse
    covariances estimated with ``nus`` degrees of freedom (the multivariate form of Welch's test):
    Q_g = I - V_g^T H^-1 V_g W_g, a = sum_g (tr Q_g^2 + (tr Q_g)^2) / (2 nu_g),
    c = dof + 2 a - 6 a / (dof + 2), nu = dof (dof + 2) / (3 a). With known covariances (nu infinite)
    c = dof and nu = inf: the chi-square test.
    """
    if dof <= 0:
        return 1.0, np.inf
    Hi = np.linalg.pinv(H)
    a = 0.0
    for V, W, nu in zip(Vs, Ws, nus):
        Q = np.eye(len(W)) - V.T @ Hi @ V @ W
        a += 0.5 * (np.trace(Q @ Q) + np.trace(Q) ** 2) / nu
    if a <= 0:
        return float(dof), np.inf
    return dof + 2 * a - 6 * a / (dof + 2), dof * (dof + 2) / (3 * a)


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
    cell = cell_labels(np.asarray(cells).reshape(len(A), -1))
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



def family_level(tests, alpha):
    """The groupings' tests at level ``alpha`` together: each at alpha / k (Bonferroni over k groupings).

    ICP tests up to three groupings of one set of correspondences and reports a disagreement when any
    rejects: each at ``alpha`` would give about k times ``alpha`` false alarms. A test that no longer
    rejects at its share of the level loses its ``between``.
    """
    k = len(tests)
    out = []
    for t in tests:
        level = alpha / k
        between = t.between if t.between is not None and t.p_value < level else np.zeros_like(t.between)
        out.append(replace(t, alpha=level, family=k, between=between))
    return out
