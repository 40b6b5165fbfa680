"""The outcome of a RANSAC sphere detection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.report import ReportMixin, fmt
from .config import BAND_K


@dataclass(frozen=True, eq=False, repr=False)
class RansacResult(ReportMixin):
    """Outcome of :func:`ransac_sphere`.

    Attributes
    ----------
    fit : SphereFit or None
        Gauss-Helmert adjustment on the final inliers (None when not found).
    inliers : ndarray of bool (n,)
        Final inliers over the input points (all False when not found).
    found : bool
    iterations : int
        Valid samples drawn (degenerate samples do not count).
    n_required_history : ndarray (k, 2)
        [iteration, required N] after each new best hypothesis (eq. 27).
    outlier_ratio : float
        Estimated share of outliers, 1 - n_inliers / n (NaN when not found).
    seed : int
        Seed that reproduces the run: ``ransac_sphere(..., rng=result.seed)``.
    reason : str
        Why the search stopped and, when not found, why.
    n_invalid : int
        Degenerate (coplanar or duplicate) samples drawn and not counted.
    n_snooped : int
        Points removed by the final data snooping.
    sigma : float or None
        A priori standard deviation used for the w-test (given or estimated).
    sampling, scoring, minimal_solver : str
        The strategies used.
    threshold, p : float
        The inlier threshold t (m) and success probability.
    n_required : float
        The required N at the end of the search.
    n_working : int
        Size of the working set the (last) search drew and scored on.
    n_rejected : int
        Candidate spheres the verification rejected during the search (each
        would have been the best by its score): pieces of planes, corners,
        round furniture, rings.
    band : float
        Half-width of the final inlier band, k sigma_hat (m): set by the
        robust scale of the residuals, not by the threshold t.
    station : ndarray (3,) or None
        Scanner position used by the visibility checks (None: not used).

    Examples
    --------
    A search that finds nothing says why instead of returning a sphere (points on a plane):

    >>> import numpy as np
    >>> from labkit.ransac import ransac_sphere
    >>> plane = np.c_[np.random.default_rng(0).uniform(0, 1, (300, 2)), np.zeros(300)]
    >>> result = ransac_sphere(plane, threshold=0.003, rng=0, radius_range=(0.05, 0.1))
    >>> result.found, result.fit, int(result.inliers.sum())
    (False, None, 0)
    >>> result.reason
    'every one of the 2048 samples was degenerate (coplanar or repeated points)'
    """

    fit: object
    inliers: np.ndarray
    found: bool
    iterations: int
    n_required_history: np.ndarray
    outlier_ratio: float
    seed: int
    reason: str
    n_invalid: int = 0
    n_snooped: int = 0
    sigma: float | None = None
    sampling: str = "uniform"
    scoring: str = "ransac"
    minimal_solver: str = "closed_form"
    threshold: float = float("nan")
    p: float = float("nan")
    n_required: float = float("inf")
    n_working: int = 0
    n_rejected: int = 0
    band: float = float("nan")
    station: np.ndarray | None = None

    @property
    def center(self):
        return None if self.fit is None else self.fit.x[:3]

    @property
    def radius(self):
        return None if self.fit is None else float(self.fit.x[3])

    @property
    def covariance(self):
        """Covariance matrix (4, 4) of [xc, yc, zc, r] from the Gauss-Helmert refit (None when not found)."""
        return None if self.fit is None else self.fit.Sigma_xx

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def _report(self):
        rows = [("found", "yes" if self.found else "no"), ("reason", self.reason)]
        if self.found:
            std = np.sqrt(np.diag(self.fit.Sigma_xx))
            rows += [
                ("centre", fmt(self.fit.x[:3], 5, "m")),
                ("std centre", fmt(std[:3] * 1e3, 3, "mm")),
                ("radius", fmt(self.fit.x[3], 5, "m")),
                ("std radius", fmt(std[3] * 1e3, 3, "mm")),
                ("sigma0", fmt(self.fit.sigma0, 3)),
                ("inliers", f"{self.n_inliers} of {self.inliers.size}"),
                ("outlier ratio", fmt(self.outlier_ratio, 3)),
            ]
        search = [
            ("sampling / solver", f"{self.sampling} / {self.minimal_solver}"),
            ("scoring", self.scoring),
            ("threshold t (search)", fmt(self.threshold * 1e3, 2, "mm")),
            ("p", fmt(self.p, 4)),
            ("working set", f"{self.n_working} points"),
            ("valid samples", f"{self.iterations}"),
            ("required N (eq. 27)", f"{self.n_required:.0f}"),
            ("degenerate samples", f"{self.n_invalid}"),
            ("new bests", f"{len(self.n_required_history)}"),
            ("seed", f"{self.seed}"),
        ]
        checks = [
            ("final inlier band", fmt(self.band * 1e3, 2, "mm") + f" ({BAND_K:g} x robust sigma)"),
            ("candidates rejected", f"{self.n_rejected} (not a sphere cap: verification)"),
            ("station", "not given (no visibility checks)" if self.station is None else fmt(self.station, 3, "m")),
            ("removed by data snooping", f"{self.n_snooped}"),
        ]
        if self.sigma is not None:
            checks.append(("sigma a priori (w-test)", fmt(self.sigma * 1e3, 3, "mm")))
        if self.found:
            checks.append(("global test passed", str(getattr(self.fit.global_test, "passed", self.fit.global_test))))
        return "RANSAC sphere detection", [("", rows), ("Search", search), ("Checks", checks)]


def not_found(n, reason, **common) -> RansacResult:
    return RansacResult(
        fit=None, inliers=np.zeros(n, dtype=bool), found=False, outlier_ratio=float("nan"), reason=reason, **common
    )
