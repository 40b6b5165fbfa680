"""Tail probabilities and quantiles of the test distributions, without importing scipy.stats.

Each function is the :mod:`scipy.special` routine that ``scipy.stats`` itself calls for that
distribution (``scipy/stats/_continuous_distns.py``), so the numbers are the same to the last bit;
importing ``scipy.stats`` costs about a second, which the command line does not pay this way.
Arguments broadcast like NumPy; degrees of freedom must be positive; probabilities outside [0, 1] give NaN.

Examples
--------
>>> from labkit.core.distributions import chi2_ppf, chi2_sf, norm_ppf
>>> round(float(chi2_ppf(0.95, 3)), 4), round(float(chi2_sf(7.8147, 3)), 4), round(float(norm_ppf(0.975)), 4)
(7.8147, 0.05, 1.96)
"""

from __future__ import annotations

import numpy as np
from scipy.special import betaincc, chdtrc, chdtri, fdtrc, fdtri, gammaincinv, ndtr, ndtri, stdtrit


def chi2_sf(x, dof):
    """P(X > x) for X ~ chi2(dof): ``scipy.stats.chi2.sf(x, dof)``."""
    return chdtrc(dof, np.maximum(x, 0.0))  # 1 below the support


def chi2_isf(p, dof):
    """x with P(X > x) = p for X ~ chi2(dof): ``scipy.stats.chi2.isf(p, dof)``."""
    return chdtri(dof, p)


def chi2_ppf(p, dof):
    """x with P(X <= x) = p for X ~ chi2(dof): ``scipy.stats.chi2.ppf(p, dof)``."""
    return 2 * gammaincinv(np.asarray(dof) / 2, p)


def f_sf(x, dfn, dfd):
    """P(X > x) for X ~ F(dfn, dfd): ``scipy.stats.f.sf(x, dfn, dfd)``."""
    return fdtrc(dfn, dfd, np.maximum(x, 0.0))  # 1 below the support


def f_ppf(p, dfn, dfd):
    """x with P(X <= x) = p for X ~ F(dfn, dfd): ``scipy.stats.f.ppf(p, dfn, dfd)``."""
    return fdtri(dfn, dfd, p)


def t_ppf(p, dof):
    """x with P(X <= x) = p for Student's X ~ t(dof): ``scipy.stats.t.ppf(p, dof)``."""
    return np.where(np.asarray(p) == 0, -np.inf, stdtrit(dof, p))  # stdtrit(dof, 0) is +inf


def beta_sf(x, a, b):
    """P(X > x) for X ~ Beta(a, b): ``scipy.stats.beta.sf(x, a, b)``."""
    return betaincc(a, b, np.clip(x, 0.0, 1.0))  # 1 below the support, 0 above it


def norm_cdf(x):
    """P(X <= x) for X ~ N(0, 1): ``scipy.stats.norm.cdf(x)``."""
    return ndtr(x)


def norm_sf(x):
    """P(X > x) for X ~ N(0, 1): ``scipy.stats.norm.sf(x)``."""
    return ndtr(-np.asarray(x, dtype=np.float64))


def norm_ppf(p):
    """x with P(X <= x) = p for X ~ N(0, 1): ``scipy.stats.norm.ppf(p)``."""
    return ndtri(p)


def norm_isf(p):
    """x with P(X > x) = p for X ~ N(0, 1): ``scipy.stats.norm.isf(p)``."""
    return -ndtri(p)


def norm_pdf(x, scale=1.0):
    """Density of N(0, scale^2) at x: ``scipy.stats.norm.pdf(x, 0, scale)``."""
    z = np.asarray(x, dtype=np.float64) / scale
    return np.exp(-z**2 / 2.0) / np.sqrt(2 * np.pi) / scale
