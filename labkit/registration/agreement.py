"""Agreement of a refinement with its start: ICP after maximum consensus (notebook 07, eq. 6).

Two routes through the same data, the consensus start and the ICP refinement, should agree
within their stated uncertainties. Where they do not, at least one of them carries an error that
its own covariance leaves out; on sparse ALS (about 1.4 m between points) it is the ICP: its local
surfaces span several metres, and a few building edges can pull it tens of millimetres away while
its covariance, from the residuals alone, states a few millimetres.
"""

from __future__ import annotations

import numpy as np

from ..core.stats import chi2_test


def disagreement_covariance(refined, start, cov_refined, cov_start):
    """The covariance a refinement must add to cover its disagreement with its start, and the test of it.

    ``d = refined - start`` (shifts at one point, m) is tested with ``C = cov_refined + cov_start``
    (eq. 6): ``T = d^T C^-1 d`` on the ``k`` components both state (finite variances). ``C`` ignores
    that both estimates come from the same data (their errors correlate positively), so it is an
    upper bound of the covariance of ``d`` and the test is on the safe side. The moment estimate
    of the error that neither covariance holds, along the disagreement, is ``(1 - k / T) d d^T``
    (``E[T] = k`` when both are right): nothing when ``T <= k``, nearly ``d d^T`` when the two lie
    far apart. Added to the refinement's covariance, a refinement that walked away from a right
    start is at most about one std from it, and one that agrees keeps its own precision.

    Parameters
    ----------
    refined, start : array_like (3,)
        The two shifts (m).
    cov_refined, cov_start : array_like (3, 3)
        Their covariances; ``inf`` or NaN on a component that estimate does not determine.

    Returns
    -------
    extra : ndarray (3, 3)
        To add to the refinement's covariance (zero on components not stated by both).
    T : float
        The test statistic (NaN when no component is stated by both).
    k : int
        Its degrees of freedom.

    References
    ----------
    .. [1] Notebook 07, section 4, eq. 6 (the chi-square test of a difference of two estimates).
    .. [2] J. A. Hausman (1978): Specification tests in econometrics. Econometrica 46(6), 1251-1271
       (testing an estimator against a consistent one from the same data).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.agreement import disagreement_covariance
    >>> cov = np.diag([1e-4, 1e-4, 1e-5])  # 10, 10, 3.2 mm
    >>> extra, T, k = disagreement_covariance([0.0, 0.06, 0.0], np.zeros(3), cov, cov)
    >>> round(T, 1), k, np.sqrt(np.diag(extra)).round(3).tolist()  # 60 mm at a combined 14 mm std
    (18.0, 3, [0.0, 0.055, 0.0])
    >>> bool(disagreement_covariance([0.0, 0.01, 0.0], np.zeros(3), cov, cov)[0].any())  # within: nothing
    False
    """
    d = np.asarray(refined, dtype=np.float64) - np.asarray(start, dtype=np.float64)
    C = np.asarray(cov_refined, dtype=np.float64) + np.asarray(cov_start, dtype=np.float64)
    both = np.isfinite(np.diag(C)) & np.isfinite(d)
    extra = np.zeros((3, 3))
    k = int(both.sum())
    if k == 0:
        return extra, float("nan"), 0
    T, _ = chi2_test(d[both], C[np.ix_(both, both)])
    if np.isfinite(T) and T > k:
        db = np.where(both, d, 0.0)
        extra = (1.0 - k / T) * np.outer(db, db)
    return extra, float(T), k
