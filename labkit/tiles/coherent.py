"""Coherent areas of a shift field: which tiles move together (notebook 08, eqs. 2-7).

Two kinds of chi-square tests decide it, all in one family:

- neighbours: do two adjacent tiles shift alike within their uncertainty? (eqs. 2, 3)
- areas: does each tile shift as the common (weighted) shift of its area? (eqs. 5, 6)

Pairwise agreement alone is not transitive: a slow drift of a small step per
tile passes every neighbour test, while its two ends differ by far more than
their uncertainty. So tiles linked by agreeing neighbours are only the first
guess of an area; an area in which some tile disagrees with the area's common
shift is split and grown again from its most similar neighbours, merging two
parts only while every tile of the union agrees with the union's common shift.

A survey of n tiles runs about 3n tests. Without correction a stable survey of
hundreds of tiles shows dozens of "disagreeing" borders at alpha = 0.05; the
p-values are therefore adjusted for the whole family (eq. 7: Holm or
Benjamini-Hochberg, :func:`labkit.core.stats.adjusted_p_values`).

Functions here work on arrays; :func:`labkit.tiles.neighbour_test` feeds them a ShiftField.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc, chdtri  # scipy.stats.chi2.sf / isf without importing scipy.stats
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..core.report import ReportMixin
from ..core.stats import CORRECTIONS  # noqa: F401  (re-exported)
from ..core.stats import adjusted_p_values, cholesky_factors, quadratic_form


@dataclass(frozen=True, eq=False, repr=False)
class NeighbourTest(ReportMixin):
    """Agreement of neighbouring tiles (eqs. 2, 3) and coherent areas (eqs. 5-7).

    Attributes
    ----------
    pairs : ndarray (k, 2)
        Indices into the field's tiles of the neighbour pairs.
    difference : ndarray (k, 3)
        t_i - t_j of each pair (m).
    chi2, dof, p_value : ndarray (k,)
        Test statistic T (eq. 3), its degrees of freedom (axes both tiles determine) and p-value;
        NaN (dof 0) where the pair has no common determined axis (no test, counted as not agreeing).
    p_adjusted : ndarray (k,)
        The p-values adjusted for the whole family of tests (eq. 7).
    agree : ndarray (k,) of bool
        ``p_adjusted > alpha``: the pair shifts alike.
    areas : ndarray (n,) of int
        Coherent area of each tile, 0 .. n_areas - 1 (-1 for tiles without a shift).
    alpha, extra_std, correction
        The test level (of the family with ``'holm'``), the extra std per tile (m) and the correction.
    tile_chi2, tile_dof, tile_p_value : ndarray (n,)
        Each tile against its final area's common shift (eq. 6); NaN for a tile alone in its area.
    area_shift, area_covariance : ndarray (n_areas, 3), (n_areas, 3, 3)
        Common (weighted) shift of each area and its covariance (eq. 5); NaN on an axis no tile
        of the area determines.
    n_pair_areas : int
        How many areas the agreeing neighbour pairs alone would give (before splitting).
    n_tests : int
        Size of the family: pair tests plus tile tests.

    Examples
    --------
    Four tiles in a square (1 mm std each); the right column moved 5 cm more in X:

    >>> import numpy as np
    >>> from labkit.tiles.coherent import neighbour_areas
    >>> t = np.array([[0.01, 0, 0], [0.06, 0, 0], [0.01, 0, 0], [0.06, 0, 0]])  # tiles (0,0) (0,1) (1,0) (1,1)
    >>> pairs = np.array([[0, 1], [0, 2], [1, 3], [2, 3]])
    >>> test = neighbour_areas(pairs, t, np.tile(np.eye(3) * 1e-6, (4, 1, 1)), np.ones((4, 3), bool),
    ...                        np.ones(4, bool), alpha=0.05)
    >>> test.agree.tolist(), test.areas.tolist(), test.area_shift[:, 0].round(3).tolist()
    ([False, True, True, False], [0, 1, 0, 1], [0.01, 0.06])
    """

    pairs: np.ndarray
    difference: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    p_value: np.ndarray
    agree: np.ndarray
    areas: np.ndarray
    alpha: float
    extra_std: float
    correction: str = "holm"
    p_adjusted: np.ndarray | None = None
    tile_chi2: np.ndarray | None = None
    tile_dof: np.ndarray | None = None
    tile_p_value: np.ndarray | None = None
    area_shift: np.ndarray | None = None
    area_covariance: np.ndarray | None = None
    n_pair_areas: int = 0
    n_tests: int = 0

    @property
    def n_areas(self) -> int:
        return int(self.areas.max() + 1) if (self.areas >= 0).any() else 0

    @property
    def neighbours_tested(self) -> np.ndarray:
        """(n,) int: neighbour pairs of each tile that were tested (a common determined axis)."""
        return self._per_tile(self.dof > 0)

    @property
    def neighbours_disagree(self) -> np.ndarray:
        """(n,) int: tested neighbour pairs of each tile that do not agree (eq. 3 after eq. 7)."""
        return self._per_tile((self.dof > 0) & ~self.agree)

    @property
    def disagreeing(self) -> np.ndarray:
        """(n,) bool: the tile disagrees with more than half of its tested neighbours (at least one).

        One border of a moved block disagrees with a minority of each tile's
        neighbours; a tile that moved alone (or whose registration went wrong)
        disagrees with most of them.
        """
        bad = self.neighbours_disagree
        return (bad >= 1) & (2 * bad > self.neighbours_tested)

    def _per_tile(self, mask) -> np.ndarray:
        return np.bincount(self.pairs[mask].ravel(), minlength=len(self.areas)).astype(int)

    @property
    def area_std(self) -> np.ndarray:
        """(n_areas, 3) standard deviations of the areas' common shifts (m)."""
        return np.sqrt(np.clip(np.einsum("kii->ki", self.area_covariance), 0, None))

    def _report(self):
        k = len(self.pairs)
        how = {"holm": "Holm (family-wise)", "fdr": "Benjamini-Hochberg (false discovery rate)",
               "none": "none (each test at alpha)"}[self.correction]
        rows = [("neighbour pairs tested", str(k)),
                ("agree within uncertainty", f"{int(self.agree.sum())} of {k}"),
                ("coherent areas", f"{self.n_areas} (agreeing neighbours alone: {self.n_pair_areas})"),
                ("test", f"chi-square, alpha = {self.alpha:g}, extra std per tile {self.extra_std:.4f} m"),
                ("correction", f"{how} over {self.n_tests} tests")]
        flagged = int(self.disagreeing.sum())
        if flagged:
            rows.append(("tiles disagreeing with most neighbours", f"{flagged} (flagged in the CSV)"))
        areas = []
        for a in range(min(self.n_areas, 12)):
            n = int((self.areas == a).sum())
            shift = ", ".join("  undet." if not np.isfinite(v) else f"{v:+.4f}" for v in self.area_shift[a])
            std = ", ".join("-" if not np.isfinite(v) else f"{1000 * v:.1f}" for v in self.area_std[a])
            areas.append((f"area {a} ({n} tile{'s' if n > 1 else ''})", f"[{shift}] m  std [{std}] mm"))
        if self.n_areas > 12:
            areas.append(("...", f"{self.n_areas - 12} more areas"))
        return "Neighbouring-tile agreement", [("", rows), ("common shift per area (eq. 5)", areas)]


