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


def disagreement_covariance(refined, start, cov_refined, cov_start, alpha: float = 0.0027):
    """How a refinement's covariance must grow to cover its disagreement with its start, and the test of it.

    ``d = refined - start`` (shifts at one point, m) is tested with ``C = cov_refined + cov_start``
    (eq. 6): ``T = d^T C^-1 d`` on the ``k`` components both state (finite variances). ``C`` ignores
    that both estimates come from the same data (their errors correlate positively), so it is an
    upper bound of the covariance of ``d`` and the test is on the safe side. Two terms:

    - ``scale = max(1, T / k)`` on the refinement's covariance: both covariances too small by a
      common factor (the scale factor of a weighted mean of measurements that disagree, Birge 1932;
      PDG). It costs little where the two agree and cannot tell apart.
    - ``extra = (1 - k / T) d d^T`` when the disagreement is significant (``p < alpha``, default the
      3 std level): the moment estimate of an error along ``d`` that neither covariance holds
      (``E[T] = k`` when both are right). A refinement that walked far from a right start, stating
      a std much smaller than the distance, is then about one std from it. Below the level it is
      left out, because a start much less precise than the refinement cannot tell which of the two
      is off, and ``d d^T`` would then be mostly the start's own noise.

    Parameters
    ----------
    refined, start : array_like (3,)
        The two shifts (m).
    cov_refined, cov_start : array_like (3, 3)
        Their covariances; ``inf`` or NaN on a component that estimate does not determine.
    alpha : float
        Level of the test above which ``d d^T`` is added.

    Returns
    -------
    scale : float
        Factor (>= 1) on the refinement's covariance.
    extra : ndarray (3, 3)
        To add after scaling (zero on components not stated by both, and below the level).
    T : float
        The test statistic (NaN when no component is stated by both).
    k : int
        Its degrees of freedom.

    References
    ----------
    .. [1] Notebook 07, section 4, eq. 6 (the chi-square test of a difference of two estimates).
    .. [2] R. T. Birge (1932): The calculation of errors by the method of least squares. Physical
       Review 40, 207-227 (the scale factor sqrt(chi^2 / dof) of inconsistent measurements).
    .. [3] J. A. Hausman (1978): Specification tests in econometrics. Econometrica 46(6), 1251-1271
       (testing an estimator against a consistent one from the same data).

    Examples
    --------
    >>> import numpy as np
    >>> from labkit.registration.agreement import disagreement_covariance
    >>> cov = np.diag([1e-4, 1e-4, 1e-5])  # 10, 10, 3.2 mm
    >>> scale, extra, T, k = disagreement_covariance([0.0, 0.06, 0.0], np.zeros(3), cov, cov)
    >>> round(T, 1), k, round(scale, 1), np.sqrt(np.diag(extra)).round(3).tolist()  # 60 mm at 14 mm std
    (18.0, 3, 6.0, [0.0, 0.055, 0.0])
    >>> scale, extra, T, k = disagreement_covariance([0.0, 0.03, 0.0], np.zeros(3), cov, cov)
    >>> round(T, 1), round(scale, 1), bool(extra.any())  # 2.1 combined std: scaled, no d d^T
    (4.5, 1.5, False)
    """
    d = np.asarray(refined, dtype=np.float64) - np.asarray(start, dtype=np.float64)
    C = np.asarray(cov_refined, dtype=np.float64) + np.asarray(cov_start, dtype=np.float64)
    both = np.isfinite(np.diag(C)) & np.isfinite(d)
    extra = np.zeros((3, 3))
    k = int(both.sum())
    if k == 0:
        return 1.0, extra, float("nan"), 0
    T, p = chi2_test(d[both], C[np.ix_(both, both)])
    if not np.isfinite(T):
        return 1.0, extra, float(T), k
    if p < alpha:
        db = np.where(both, d, 0.0)
        extra = (1.0 - k / T) * np.outer(db, db)
    return max(1.0, T / k), extra, float(T), k
