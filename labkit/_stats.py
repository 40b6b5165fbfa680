"""Statistics of a least-squares adjustment: global test, w-test, confidence ellipsoid.

Generic helpers shared by the adjustments (notebook 01, section "Statistics").
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import stats

from ._checks import probability
from ._report import ReportMixin, fmt

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
    """Two-sided chi-square test of ``omega = v^T Sigma_ll^-1 v`` with ``dof`` degrees of freedom."""
    alpha = probability(alpha, "alpha")
    if dof <= 0:
        return GlobalTest(np.nan, int(dof), np.nan, np.nan, alpha, None, np.nan)
    T = omega / sigma0_apriori**2
    lower, upper = _chi2_bounds(int(dof), alpha)
    return GlobalTest(float(T), int(dof), float(lower), float(upper), alpha, bool(lower <= T <= upper), float(T / dof))


@lru_cache(maxsize=256)
def _chi2_bounds(dof: int, alpha: float) -> tuple:
    lower, upper = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], dof)
    return float(lower), float(upper)


@lru_cache(maxsize=64)
def _norm_quantile(p: float) -> float:
    return float(stats.norm.ppf(p))


def w_critical(alpha_w: float) -> float:
    """Two-sided critical value of Baarda's w-test (normal quantile), e.g. 3.29 for 0.001."""
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
    q = 3 * stats.f.ppf(level, 3, dof) if dof else stats.chi2.ppf(level, 3)
    lam, vecs = np.linalg.eigh(C)
    order = np.argsort(lam)[::-1]
    semi = np.sqrt(np.clip(lam[order], 0.0, None) * q)
    return ConfidenceEllipsoid(np.asarray(center, dtype=np.float64).copy(), C, semi, vecs[:, order], level, float(q))
