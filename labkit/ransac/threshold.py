"""The RANSAC inlier threshold t from the data: a multiple of the scanner's noise (notebook 02, eq. 26).

The noise is read from small neighbourhoods (k = 8 nearest points of a sample of at
most 4000): a neighbourhood spread over a surface (lambda_2 / lambda_1 >= 0.1) gives its
noise as sqrt(lambda_3), the spread off its best plane; a neighbourhood along one scan
line -- what a multi-beam scanner's sparse rings give, where all 8 neighbours lie on one
ring -- gives it as sqrt(lambda_2), the spread off its best line within the ring. The
noise sigma is the median over the sample, with the degrees of freedom of the fit
(the variance times (k - 1) / (k - 3) for a plane, (k - 1) / (k - 2) for a line), and
t = 3 sigma (a residual of a normal distribution passes with 99.7 %; Hartley and
Zisserman use 1.96 sigma per coordinate for 95 %), at least 1 mm (coordinates quantised to a grid give lambda = 0). Where the
noise exceeds the point spacing the neighbourhoods are blobs, not patches, and the
estimate is low: then give the threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..core.checks import as_points
from ..core.frame import local_origin, reduce

__all__ = ["ThresholdEstimate", "estimate_threshold"]

K = 8
SAMPLE = 4000
FACTOR = 3.0
FLOOR = 0.001  # m
PLANAR = 0.1  # lambda_2 / lambda_1 above this: a surface patch, not a scan line


@dataclass(frozen=True)
class ThresholdEstimate:
    """The inlier threshold and the noise it was made from (m).

    Examples
    --------
    >>> from labkit.ransac.threshold import ThresholdEstimate
    >>> ThresholdEstimate(0.021, 0.007, 0.6).text()
    'threshold 21 mm = 3 x noise 7.0 mm (median spread of 8-point neighbourhoods; 60 % along scan lines)'
    """

    threshold: float
    noise: float
    share_lines: float  # share of the neighbourhoods that lay along one scan line

    def text(self) -> str:
        return (f"threshold {1000 * self.threshold:.0f} mm = {FACTOR:g} x noise {1000 * self.noise:.1f} mm "
                f"(median spread of {K}-point neighbourhoods; {100 * self.share_lines:.0f} % along scan lines)")


def estimate_threshold(points, *, rng=0) -> ThresholdEstimate:
    """Estimate the RANSAC inlier threshold t = 3 sigma from the noise sigma of the cloud itself.

    Parameters
    ----------
    points : array_like (n, 3) or PointCloud
        The scan (metres), at least 9 points.
    rng : int or numpy.random.Generator
        For the sample of at most 4000 points.

    Returns
    -------
    ThresholdEstimate

    References
    ----------
    .. [1] Notebook 02, eqs. 25-26 (the inlier test d^2 < t^2 and the choice of t from sigma).
    .. [2] R. Hartley, A. Zisserman (2004): Multiple View Geometry in Computer Vision, 2nd ed.,
       Cambridge University Press, sec. 4.7.1 (the distance threshold t from the noise).

    Examples
    --------
    A plane with 2 mm noise: t is about 3 x 2 mm.

    >>> import numpy as np
    >>> from labkit.ransac.threshold import estimate_threshold
    >>> rng = np.random.default_rng(0)
    >>> xyz = np.c_[rng.uniform(0, 1, (5000, 2)), rng.normal(0, 0.002, 5000)]
    >>> est = estimate_threshold(xyz)
    >>> bool(0.005 < est.threshold < 0.007), round(est.share_lines, 1)
    (True, 0.0)
    """
    xyz = as_points(points, min_points=K + 1, name="points")
    xyz = reduce(xyz, local_origin(xyz))
    gen = np.random.default_rng(rng)
    sample = xyz[gen.choice(len(xyz), SAMPLE, replace=False)] if len(xyz) > SAMPLE else xyz
    _, idx = cKDTree(xyz).query(sample, k=K, workers=-1)
    nb = xyz[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    lam = np.clip(np.linalg.eigvalsh(np.einsum("mki,mkj->mij", centred, centred) / (K - 1)), 0.0, None)
    line = lam[:, 1] < PLANAR * lam[:, 2]
    # degrees of freedom: a plane takes 3 of the K points, a line within its ring 2
    spread = np.sqrt(np.where(line, lam[:, 1] * (K - 1) / (K - 2), lam[:, 0] * (K - 1) / (K - 3)))
    sigma = float(np.median(spread))
    return ThresholdEstimate(max(FACTOR * sigma, FLOOR), sigma, float(line.mean()))