def neighbour_areas(pairs, t, C, determined, ok, *, alpha: float, extra_std: float = 0.0,
                    correction: str = "holm") -> NeighbourTest:
    """The neighbour test and the coherent areas on arrays (checked by the caller).

    Parameters
    ----------
    pairs : (k, 2) int
        Neighbour pairs among the registered tiles.
    t, C, determined, ok : (n, 3), (n, 3, 3), (n, 3) bool, (n,) bool
        Shift, covariance and determined axes of every tile; ``ok`` marks tiles with a shift.
    alpha, extra_std, correction
        See :func:`labkit.tiles.neighbour_test`.

    Notes
    -----
    The family of tests is fixed before any decision: every pair test and every
    tile against the common shift of its connected part of the field (what the
    area would be if all neighbours agreed). When all tiles shift alike, the
    chance that the family rejects anything - a disagreeing border or a split
    area - is at most alpha with ``'holm'`` (and with ``'fdr'`` for tests that
    are positively dependent, as these are). Pairs rejected there stay rejected;
    the areas then follow from the agreeing pairs, and while some tile of an
    area is rejected (its p-value adjusted in the same family) the area is
    grown again from its tiles (:func:`_regrow`).

    References
    ----------
    .. [1] Notebook 08, sections 4.1-4.2, eqs. 2-7.
    .. [2] S. Holm (1979): A simple sequentially rejective multiple test procedure. Scandinavian
       Journal of Statistics 6(2), 65-70.
    .. [3] Y. Benjamini, Y. Hochberg (1995): Controlling the false discovery rate: a practical and
       powerful approach to multiple testing. Journal of the Royal Statistical Society B 57(1),
       289-300.
    """
    n, k = len(t), len(pairs)
    Ce = C + extra_std**2 * np.eye(3)
    # Neighbour pairs: d = t_i - t_j, C_d = C_i + C_j + 2 s^2 I on the axes both determine (eqs. 2, 3)
    i, j = pairs[:, 0], pairs[:, 1]
    d = t[i] - t[j] if k else np.zeros((0, 3))
    axes = determined[i] & determined[j]
    chi2, p_pair = _masked_chi2(d, Ce[i] + Ce[j], axes)
    dof = axes.sum(axis=1)
    # The family: the pairs, and every tile against its connected part of the field
    W, Wt = _weights(t, Ce, determined, ok)
    tested = np.isfinite(p_pair)
    whole = _components(n, pairs[tested], ok)
    p_tile = _tile_tests(whole, t, Ce, determined, W, Wt)[2]
    p_adj = adjusted_p_values(np.r_[p_pair, p_tile], correction)[:k]
    agree = np.isfinite(p_adj) & (p_adj > alpha)
    # Areas: first those of the agreeing pairs, then split while a tile disagrees with its area (eqs. 5-7)
    areas = _components(n, pairs[agree], ok)
    n_pair_areas = _count(areas)
    order = np.argsort(-np.nan_to_num(p_pair[agree], nan=-1.0), kind="stable")  # most alike first
    edges = pairs[agree][order]
    for _ in range(n):  # every round adds at least one area
        T_tile, dof_tile, p_tile = _tile_tests(areas, t, Ce, determined, W, Wt)
        rejected = adjusted_p_values(np.r_[p_pair, p_tile], correction)[k:] <= alpha
        if not rejected.any():
            break
        p_cut = float(p_tile[rejected].max())
        for label in np.unique(areas[rejected]):
            members = np.flatnonzero(areas == label)
            inside = np.isin(edges, members).all(axis=1)
            parts = _regrow(members, edges[inside], p_cut, t, Ce, determined, W, Wt)
            areas[members] = np.where(parts == 0, label, areas.max() + parts)
    # Greedy growth can stop early: join neighbouring areas again where the whole family still rejects no tile
    areas, (T_tile, dof_tile, p_tile) = _merge_back(areas, edges, p_pair, correction, alpha, t, Ce, determined, W, Wt)
    areas = _renumber(areas, ok)
    shift, cov = _area_shifts(areas, W, Wt)
    return NeighbourTest(pairs, d, chi2, dof, p_pair, agree, areas, float(alpha), float(extra_std),
                         correction, p_adj, T_tile, dof_tile, p_tile, shift, cov, n_pair_areas,
                         int(np.isfinite(p_pair).sum() + np.isfinite(p_tile).sum()))


