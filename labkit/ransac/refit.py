"""The final refit on the full cloud: robust inlier band, Gauss-Helmert adjustment, data snooping."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq

from ..sphere.ghm import adjust_sphere, check_sigma
from ..core.errors import LabkitError
from ._ball import band_median, gather, mark_shell, near_shell, residuals
from .config import BAND_K, SNOOP_ROUNDS, START_STEPS, S
from .hypotheses import orthogonal_fit, shell_mask


_SQRT_HALF = math.sqrt(0.5)


@dataclass(frozen=True)
class _Final:
    fit: object
    inliers: np.ndarray
    n_snooped: int
    sigma: float | None
    reason: str
    band: float = float("nan")


def refit_sphere(xyz, x0, cfg, X=None, shift=None, reader=None):
    """Final inliers from a robust band on the full cloud, Gauss-Helmert refit, then data snooping.

    ``X = xyz - shift[:3]`` are the points reduced to a local origin (default: xyz itself, shift 0), and
    x0 is a sphere in that frame: band, inliers and initial values are computed there (the compiled
    sums may reorder their terms, which costs digits only on UTM-sized numbers); the Gauss-Helmert
    refit adjusts the points xyz, and the result is in their frame. ``reader(x, reach)`` may answer
    :func:`~labkit.ransac._ball.near_shell` of X from points it holds already (default: a pass over X).

    The band |d| < k sigma_hat (k = 3) replaces the search threshold t: sigma_hat
    is the truncation-consistent MAD of the residuals inside the band (or the
    given sigma), band and sphere are iterated to a fixed point. Inliers cut
    at t ~ sigma would have residuals that understate sigma0 (and so every
    standard deviation) by a factor of up to 4-5. The refit is repeated (at
    most 3 times) only while more than 1 % of the inliers change with the
    adjusted sphere; the returned fit always belongs to exactly the returned inliers.
    """
    sigma, min_inliers = cfg.sigma, cfg.min_inliers
    X = np.ascontiguousarray(xyz if X is None else X, dtype=np.float64)
    shift = np.zeros(4) if shift is None else np.asarray(shift, dtype=np.float64)

    checked = np.zeros(len(xyz), dtype=bool)  # rows of a sigma array checked so far

    def adjust(mask, x_start, sig):  # xyz is checked; each row of sig is checked once, when first used
        if isinstance(sig, np.ndarray):
            new = mask & ~checked
            if new.any():
                check_sigma(sig[new], int(np.count_nonzero(new)))
                checked[new] = True
            sig = sig[mask]
        idx = np.flatnonzero(mask)  # (a gather by index beats a boolean row mask)
        if cfg.hold_radius is None:
            # start from the orthogonal-distance fit (compiled passes, reduced frame): for equal precisions it
            # is the adjustment's own solution, so the Gauss-Helmert iteration confirms it in one or two steps
            local = mask[near[2]]
            if np.count_nonzero(local) == len(idx):  # every inlier is a near point: sum over them in place
                x_start = _start(near[3], x_start - shift, mask=local) + shift
            else:
                x_start = _start(gather(X, idx, by_axis=True), x_start - shift) + shift
        pts = gather(xyz, idx) if xyz.flags.c_contiguous else np.take(xyz, idx, axis=0)
        return adjust_sphere(pts, x0=x_start, sigma=sig, radius=cfg.hold_radius, alpha_w=cfg.alpha)

    # Robust band and sphere at their fixed point (eqs. 25-26 with t -> k sigma_hat); with a
    # per-point sigma the band is k sigma_i for each point
    unit = _point_sigma(sigma)
    if reader is None:
        reader = lambda x, reach: near_shell(X, x[:3], x[3], reach)  # noqa: E731
    x0, band, sigma_hat, near = _robust_band(reader, x0, cfg, unit)
    if unit is not None:
        band = BAND_K * unit
    inliers = _band_mask(X, x0, band, near)
    x0 = x0 + shift  # the caller's frame
    if sigma is None:  # a priori sigma for the adjustment and the w-test: the robust scale
        sigma = sigma_hat
    fit = None
    for round_ in range(3):
        n_in = np.count_nonzero(inliers)
        if n_in < min_inliers:
            return _Final(None, inliers, 0, None, f"only {n_in} inliers (< min_inliers = {min_inliers})", band)
        try:
            if fit is None and not isinstance(sigma, np.ndarray):
                sigma = check_sigma(sigma, len(xyz))  # a scalar (or the robust scale): once
            fit = adjust(inliers, x0 if fit is None else fit.x, sigma)
        except LabkitError as exc:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit failed: {exc}", band)
        if not fit.converged:
            return _Final(None, inliers, 0, None, f"Gauss-Helmert refit did not converge: {fit.reason}", band)
        new = _band_mask(X, fit.x - shift, band, near)
        if np.count_nonzero(new != inliers) <= 0.01 * n_in or round_ == 2:
            break  # (the fit always belongs to exactly these inliers)
        inliers = new
    band = float(band) if np.ndim(band) == 0 else float(np.median(band))  # reported: the typical band
    if not cfg.snooping:
        return _Final(fit, inliers, 0, _sigma_scalar(sigma), "", band)
    return replace(_snoop(fit, inliers, sigma, min_inliers, adjust), band=band)


def _band_mask(xyz, x, band, near):
    """shell_mask(xyz, x, band), read from the points near the search's sphere where that is exact.

    ``near = (x_s, reach, idx, T)``: the points T = xyz[idx].T are all those with |d| < reach about
    x_s. A sphere x that moved by |c - c_s| + |r - r_s| < reach - band keeps every other point
    outside its band (|d| changes by at most that much), so only T needs the test.
    """
    x_s, reach, idx, T = near
    dc = x[:3] - x_s[:3]
    move = float(np.sqrt(dc.dot(dc)) + abs(x[3] - x_s[3]))  # (np.linalg.norm's sum, without its checks)
    if np.ndim(band) != 0 or not move < 0.999 * (reach - band):
        return shell_mask(xyz, x, band)
    return mark_shell(T, idx, x[:3], x[3], band, len(xyz))


def _start(T, x, steps=START_STEPS, mask=None):
    """Initial values for the Gauss-Helmert refit: Gauss-Newton steps of the orthogonal fit from x (x if it
    fails), on the points T by axis (3, m) (those with mask_i)."""
    x_ls = orthogonal_fit(T, x, steps=steps, mask=mask, by_axis=True)
    return x if x_ls is None else x_ls


def _point_sigma(sigma):
    """Per-point standard deviation (n,) for a per-point band, or None for a scalar / no sigma."""
    if sigma is None or np.ndim(sigma) == 0:
        return None
    s = np.asarray(sigma, dtype=np.float64)
    return s if s.ndim == 1 else np.sqrt(np.trace(s, axis1=1, axis2=2) / 3.0)


def _robust_band(reader, x, cfg, unit=None, max_rounds=12):
    """Fixed point of (band -> inliers -> orthogonal fit -> sigma_hat -> band = k sigma_hat), from t.

    Returns the sphere, the band half-width, sigma_hat and the points read (the search's sphere,
    the reach, their indices and coordinates: every point with |d| < reach). With an a priori
    sigma the band is k sigma at once (k sigma_i per point for ``unit``, the
    per-point sigma); only the sphere is iterated.
    """
    t = cfg.threshold
    known = cfg.sigma if cfg.sigma is not None and np.ndim(cfg.sigma) == 0 else None
    band = BAND_K * known if known is not None else t
    sigma_hat = known if known is not None else t / BAND_K
    # only points that can ever be in a band matter: a generous neighbourhood of the hypothesis
    reach = max(8.0 * t, 8.0 * band) if unit is None else max(8.0 * t, 3.0 * BAND_K * float(unit.max()))
    x_s = np.array(x, dtype=np.float64)
    near, d, T = reader(x, reach)  # the points with |d| < reach, by axis (3, k)
    if unit is not None:
        known, band = True, BAND_K * unit[near]
        sigma_hat = float(np.median(unit))
    for _ in range(max_rounds):
        inl = np.abs(d) < band
        if np.count_nonzero(inl) <= S:
            break
        x_new = orthogonal_fit(T, x, steps=2, mask=inl, by_axis=True)  # on the inliers, without gathering them
        x = x if x_new is None else x_new
        d = residuals(T, x, by_axis=True)
        if known is not None:  # band fixed by the given sigma: iterate the sphere until the inliers settle
            if np.array_equal(np.abs(d) < band, inl):
                break
            continue
        median, count = band_median(d, band)  # of the |d| inside the band, in two streaming passes
        if count <= S:
            break
        sigma_hat = scale_from_median(median, band)
        new_band = min(BAND_K * sigma_hat, 2.0 * band, reach)  # grow at most 2x per round
        converged = abs(new_band - band) <= 0.005 * band
        band = new_band
        if converged:
            break
    return x, (float(band) if np.ndim(band) == 0 else band), float(sigma_hat), (x_s, reach, near, T)


def truncated_mad_scale(abs_d, band):
    """sigma of N(0, sigma^2) whose |d|, truncated at ``band``, has the observed median.

    Solves (2 Phi(m / sigma) - 1) / (2 Phi(b / sigma) - 1) = 1/2 for sigma. A
    median of b/2 or more means no peak inside the band (flat): returns 2 b / k,
    which doubles the band.
    """
    median, count = band_median(abs_d, band)  # exact, without a partition of a copy
    if count != len(abs_d):  # (values at or beyond the band: numpy's median of all of them)
        median = float(np.median(abs_d))
    return scale_from_median(median, band)


def scale_from_median(m, band):
    """:func:`truncated_mad_scale` from the median m of the |d| inside the band."""
    q = m / band
    if q >= 0.499:
        return 2.0 * band / BAND_K
    if q <= 1e-9:
        return max(m, 1e-12)
    # 2 Phi(x) - 1 = erf(x / sqrt 2), on Python floats (a scipy ufunc per evaluation costs 20x more)
    g = lambda z: 2.0 * math.erf(q * z * _SQRT_HALF) - math.erf(z * _SQRT_HALF)  # noqa: E731  (z = b / sigma)
    hi = 1.0
    while g(hi) < 0 and hi < 1e6:
        hi *= 2.0
    z = brentq(g, 1e-6, hi, xtol=1e-10)
    return band / z


def _snoop(fit, inliers, sigma, min_inliers, adjust):
    """Data snooping: drop points whose |w| exceeds the critical value, refit, repeat."""
    n_removed = 0
    for _ in range(SNOOP_ROUNDS):
        flagged = fit.flagged  # |w_i| > critical value of level alpha (two-sided)
        if not flagged.any():
            break
        idx = np.flatnonzero(inliers)
        inliers = inliers.copy()
        inliers[idx[flagged]] = False
        n_removed += int(flagged.sum())
        if np.count_nonzero(inliers) < min_inliers:
            return _Final(None, inliers, n_removed, _sigma_scalar(sigma), "too few inliers left after data snooping")
        try:
            fit = adjust(inliers, fit.x, sigma)
        except LabkitError as exc:
            return _Final(None, inliers, n_removed, _sigma_scalar(sigma), f"refit after data snooping failed: {exc}")
    return _Final(fit, inliers, n_removed, _sigma_scalar(sigma), "")


def _sigma_scalar(sigma):
    return float(sigma) if np.ndim(sigma) == 0 else None
