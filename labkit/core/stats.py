"""Statistics of a least-squares adjustment: global test, w-test, confidence ellipsoid, chi-square tests.

Generic helpers shared by the adjustments (notebook 01, section "Statistics"),
the comparison of transformations (notebook 07, eq. 6) and the neighbour test
of a shift field (notebook 08, eqs. 3 and 5), with the correction of a family
of many tests (Holm; Benjamini-Hochberg).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from .checks import choice, probability
from .distributions import chi2_ppf, chi2_sf, f_ppf, norm_ppf
from .report import ReportMixin, fmt

#: sigma of a normal distribution per median absolute deviation: 1 / Phi^-1(3/4) (the robust scale 1.4826 MAD)
MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True, eq=False, repr=False)
class GlobalTest(ReportMixin):
    """Chi-square test of the a posteriori against the a priori variance factor.

    Under H0 (model and stochastic model right, no gross errors)
    ``statistic = Omega / sigma0_apriori^2 = dof * sigma0^2 / sigma0_apriori^2``
    follows a chi-square distribution with ``dof`` degrees of freedom.

    Attributes
    ----------
    statistic : float
        Omega / sigma0_apriori^2 (NaN without redundancy).
    dof : int
        Redundancy n - u.
    lower, upper : float
        Two-sided critical values chi2(alpha/2), chi2(1 - alpha/2).
    alpha : float
        Significance level.
    passed : bool or None
        True when lower <= statistic <= upper; None when dof = 0 (no test possible).
    variance_ratio : float
        sigma0^2 / sigma0_apriori^2.
    """

    statistic: float
    dof: int
    lower: float
    upper: float
    alpha: float
    passed: bool | None
    variance_ratio: float

    def __repr__(self) -> str:
        return (f"GlobalTest(statistic={self.statistic:.2f}, dof={self.dof}, "
                f"accepted=[{self.lower:.2f}, {self.upper:.2f}], alpha={self.alpha:g}, passed={self.passed})")

    def _report(self):
        verdict = {True: "passed", False: "REJECTED", None: "not testable (no redundancy)"}[self.passed]
        return "Global test", [("", [
            ("statistic", f"{self.statistic:.2f}  (dof {self.dof})"),
            ("accepted range", f"[{self.lower:.2f}, {self.upper:.2f}] at alpha = {self.alpha:g}"),
            ("sigma0^2 / prior", fmt(self.variance_ratio, 4)),
            ("decision", verdict),
        ])]


def global_test(omega: float, dof: int, sigma0_apriori: float, alpha: float) -> GlobalTest:
    """Two-sided chi-square test of ``omega = v^T Sigma_ll^-1 v`` with ``dof`` degrees of freedom.

    References
    ----------
    .. [1] Notebook 01, section 9 (the global test of the sphere adjustment).
    .. [2] W. Niemeier (2008): Ausgleichungsrechnung. 2nd edition, de Gruyter, Berlin.
    .. [3] W. Baarda (1968): A testing procedure for use in geodetic networks. Netherlands Geodetic
       Commission, Publications on Geodesy, New Series 2(5), Delft.
    """
    alpha = probability(alpha, "alpha")
    if dof <= 0:
        return GlobalTest(np.nan, int(dof), np.nan, np.nan, alpha, None, np.nan)
    T = omega / sigma0_apriori**2
    lower, upper = _chi2_bounds(int(dof), alpha)
    return GlobalTest(float(T), int(dof), float(lower), float(upper), alpha, bool(lower <= T <= upper), float(T / dof))


@lru_cache(maxsize=256)
def _chi2_bounds(dof: int, alpha: float) -> tuple:
    lower, upper = chi2_ppf([alpha / 2, 1 - alpha / 2], dof)
    return float(lower), float(upper)


@lru_cache(maxsize=64)
def _norm_quantile(p: float) -> float:
    return float(norm_ppf(p))


def w_critical(alpha_w: float) -> float:
    """Two-sided critical value of Baarda's w-test (normal quantile), e.g. 3.29 for 0.001.

    References
    ----------
    .. [1] Notebook 01, section 9 (the w-test).
    .. [2] W. Baarda (1968): A testing procedure for use in geodetic networks. Netherlands Geodetic
       Commission, Publications on Geodesy, New Series 2(5), Delft.
    """
    return _norm_quantile(1 - probability(alpha_w, "alpha_w") / 2)


@dataclass(frozen=True, eq=False, repr=False)
class ConfidenceEllipsoid(ReportMixin):
    """Confidence ellipsoid of a 3D point from its covariance matrix.

    The ellipsoid ``(p - center)^T C^-1 (p - center) <= quantile`` holds the
    true point with probability ``level``.

    Attributes
    ----------
    center : ndarray (3,)
    covariance : ndarray (3, 3)
    semi_axes : ndarray (3,)
        Semi-axis lengths, largest first (m).
    axes : ndarray (3, 3)
        Unit directions of the semi-axes in the columns.
    level : float
        Confidence level.
    quantile : float
        chi2_3(level) with a known variance factor, 3 F(3, dof; level) with an estimated one.
    """

    center: np.ndarray
    covariance: np.ndarray
    semi_axes: np.ndarray
    axes: np.ndarray
    level: float
    quantile: float

    def __repr__(self) -> str:
        return (f"ConfidenceEllipsoid(level={self.level:g}, center={fmt(self.center, 5)}, "
                f"semi_axes={fmt(self.semi_axes * 1e3, 4)} mm)")

    def contains(self, point) -> bool:
        """True when ``point`` (3,) lies inside the ellipsoid."""
        d = np.asarray(point, dtype=np.float64) - self.center
        return bool(d @ np.linalg.solve(self.covariance, d) <= self.quantile)

    def _report(self):
        rows = [(f"semi-axis {i + 1}", f"{a * 1e3:.3f} mm along {fmt(ax, 3)}") for i, (a, ax) in
                enumerate(zip(self.semi_axes, self.axes.T))]
        return f"{self.level:.0%} confidence ellipsoid of the centre", [("", rows)]


def confidence_ellipsoid(center, covariance, level: float = 0.95, dof: int | None = None) -> ConfidenceEllipsoid:
    """Semi-axes and directions of the ``level`` confidence ellipsoid of a 3D point.

    Parameters
    ----------
    center : array_like (3,)
    covariance : array_like (3, 3)
        Covariance of the point (sigma0^2 N^-1 block).
    level : float
        Confidence level in (0, 1).
    dof : int, optional
        Redundancy of the adjustment when the covariance was scaled with the
        estimated sigma0 (uses 3 F(3, dof)); None or 0 for a known variance factor (chi2_3).
    """
    level = probability(level, "level")
    C = 0.5 * (np.asarray(covariance, dtype=np.float64) + np.asarray(covariance, dtype=np.float64).T)
    q = 3 * f_ppf(level, 3, dof) if dof else chi2_ppf(level, 3)
    lam, vecs = np.linalg.eigh(C)
    order = np.argsort(lam)[::-1]
    semi = np.sqrt(np.clip(lam[order], 0.0, None) * q)
    return ConfidenceEllipsoid(np.asarray(center, dtype=np.float64).copy(), C, semi, vecs[:, order], level, float(q))


# --------------------------------------------------------------------------- chi-square test of a difference
def chi2_test(e, C):
    """T = e^T C^-1 e and its chi-square p-value with ``len(e)`` degrees of freedom (notebook 07, eq. 6).

    ``e`` is one difference (k,) with covariance ``C`` (k, k), or a stack
    (..., k) with (..., k, k). T is solved through a Cholesky factor of C; where
    C (or e) is not finite or C is not positive definite, or k = 0, T and p are
    NaN (no test), never a number that looks like one.

    Returns
    -------
    (T, p) : floats for one difference, arrays of shape ``e.shape[:-1]`` for a stack.

    Examples
    --------
    >>> T, p = chi2_test([0.01, 0.0], [[1e-4, 0.0], [0.0, 1e-4]])
    >>> round(T, 6), round(p, 4)
    (1.0, 0.6065)
    """
    e = np.asarray(e, dtype=np.float64)
    k = e.shape[-1]
    T = quadratic_form(e, C)
    with np.errstate(invalid="ignore"):
        p = chi2_sf(T, max(k, 1))
    if e.ndim == 1:
        return float(T), float(p)
    return T, p


def quadratic_form(e, C):
    """T = e^T C^-1 e through a Cholesky factor of C (one or a stack); NaN where C is not positive definite."""
    e, C = np.asarray(e, dtype=np.float64), np.asarray(C, dtype=np.float64)
    k = e.shape[-1]
    if k == 0:  # no axis to test
        return np.nan if e.ndim == 1 else np.full(e.shape[:-1], np.nan)
    E, Cs = e.reshape(-1, k), C.reshape(-1, k, k)
    T = np.full(len(E), np.nan)
    if len(E):
        idx = np.flatnonzero(np.isfinite(E).all(axis=1) & np.isfinite(Cs).all(axis=(1, 2)))
        L, factored = cholesky_factors(Cs[idx])
        if factored.any():
            # z = L^-1 e, T = z^T z
            z = np.linalg.solve(L[factored], E[idx[factored], :, None])[..., 0]
            T[idx[factored]] = np.einsum("ij,ij->i", z, z)
    return float(T[0]) if e.ndim == 1 else T.reshape(e.shape[:-1])


def cholesky_factors(C: np.ndarray):
    """Lower Cholesky factors of a stack of matrices and a mask of those that have one (positive definite).

    Examples
    --------
    >>> L, ok = cholesky_factors(np.array([np.eye(2) * 4.0, [[1.0, 2.0], [2.0, 1.0]]]))
    >>> ok.tolist(), L[0].tolist()
    ([True, False], [[2.0, 0.0], [0.0, 2.0]])
    """
    try:
        return np.linalg.cholesky(C), np.ones(len(C), bool)
    except np.linalg.LinAlgError:  # at least one is not positive definite: factor one by one
        L, ok = np.zeros_like(C), np.zeros(len(C), bool)
        for n, c in enumerate(C):
            try:
                L[n], ok[n] = np.linalg.cholesky(c), True
            except np.linalg.LinAlgError:
                pass
        return L, ok


# --------------------------------------------------------------------------- a family of many tests
#: Corrections for a family of tests: family-wise error (Holm), false discovery rate (Benjamini-Hochberg), none.
CORRECTIONS = ("holm", "fdr", "none")


def adjusted_p_values(p, correction: str = "holm") -> np.ndarray:
    """p-values of a family of tests adjusted for their number; reject where the adjusted value <= alpha.

    ``'holm'`` (Holm 1979) keeps the family-wise error rate, the probability of
    rejecting any true hypothesis, at alpha under any dependence between the
    tests: sorted p_(1) <= ... <= p_(m), p~_(i) = max_{j <= i} min(1, (m - j + 1) p_(j)).
    ``'fdr'`` (Benjamini and Hochberg 1995) keeps the expected share of false
    rejections among the rejections at alpha (for independent or positively
    dependent tests): p~_(i) = min_{j >= i} min(1, m p_(j) / j). When every
    hypothesis is true, both keep the chance of any rejection at alpha.
    ``'none'`` returns the p-values unchanged. NaN entries are not tests: they
    stay NaN and do not count in m.

    References
    ----------
    .. [1] Notebook 08, section 4.1, eq. 7.
    .. [2] S. Holm (1979): A simple sequentially rejective multiple test procedure. Scandinavian
       Journal of Statistics 6(2), 65-70.
    .. [3] Y. Benjamini, Y. Hochberg (1995): Controlling the false discovery rate: a practical and
       powerful approach to multiple testing. Journal of the Royal Statistical Society B 57(1),
       289-300.

    Examples
    --------
    >>> adjusted_p_values([0.01, 0.04, 0.03, np.nan], "holm").round(3).tolist()
    [0.03, 0.06, 0.06, nan]
    >>> adjusted_p_values([0.01, 0.04, 0.03], "fdr").round(3).tolist()
    [0.03, 0.04, 0.04]
    """
    correction = choice(correction, CORRECTIONS, "correction")
    p = np.asarray(p, dtype=np.float64)
    out = p.copy()
    tested = np.flatnonzero(np.isfinite(p))
    m = len(tested)
    if correction == "none" or m == 0:
        return out
    order = tested[np.argsort(p[tested], kind="stable")]
    ps = p[order]
    rank = np.arange(1, m + 1)
    if correction == "holm":
        adj = np.maximum.accumulate(np.minimum(1.0, (m - rank + 1) * ps))
    else:
        adj = np.minimum.accumulate(np.minimum(1.0, m * ps / rank)[::-1])[::-1]
    out[order] = adj
    return out