# --------------------------------------------------------------------------- common shift of an area
def _weights(t, Ce, determined, ok):
    """W_i = E (E^T C_i E)^-1 E^T on the determined axes E of tile i (0 elsewhere), and W_i t_i."""
    n = len(t)
    W = np.zeros((n, 3, 3))
    for mask in _masks(determined, ok):
        rows = np.flatnonzero(ok & (determined == mask).all(axis=1))
        ax = np.flatnonzero(mask)
        sub = Ce[rows][:, ax][:, :, ax]
        L, fine = cholesky_factors(np.where(np.isfinite(sub).all(axis=(1, 2))[:, None, None], sub, 0.0))
        rows, L = rows[fine], L[fine]  # a tile without a positive definite covariance gets no weight
        Linv = np.linalg.solve(L, np.broadcast_to(np.eye(len(ax)), L.shape))
        W[np.ix_(rows, ax, ax)] = np.einsum("nki,nkj->nij", Linv, Linv)  # C^-1 = L^-T L^-1
    Wt = np.einsum("nij,nj->ni", W, np.where(determined & ok[:, None], t, 0.0))
    return W, Wt


def _common(N: np.ndarray, b: np.ndarray):
    """t_bar = N^-1 b and C_bar = N^-1 on the axes N determines (eq. 5); NaN on the others."""
    ax = np.flatnonzero(np.diag(N) > 0)
    shift, cov = np.full(3, np.nan), np.full((3, 3), np.nan)
    if len(ax):
        sub = N[np.ix_(ax, ax)]
        shift[ax] = np.linalg.solve(sub, b[ax])
        cov[np.ix_(ax, ax)] = np.linalg.solve(sub, np.eye(len(ax)))
    return shift, cov


def _test_members(members, t, Ce, determined, W, Wt, p_values=True):
    """Each member against the members' common shift: T_i = d^T (C_i - C_bar)^-1 d, d = t_i - t_bar (eq. 6).

    An axis is tested where the tile and at least one other member determine it
    (a tile alone on an axis sets the common value there: nothing to test).
    """
    shift, cov = _common(W[members].sum(axis=0), Wt[members].sum(axis=0))
    axes = determined[members] & (determined[members].sum(axis=0) >= 2)
    d = t[members] - shift
    if not p_values:
        return _masked_T(d, Ce[members] - cov, axes), axes.sum(axis=1)
    T, p = _masked_chi2(d, Ce[members] - cov, axes)
    return T, axes.sum(axis=1), p


