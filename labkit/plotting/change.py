"""Plots of M3C2 change (notebook 10, ``labkit change``).

Every helper takes an optional ``ax`` and returns it; none calls ``show()``.
Core points are drawn in a top view reduced to an origin rounded to 10 m, which the
axis labels name (``x - 194470 m``); colour limits are robust (quantiles of the cores).
"""

from __future__ import annotations

import numpy as np

from ..core.frame import local_origin
from ._style import CMAP_DIVERGING, CMAP_SEQUENTIAL, COLORS

NOT_SIGNIFICANT = "#c8c8c8"


def _axes(ax, **kw):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(**kw)
    return ax


def _top(points):
    """Points reduced to a rounded origin, and that origin (for the axis labels)."""
    xyz = np.asarray(points, dtype=float)
    o = np.round(local_origin(xyz), -1) if len(xyz) else np.zeros(3)
    return xyz - o, o


def _origin_labels(ax, o):
    """``x - 194470 m``: the unit and the origin the top view is reduced to."""
    ax.set_xlabel(f"x - {o[0]:.0f} m" if o[0] else "x (m)")
    ax.set_ylabel(f"y - {o[1]:.0f} m" if o[1] else "y (m)")


def _limit(values, quantile=0.98):
    v = np.abs(np.asarray(values)[np.isfinite(values)])
    a = float(np.quantile(v, quantile)) if v.size else 1.0
    return a if a > 0 else 1.0


def plot_change_map(result, *, ax=None, clim=None, s=12.0, title="significant change (m)", colorbar=True):
    """Top view of the core points: significant change coloured by the M3C2 distance, the rest grey.

    Cores without a distance (too few points in a cylinder) are drawn as small crosses.
    ``clim`` (a, b) defaults to symmetric limits at the 98 % quantile of the significant |distance|.
    """
    ax = _axes(ax, figsize=(7, 6), layout="constrained")
    xyz, o = _top(result.corepoints)
    xy = xyz[:, :2]
    sig, valid = result.significant, result.valid
    a = _limit(result.distance[sig] if sig.any() else result.distance)
    clim = (-a, a) if clim is None else clim
    ax.scatter(*xy[valid & ~sig].T, s=s, c=NOT_SIGNIFICANT, label=f"not significant ({int((valid & ~sig).sum())})")
    ax.scatter(*xy[~valid].T, s=0.6 * s, c=COLORS["rejected"], marker="x", label=f"no distance ({int((~valid).sum())})")
    sc = ax.scatter(*xy[sig].T, s=1.5 * s, c=result.distance[sig], cmap=CMAP_DIVERGING, vmin=clim[0], vmax=clim[1],
                    edgecolors="black", linewidths=0.5, label=f"significant ({int(sig.sum())})")
    if colorbar:
        ax.figure.colorbar(sc, ax=ax, label="M3C2 distance (m)", extend="both")
    ax.set_aspect("equal")
    _origin_labels(ax, o)
    ax.legend(loc="upper right", fontsize="small", markerscale=1.5)
    ax.set_title(title)
    return ax


def plot_lod_map(result, *, ax=None, s=12.0, title="level of detection (m)", colorbar=True):
    """Top view of the core points coloured by their level of detection (infinite LoD in red crosses)."""
    ax = _axes(ax, figsize=(7, 6), layout="constrained")
    xyz, o = _top(result.corepoints)
    xy = xyz[:, :2]
    finite = np.isfinite(result.lod)
    lo, hi = np.quantile(result.lod[finite], [0.02, 0.98]) if finite.any() else (0.0, 1.0)
    sc = ax.scatter(*xy[finite].T, s=s, c=result.lod[finite], cmap=CMAP_SEQUENTIAL, vmin=lo, vmax=max(hi, lo * 1.01))
    inf = np.isinf(result.lod)
    if inf.any():
        ax.scatter(*xy[inf].T, s=s, c=COLORS["outlier"], marker="x", label=f"LoD infinite ({int(inf.sum())})")
        ax.legend(loc="upper right", fontsize="small")
    if colorbar:
        ax.figure.colorbar(sc, ax=ax, label="LoD (m), 2-98 % of the cores", extend="both")
    ax.set_aspect("equal")
    _origin_labels(ax, o)
    ax.set_title(title)
    return ax


def plot_distance_vs_lod(result, *, ax=None, s=8.0, title="M3C2 distance against its level of detection"):
    """Scatter |distance| against LoD; points above the diagonal are significant change."""
    ax = _axes(ax, figsize=(6, 5), layout="constrained")
    ok = result.valid & np.isfinite(result.lod)
    sig = result.significant
    ax.scatter(result.lod[ok & ~sig], np.abs(result.distance[ok & ~sig]), s=s, c=NOT_SIGNIFICANT, label="not significant")
    ax.scatter(result.lod[ok & sig], np.abs(result.distance[ok & sig]), s=s, c=COLORS["outlier"], label="significant")
    top = float(max(np.nanmax(result.lod[ok]), np.nanmax(np.abs(result.distance[ok])))) if ok.any() else 1.0
    ax.plot([0, top], [0, top], color=COLORS["reference"], lw=1, label="|d| = LoD")
    ax.set_xlabel("level of detection (m)")
    ax.set_ylabel("|M3C2 distance| (m)")
    ax.legend(fontsize="small")
    ax.set_title(title)
    return ax


def plot_change_figure(result, title=""):
    """The two-panel figure of ``labkit change``: significant change and the level of detection."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.6), layout="constrained")
    plot_change_map(result, ax=axes[0])
    plot_lod_map(result, ax=axes[1])
    if title:
        fig.suptitle(title)
    return fig


def plot_registration_term(result, *, ax=None, s=8.0, title="registration term of the LoD against the slope"):
    """z sqrt(n^T Sigma_t n) (the LoD's registration part) against the slope of the surface (degrees).

    Flat ground (slope 0) feels only the vertical uncertainty of the registration, steep
    faces its horizontal uncertainty.
    """
    ax = _axes(ax, figsize=(6, 4.5), layout="constrained")
    ok = result.valid & np.isfinite(result.registration_variance)
    slope = np.degrees(np.arccos(np.clip(np.abs(result.normals[ok, 2]), 0, 1)))
    term = result.z[ok] * np.sqrt(result.registration_variance[ok])
    ax.scatter(slope, term, s=s, c=COLORS["source"], alpha=0.6, label="registration part")
    ax.scatter(slope, result.lod_without_registration[ok], s=0.5 * s, c=NOT_SIGNIFICANT,
               label="LoD without registration")
    ax.set_xlabel("slope of the surface (deg)")
    ax.set_ylabel("q sqrt(n^T Sigma_t n) (m)")
    ax.legend(fontsize="small")
    ax.set_title(title)
    return ax
