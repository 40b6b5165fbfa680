"""The adjusted sphere of :func:`labkit.gauss_helmert_model` with its statistics (notebook 01).

A frozen result: parameters and their covariance (eqs. 23-24), residuals,
redundancy numbers, the main check, the global test and the w- (or tau-) test
of every point, with a plain-text ``summary()`` and an HTML view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.report import ReportMixin, fmt
from ..core.stats import ConfidenceEllipsoid, GlobalTest, confidence_ellipsoid


@dataclass(frozen=True, eq=False, repr=False)
class SphereFit(ReportMixin):
    """Adjusted sphere with the statistics of the Gauss-Helmert model.

    Attributes
    ----------
    x : ndarray (4,)
        Adjusted parameters [xc, yc, zc, r] in the caller's frame (m).
    Sigma_xx : ndarray (4, 4)
        Covariance of x: sigma0^2 N^-1 (eq. 24, corrected), with the a priori
        variance factor when there is no redundancy. Zero row/column for a
        fixed radius.
    sigma0 : float
        A posteriori standard deviation of unit weight (eq. 23); NaN without redundancy.
    v : ndarray (n, 3)
        Residuals (Verbesserungen) of the coordinates (m).
    converged : bool
        max|dx| fell below the tolerance.
    iterations : int
        Number of iterations run.
    main_check : float
        Main check (Hauptprobe): max_i |f_i(l + v, x)| of eq. 4 (m).
    main_check_passed : bool
        main_check below the tolerance.
    redundancy : int
        n - u (u = 4, or 3 with a fixed radius).
    dx_history : ndarray (k, 4)
        The parameter increments dx of every iteration.
    omega_history : ndarray (k,)
        v^T Sigma_ll^-1 v after every iteration.
    redundancy_numbers : ndarray (n,)
        Share r_i of each condition in the redundancy; sum = redundancy.
    w_test : ndarray (n,)
        Test statistic per point, positive for points outside the sphere, NaN
        where r_i = 0. With a given ``sigma`` (``sigma_known``): Baarda's w
        (N(0, 1) under H0, a priori sigma0). Without it: Pope's tau, the same
        residual scaled with the estimated sigma0 (tau-distributed under H0).
    normal_residuals : ndarray (n,)
        Residual component along the surface normal, -b_i^T v_i (m); positive
        outside the sphere.
    global_test : GlobalTest
        Chi-square test of sigma0^2 against sigma0_apriori^2; not run
        (``passed=None``) when no a priori precision was given.
    w_critical : float
        Critical value of the point test (two-sided, level ``alpha_w``): the
        normal quantile for Baarda's w, the tau quantile for Pope's tau.
    alpha_w : float
        Significance level of each w-test.
    N : ndarray (u, u)
        Normal matrix of the last iteration (local frame; the values do not depend on it).
    fixed_radius : bool
        The radius was held at a nominal value.
    sigma0_apriori : float
        A priori standard deviation of unit weight.
    sigma_known : bool
        An a priori precision was given (``sigma`` or ``sigma0_apriori``):
        global test and w-test. False: unit weights of unknown scale, no
        global test, Pope's tau test on the estimated sigma0.
    reason : str
        Empty when everything is fine; otherwise why the result must not be trusted.

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.sphere.ghm import gauss_helmert_model
    >>> u = np.random.default_rng(0).normal(size=(200, 3))
    >>> u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> fit = gauss_helmert_model(np.array([1.0, 2.0, 0.5]) + 0.2 * u, sigma=0.001)
    >>> type(fit).__name__, fit.converged, fit.x.round(4).tolist()
    ('SphereFit', True, [1.0, 2.0, 0.5, 0.2])
    """

    x: np.ndarray
    Sigma_xx: np.ndarray
    sigma0: float
    v: np.ndarray
    converged: bool
    iterations: int
    main_check: float
    main_check_passed: bool
    redundancy: int
    dx_history: np.ndarray
    omega_history: np.ndarray
    redundancy_numbers: np.ndarray
    w_test: np.ndarray
    normal_residuals: np.ndarray
    global_test: GlobalTest
    w_critical: float
    alpha_w: float
    N: np.ndarray
    fixed_radius: bool
    sigma0_apriori: float
    reason: str = ""
    sigma_known: bool = True

    @property
    def center(self) -> np.ndarray:
        """Adjusted centre [xc, yc, zc] (m)."""
        return self.x[:3]

    @property
    def radius(self) -> float:
        """Adjusted (or fixed) radius (m)."""
        return float(self.x[3])

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of [xc, yc, zc, r] (m)."""
        return np.sqrt(np.diag(self.Sigma_xx))

    @property
    def ok(self) -> bool:
        """Converged, main check passed and no other complaint."""
        return self.converged and self.main_check_passed and not self.reason

    @property
    def n(self) -> int:
        return self.v.shape[0]

    @property
    def test_name(self) -> str:
        """'w' (Baarda, a priori sigma given) or 'tau' (Pope, estimated sigma0)."""
        return "w" if self.sigma_known else "tau"

    @property
    def standardized_residuals(self) -> np.ndarray:
        """Residuals scaled with the a posteriori sigma0 (Pope's tau), NaN without redundancy."""
        if not self.sigma_known:
            return self.w_test
        return self.w_test * self.sigma0_apriori / self.sigma0

    @property
    def flagged(self) -> np.ndarray:
        """Points whose |w| exceeds the critical value (candidate gross errors)."""
        return np.abs(self.w_test) > self.w_critical  # (NaN compares False: no copy without NaN needed)

    @property
    def largest_w(self) -> int:
        """Index of the point with the largest |w| (-1 when no w is defined)."""
        w = np.abs(self.w_test)
        return -1 if np.isnan(w).all() else int(np.nanargmax(w))

    def __repr__(self) -> str:
        state = "ok" if self.ok else f"NOT ok: {self.reason or 'main check failed'}"
        return (f"SphereFit(center={fmt(self.center, 5)}, radius={self.radius:.5f}, sigma0={self.sigma0:.4g}, "
                f"n={self.n}, iterations={self.iterations}, {state})")

    def confidence_ellipsoid(self, level: float = 0.95) -> ConfidenceEllipsoid:
        """Confidence ellipsoid of the centre at ``level`` (semi-axes and directions)."""
        return confidence_ellipsoid(self.center, self.Sigma_xx[:3, :3], level, self.redundancy)

    def _report(self):
        std = self.std * 1e3
        status = "converged" if self.converged else "NOT converged"
        ell = self.confidence_ellipsoid(0.95)
        j = self.largest_w
        w_row = "no redundancy" if j < 0 else (
            f"{self.w_test[j]:+.2f} at point {j} (critical {self.w_critical:.2f}): "
            + ("GROSS ERROR SUSPECTED" if self.flagged[j] else "no gross error"))
        if self.sigma_known:
            g = self.global_test
            global_row = (f"T = {g.statistic:.1f}, accepted [{g.lower:.1f}, {g.upper:.1f}]: "
                          + {True: "passed", False: "REJECTED", None: "not testable"}[g.passed])
            apriori = f"a priori {self.sigma0_apriori:g}"
        else:
            global_row = "not run: no a priori sigma given (sigma0 is estimated, not tested)"
            apriori = "no a priori value"
        sections = [
            ("Sphere", [
                ("centre", fmt(self.center, 5, "m")),
                ("std centre", fmt(std[:3], 3, "mm")),
                ("radius", fmt(self.radius, 5, "m") + ("  (held fixed)" if self.fixed_radius else "")),
                ("std radius", fmt(std[3], 3, "mm")),
            ]),
            ("Adjustment", [
                ("points", f"{self.n:d}"),
                ("redundancy", f"{self.redundancy:d}"),
                ("iterations", f"{self.iterations:d} ({status})"),
                ("main check", f"max|f(l+v, x)| = {self.main_check:.2e} m ({'passed' if self.main_check_passed else 'FAILED'})"),
                ("sigma0", f"{self.sigma0:.4g} ({apriori})"),
            ]),
            ("Tests", [
                ("global test", global_row),
                (f"largest {self.test_name}" + ("" if self.sigma_known else " (Pope)"), w_row),
                ("flagged points", f"{int(self.flagged.sum()):d} (false alarms expected by chance: "
                 f"{np.isfinite(self.w_test).sum() * self.alpha_w:.1f})"),
                ("95% ellipsoid", fmt(ell.semi_axes * 1e3, 3, "mm")),
            ]),
        ]
        if self.reason:
            sections.insert(0, ("WARNING", [("reason", self.reason)]))
        return "Sphere adjustment (Gauss-Helmert model)", sections
