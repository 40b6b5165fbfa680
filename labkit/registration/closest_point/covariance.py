"""The stated covariance of ICP besides sigma0^2 N^-1: the cluster-robust sandwich (eq. 5.13) and the
effect of held parameters' priors (eq. 5.15).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ...core.distributions import norm_cdf, t_ppf
from ...core.jit import compiled, have_numba
from .weights import deletion_limit, psi_prime
from ..consistency import cell_labels, sum_by_cell

#: The level at which a stated std is read: |error| <= 3 std (two-sided 99.73 %).
SIGMAS = 3.0


def few_clusters_factor(n_cells, sigmas=SIGMAS):
    """Factor on a cluster-robust std from ``n_cells`` cells: t_(G-1) quantile / normal quantile at ``sigmas``.

    A sandwich summed over G cells is a variance estimate with about G - 1 degrees of freedom; the
    estimate divided by it follows Student's t with G - 1 of them, not the normal distribution. Scaling
    the std by this factor keeps "+- 3 std" the 99.73 % interval: 1.04 for 74 cells (sparse ALS, 86 pairs),
    1.003 for 1000 cells. See A. C. Cameron, D. L. Miller (2015): A practitioner's guide to
    cluster-robust inference. Journal of Human Resources 50(2), 317-372, section VI.C.

    Examples
    --------
    >>> round(few_clusters_factor(74), 3), round(few_clusters_factor(1000), 3)
    (1.035, 1.003)
    """
    if n_cells < 3:
        return np.inf
    return float(t_ppf(norm_cdf(sigmas), n_cells - 1) / sigmas)


def effective_cells(info, Ji):
    """Effective number of cells behind each parameter's sandwich variance (Satterthwaite).

    The sandwich variance of parameter j is a sum over cells of squared scores, each with expected
    size a_cj = (J^-1 J_c J^-1)_jj under independent rows (J_c: the cell's information). A sum of
    independent a_c chi^2_1 terms behaves like a scaled chi^2 with (sum a_c)^2 / sum a_c^2 degrees
    of freedom: the number of cells when they inform j equally, about the number of informative
    cells otherwise. On sparse ALS a horizontal axis rests on the few cells with building walls and
    roof edges: the variance estimated from them scatters from sampling to sampling (its std by
    40 %, about 3 effective cells), and a stated std read with the normal quantile was up to 6.7
    std from the truth. See C. Carter, K. Schnepel, D. Steigerwald (2017): Asymptotic behavior of a
    t-test robust to cluster heterogeneity. Review of Economics and Statistics 99(4), 698-709.

    Parameters
    ----------
    info : ndarray (G, p, p)
        Information of each cell.
    Ji : ndarray (p, p)
        Inverse of the bread.

    Returns
    -------
    ndarray (p,)
        The effective number of cells per parameter, at most G.

    Examples
    --------
    >>> import numpy as np
    >>> equal = np.broadcast_to(np.eye(2), (10, 2, 2))
    >>> effective_cells(equal, np.eye(2) / 10).tolist()
    [10.0, 10.0]
    >>> one = np.zeros((10, 2, 2)); one[:, 0, 0] = 1; one[:3, 1, 1] = 1  # the second: 3 cells
    >>> effective_cells(one, np.diag([0.1, 1 / 3])).round(6).tolist()
    [10.0, 3.0]
    """
    a = np.einsum("ij,cjk,ki->ci", Ji, info, Ji)  # a_cj = (J^-1 J_c J^-1)_jj
    with np.errstate(invalid="ignore", divide="ignore"):
        g = a.sum(axis=0) ** 2 / (a**2).sum(axis=0)
    return np.where(np.isfinite(g), np.minimum(g, len(info)), len(info))


def block_covariance(A, l, w, u, centred, keep, factor, dx_s, free, xy, N_eps, opts, cell=None):
    """Cluster-robust sandwich J^-1 M J^-1 in the scaled parameters (eq. 5.13); inf where held.

    M = sum over cells c of g_c g_c^T with g_c = sum_(i in c) A_i^T p_i v_i (scores of the kept
    rows); J = -d(A^T P l)/dx: sum w A_i^T [psi'(u) e e^T + psi(u)/u (I - e e^T)] A_i over the kept
    rows minus psi(k) w A_i^T e e^T A_i times the density of |u| at the deletion limit k (the
    boundary moves with x, eq. 5.14); e = unit direction of the standardized residual. With few cells
    the std of each parameter is scaled by :func:`few_clusters_factor` of its effective number of
    cells (:func:`effective_cells`): t instead of the normal quantile.
    """
    p = A.shape[2]
    fixed = ~free
    cov = np.full((p, p), np.nan)
    cov[free, :] = cov[:, free] = np.inf
    P = w * factor
    v = np.einsum("mru,u->mr", A, dx_s) - l
    if cell is None:
        cell = cell_labels(block_cells(xy[keep], opts.block_size))
    one = A.shape[1] == 1 and have_numba()  # one residual per row: the cell sums in compiled passes
    kept, cols = np.flatnonzero(keep), np.flatnonzero(fixed)
    if one:  # the same sums (see _cell_scores)
        G = compiled(_cell_scores)(cell, int(cell.max()) + 1, A, P, v, kept, cols)
    else:
        g = np.einsum("mru,m,mr->mu", A, P, v)[keep][:, fixed]  # score of each kept correspondence
        G = sum_by_cell(cell, g, int(cell.max()) + 1)
    n_cells, m, k = len(G), len(kept), len(cols)
    if n_cells < 2 * k:
        return cov  # too few cells for a sandwich: NaN, the caller falls back to the formal one
    M = np.einsum("ci,cj->ij", G, G) * n_cells / (n_cells - 1)  # small-sample factor of the cluster sandwich
    dpsi = psi_prime(u, opts.robust)  # factor = psi(u) / u
    near = None
    if opts.reject_sigma is not None:  # rows crossing the deletion limit as x changes
        limit = deletion_limit(opts.reject_sigma, A.shape[1])
        h = 0.1 * limit
        near = np.abs(u - limit) < h
    if one:  # J and the boundary term in one compiled pass, without the (m, u, u) arrays (see _bread_sums)
        J, J_near = compiled(_bread_sums)(A, centred, w, keep, near if near is not None else keep, factor, dpsi)
    else:
        e = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-300)
        Ae = np.einsum("mru,mr->mu", A, e)  # A^T e per row
        AA = np.einsum("mru,mrv->muv", A, A)
        inner = factor[:, None, None] * AA + ((dpsi - factor)[:, None, None] * np.einsum("mu,mv->muv", Ae, Ae))
        J = np.einsum("m,muv->uv", (w * keep), inner)
        J_near = None if near is None else np.einsum("m,mu,mv->uv", w * near, Ae, Ae)
    if near is not None:
        psi_limit = limit * (np.median(factor[keep & near]) if (keep & near).any() else 1.0)
        J -= psi_limit / (2 * h) * J_near
    J = (J - N_eps)[np.ix_(fixed, fixed)]  # the bread: what survives re-matching (eq. 5.12b)
    try:
        c = cho_factor(0.5 * (J + J.T))
    except np.linalg.LinAlgError:
        return cov
    Ji = cho_solve(c, np.eye(len(J)))
    if one:
        info = compiled(_cell_information)(cell, n_cells, A, P, kept, cols)
    else:
        info = sum_by_cell(cell, (w * factor)[keep, None, None] * AA[keep][:, fixed][:, :, fixed], n_cells)
    dof = effective_cells(info, Ji) * (n_cells - 1) / n_cells  # n_cells - 1 when all cells inform alike
    t_factor = t_ppf(norm_cdf(SIGMAS), np.maximum(dof, 1.0)) / SIGMAS
    cov[np.ix_(fixed, fixed)] = Ji @ M @ Ji * (m / max(m - k, 1)) * np.outer(t_factor, t_factor)
    return cov


def _bread_sums(A, centred, w, keep, near, factor, dpsi):  # pragma: no cover - compiled
    """For one residual per row: J = sum (w keep) [factor a a^T + (psi' - factor) (a e)(a e)^T] and the boundary
    term sum (w near) (a e)(a e)^T, e = c / |c| of the centred residual c: each product formed as numpy forms
    the arrays of :func:`block_covariance`, added in row order from zero (np.einsum's order)."""
    m, _, p = A.shape
    J = np.zeros((p, p))
    Jn = np.zeros((p, p))
    ae = np.empty(p)
    for i in range(m):
        c = centred[i, 0]
        e = c / max(np.sqrt(c * c), 1e-300)
        for a in range(p):
            ae[a] = A[i, 0, a] * e
        wk = w[i] * keep[i]
        wn = w[i] * near[i]
        f, d = factor[i], dpsi[i] - factor[i]
        for a in range(p):
            for b in range(p):
                J[a, b] += wk * (f * (A[i, 0, a] * A[i, 0, b]) + d * (ae[a] * ae[b]))
                Jn[a, b] += (wn * ae[a]) * ae[b]
    return J, Jn


def _cell_scores(cell, n_cells, A, P, v, rows, cols):  # pragma: no cover - compiled
    """Per cell the scores (a_u p) v of its rows ``rows`` (one residual each) in the columns ``cols``: the
    products as einsum forms them, added in row order from zero as np.bincount adds them (sum_by_cell)."""
    G = np.zeros((n_cells, len(cols)))
    for r in range(len(rows)):
        i, c = rows[r], cell[r]
        for a in range(len(cols)):
            G[c, a] += (A[i, 0, cols[a]] * P[i]) * v[i, 0]
    return G


def _cell_information(cell, n_cells, A, pw, rows, cols):  # pragma: no cover - compiled
    """Per cell the information pw (a_u a_v) of its rows ``rows`` (one residual each) in the columns ``cols``,
    added in row order from zero (the numbers of sum_by_cell on the products)."""
    k = len(cols)
    info = np.zeros((n_cells, k, k))
    for r in range(len(rows)):
        i, c = rows[r], cell[r]
        for a in range(k):
            for b in range(k):
                info[c, a, b] += pw[i] * (A[i, 0, cols[a]] * A[i, 0, cols[b]])
    return info


def block_cells(xy, block_size):
    """The square cell (m, 2) of side ``block_size`` of every point ``xy`` (m, 2): the clusters of eq. 5.13."""
    return np.floor(xy / block_size).astype(np.int64)


def held_rotation_covariance(N, deg, opts):
    """B Sigma_h B^T in the scaled parameters: what the held rotations' prior does to the others.

    Holding h at its prior value h0 makes the free parameters conditional on it: their
    solution moves by -B (h - h0) with B = N_ff^-1 N_fh (eq. 5.15), so a prior standard deviation
    sigma_h of the rotation adds B sigma_h^2 B^T to their covariance. The scaled rotation is L omega.
    A held translation does the same with a prior std of the matching distance (its true value may
    lie anywhere within reach): on sloped ground a held X moves Z by slope times X (eq. 5.15).
    """
    p = len(N)
    out = np.zeros((p, p))
    if deg.parameter_determined is None:
        return out
    free = deg.parameter_determined.copy()
    is_rot = np.array([n.startswith("r") for n in deg.names])
    held = ~free
    if not held.any() or not free.any():
        return out
    prior = np.where(is_rot, opts.held_rotation_std * opts.L, opts.held_shift_std)[held]
    B = np.linalg.lstsq(N[np.ix_(free, free)], N[np.ix_(free, held)], rcond=None)[0]
    out[np.ix_(free, free)] = (B * prior**2) @ B.T
    return out