def _tile_tests(areas, t, Ce, determined, W, Wt):
    """T, dof, p of every tile against its area's common shift; NaN for tiles alone or without a shift."""
    n = len(t)
    T, dof, p = np.full(n, np.nan), np.zeros(n, int), np.full(n, np.nan)
    labels, sizes = np.unique(areas[areas >= 0], return_counts=True)
    for label in labels[sizes > 1]:
        members = np.flatnonzero(areas == label)
        T[members], dof[members], p[members] = _test_members(members, t, Ce, determined, W, Wt)
    return T, dof, p


def _area_shifts(areas, W, Wt):
    count = _count(areas)
    shift, cov = np.full((count, 3), np.nan), np.full((count, 3, 3), np.nan)
    for a in range(count):
        members = areas == a
        shift[a], cov[a] = _common(W[members].sum(axis=0), Wt[members].sum(axis=0))
    return shift, cov


# --------------------------------------------------------------------------- growing areas
def _regrow(members, edges, p_cut, t, Ce, determined, W, Wt) -> np.ndarray:
    """Split an area: grow parts from single tiles along its agreeing pairs, most alike first.

    Two parts merge only when no tile of the union has a p-value at or below
    ``p_cut`` against the union's common shift (eq. 6), so a chain of small
    steps stops growing where its tiles no longer fit one shift. Returns a part
    label 0, 1, ... for each member.
    """
    parent = {int(m): int(m) for m in members}

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    part = {int(m): [int(m)] for m in members}
    limit = np.r_[np.inf, chdtri([1, 2, 3], p_cut)]  # p > p_cut  <=>  T < limit[dof]
    for a, b in edges:
        ra, rb = root(int(a)), root(int(b))
        if ra == rb:
            continue
        union = np.array(part[ra] + part[rb])
        T, dof = _test_members(union, t, Ce, determined, W, Wt, p_values=False)
        if not np.any(T >= limit[dof]):
            parent[rb] = ra
            part[ra] = part[ra] + part.pop(rb)
    roots = np.array([root(int(m)) for m in members])
    return np.unique(roots, return_inverse=True)[1]


def _merge_back(areas, edges, p_pair, correction, alpha, t, Ce, determined, W, Wt):
    """Join two areas across an agreeing pair (most alike first) when no tile of the family is then rejected."""
    k = len(p_pair)
    T, dof, p = _tile_tests(areas, t, Ce, determined, W, Wt)
    for a, b in edges:
        la, lb = areas[a], areas[b]
        if la == lb:
            continue
        union = np.flatnonzero((areas == la) | (areas == lb))
        T_u, dof_u, p_u = _test_members(union, t, Ce, determined, W, Wt)
        p_new = p.copy()
        p_new[union] = p_u
        if not (adjusted_p_values(np.r_[p_pair, p_new], correction)[k:] <= alpha).any():
            areas = np.where(areas == lb, la, areas)
            T, dof, p = T.copy(), dof.copy(), p_new
            T[union], dof[union] = T_u, dof_u
    return areas, (T, dof, p)


def _components(n: int, edges: np.ndarray, ok: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    labels = connected_components(graph, directed=False)[1]
    return np.where(ok, labels, -1)


def _renumber(labels: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Areas 0 .. k-1 over the registered tiles, in order of first appearance; -1 elsewhere."""
    uniq = {lab: i for i, lab in enumerate(dict.fromkeys(labels[ok].tolist()))}
    return np.array([uniq.get(lab, -1) if o else -1 for lab, o in zip(labels.tolist(), ok)], int)


def _count(labels: np.ndarray) -> int:
    return len(np.unique(labels[labels >= 0]))


# --------------------------------------------------------------------------- chi-square on chosen axes
def _masks(determined, ok):
    return [m for m in np.unique(determined[ok], axis=0) if m.any()] if ok.any() else []


def _masked_chi2(d, C, axes):
    """chi2_test of each row on its own axes; NaN where a row has no axis (no test)."""
    T = _masked_T(d, C, axes)
    with np.errstate(invalid="ignore"):
        return T, chdtrc(np.maximum(axes.sum(axis=1), 1), T)  # T >= 0 or NaN


def _masked_T(d, C, axes):
    """T = d^T C^-1 d of each row on its own axes (rows grouped by their axis mask); NaN where no axis."""
    T = np.full(len(d), np.nan)
    code = axes @ np.array([1, 2, 4])
    for c in np.unique(code[code > 0]):
        rows = np.flatnonzero(code == c)
        ax = np.flatnonzero(axes[rows[0]])
        T[rows] = quadratic_form(d[rows][:, ax], C[rows][:, ax][:, :, ax]) if len(ax) < 3 else \
            quadratic_form(d[rows], C[rows])
    return T
