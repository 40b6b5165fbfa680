"""The number of samples RANSAC needs: eq. (27) of the exercise sheet (notebook 02)."""

from __future__ import annotations

import math

import numpy as np

from ..core.checks import probability
from ..core.errors import LabkitError
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

    References
    ----------
    .. [1] Seed 000, section 2, eq. (27).
    .. [2] M. A. Fischler, R. C. Bolles (1981): Random sample consensus: a
       paradigm for model fitting with applications to image analysis and
       automated cartography. Communications of the ACM 24(6), 381-395,
       doi:10.1145/358669.358692.
    .. [3] R. Hartley, A. Zisserman (2004): Multiple View Geometry in Computer
       Vision, 2nd edition, Cambridge University Press, section 4.7.1 (the
       adaptive number of samples).

    Examples
    --------
    >>> from labkit.ransac import required_iterations
    >>> required_iterations(0.5), required_iterations(0.5, p=0.999), required_iterations(0.0)
    (72, 108, 1)
    >>> required_iterations([0.2, 0.8]).tolist()
    [9.0, 2876.0]
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


def required_for_ratio(eps, p, s=S):
    """:func:`required_iterations` for one outlier ratio eps in [0, 1] and a p checked already (the same N, on
    scalars: no checks, arrays or error states; the search asks after every new best)."""
    w_s = np.float64(1.0 - eps) ** int(s)
    if w_s <= 0:
        return math.inf
    if w_s >= 1:
        return 1
    N = max(np.ceil(np.log1p(-p) / np.log1p(-w_s) * (1 - 1e-12)), 1.0)  # (eq. 27)
    return math.inf if np.isinf(N) else int(N)


def required_from_probability(w, p):
    """N of eq. (27) written with the outlier-free sample probability w directly."""
    if w <= 0:
        return math.inf
    if w >= 1:
        return 1
    return max(1, int(np.ceil(np.log1p(-p) / np.log1p(-w) * (1 - 1e-12))))
