"""The number of samples RANSAC needs: eq. (27) of the seed."""

from __future__ import annotations

import math

import numpy as np

from .._checks import probability
from ..errors import LabkitError
from .config import S


def required_iterations(outlier_ratio, p=0.99, s=S):
    """Number of samples N for success probability ``p`` (eq. 27), rounded up.

    ``N = log(1 - p) / log(1 - (1 - eps)^s)``.

    Parameters
    ----------
    outlier_ratio : float or array_like
        eps = n_outliers / n, in [0, 1].
    p : float
        Probability that at least one sample is free of outliers, in (0, 1).
    s : int
        Sample size (4 for a sphere).

    Returns
    -------
    int or float or ndarray
        An int for a scalar ratio (``math.inf`` when eps = 1); a float array
        for array input.
    """
    eps = np.asarray(outlier_ratio, dtype=np.float64)
    if not np.all((eps >= 0) & (eps <= 1)):
        raise LabkitError(f"outlier_ratio must lie in [0, 1], got {outlier_ratio!r}")
    p = probability(p, "p")
    if isinstance(s, bool) or int(s) != s or s < 1:
        raise LabkitError(f"s must be a whole number >= 1, got {s!r}")
    w_s = (1.0 - eps) ** int(s)  # probability that one sample is outlier-free
    with np.errstate(divide="ignore", invalid="ignore"):
        N = np.log1p(-p) / np.log1p(-w_s)  # (eq. 27)
    N = np.where(w_s <= 0, np.inf, np.where(w_s >= 1, 1.0, np.ceil(N * (1 - 1e-12))))
    N = np.maximum(N, 1.0)
    if N.ndim == 0:
        return math.inf if np.isinf(N) else int(N)
    return N


def _required_from_probability(w, p):
    """N of eq. (27) written with the outlier-free sample probability w directly."""
    if w <= 0:
        return math.inf
    if w >= 1:
        return 1
    return max(1, int(np.ceil(np.log1p(-p) / np.log1p(-w) * (1 - 1e-12))))
