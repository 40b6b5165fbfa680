"""Robust weights of ICP: iterative deletion (eq. 5.8) and Huber / Tukey IRLS weights (eq. 5.9).

Change the weighting of :func:`labkit.registration.icp` here: :func:`robust_weights` turns the
residuals of the current correspondences into kept rows and weight factors, :func:`psi_prime` is the
derivative of the influence function that the cluster-robust covariance (eq. 5.13) needs.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ...core.distributions import chi2_ppf, norm_sf
from ...core.order import median

HUBER_C, TUKEY_C = 1.345, 4.685  # 95 % efficiency under normal errors


@lru_cache(maxsize=64)
def deletion_limit(reject_sigma, r):
    """Limit on |u| of an r-component standardized residual: ``reject_sigma`` sigma, two-sided (eq. 5.8).

    Kept per (reject_sigma, r): the quantile costs microseconds a call, every iteration.
    """
    return np.sqrt(chi2_ppf(1 - 2 * norm_sf(reject_sigma), r))


@lru_cache(maxsize=8)
def _median_chi(r):
    """The median of the chi distribution with r degrees of freedom (kept per r)."""
    return np.sqrt(chi2_ppf(0.5, r))


def robust_weights(l, w, reject_sigma, robust):
    """Iterative deletion (eq. 5.8) and IRLS weights (eq. 5.9) from standardized residuals.

    Parameters
    ----------
    l : ndarray (m, r)
        Residual vectors (r = 1 point-to-plane, r = 3 point-to-point).
    w : ndarray (m,)
        A priori weights.
    reject_sigma : float or None
        Delete rows beyond this many robust standard deviations; None: keep all.
    robust : {None, 'huber', 'tukey'}

    Returns
    -------
    keep, factor, scale, u, centred
        Kept rows, weight factor per row (0 where deleted), robust scale of one component,
        standardized residual sizes and the centred standardized residuals.

    Examples
    --------
    >>> import numpy as np
    >>> l = np.array([[0.01], [-0.01], [0.0], [0.02], [-0.02], [1.0]])
    >>> keep, factor, scale, u, _ = robust_weights(l, np.ones(6), 3.0, "huber")
    >>> keep.tolist()
    [True, True, True, True, True, False]
    """
    e = np.sqrt(w)[:, None] * l
    centred = e - np.array([median(e[:, c]) for c in range(e.shape[1])])  # np.median(e, axis=0), the same numbers
    r = centred.shape[1]
    if r == 1:  # |e|: sqrt(e^2), as np.linalg.norm forms it, without its slow reduction over a single column
        size = np.sqrt(centred[:, 0] * centred[:, 0])
    else:
        size = np.linalg.norm(centred, axis=1)
    # robust scale of one component: MAD (r = 1) or the median of a chi distribution (r = 3)
    scale = median(size) / _median_chi(r)
    scale = max(scale, 1e-12)
    u = size / scale
    keep = np.ones(len(u), dtype=bool)
    if reject_sigma is not None:
        keep = u <= deletion_limit(reject_sigma, r)  # k sigma, two-sided, r components
    if robust == "huber":
        factor = np.minimum(1.0, HUBER_C / np.maximum(u, 1e-12))
    elif robust == "tukey":
        factor = np.where(u < TUKEY_C, (1 - (u / TUKEY_C) ** 2) ** 2, 0.0)
    else:
        factor = np.ones(len(u))
    return keep, factor * keep, scale, u, centred


def psi_prime(u, robust):
    """Derivative of the influence function psi(u) = u * factor(u) (Huber 1981)."""
    if robust == "huber":
        return (u <= HUBER_C).astype(np.float64)
    if robust == "tukey":
        q = (u / TUKEY_C) ** 2
        return np.where(u < TUKEY_C, (1 - q) * (1 - 5 * q), 0.0)
    return np.ones_like(u)
